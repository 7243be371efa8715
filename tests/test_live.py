"""benchmarks/live.py: a sequence as a live camera, repeated, against one offline run."""

import json

import pytest
from repo import benchmark, usage_error

from dimslam.common.cli import main as dimslam


@pytest.fixture
def live(monkeypatch):
    return benchmark(monkeypatch, "live")


def test_live_runs_beside_the_offline_run_resume_and_refuse_other_settings(
    live, tmp_path, monkeypatch, capsys
):
    scene = tmp_path / "scene"
    assert dimslam(["synth", str(scene), "--frames", "24", "--size", "160x120"]) == 0
    out, figures = tmp_path / "out", tmp_path / "figures.json"
    argv = ["live.py", str(scene), "--out", str(out), "--preset", "tiny", "--repeats", "1",
            "--set", "mapper.live_iters=2", "--json", str(figures)]  # fmt: skip
    monkeypatch.setattr("sys.argv", argv)
    assert live.main() == 0
    offline = json.loads((out / "offline" / "config.json").read_text())
    assert "realtime_fps" not in offline and offline["mapper"]["live_iters"] == 2
    assert json.loads((out / "live_0" / "config.json").read_text())["realtime_fps"] == 10
    report = json.loads(figures.read_text())
    (run,) = report["runs"]
    assert 0 < run["tracked"] <= 24 and run["rounds"] >= 2
    summary = report["summary"]
    assert summary["ate_m_median"] == run["ate_m"]
    assert summary["ate_ratio"] == pytest.approx(run["ate_m"] / report["offline"]["ate_m"])
    printed = capsys.readouterr().out
    assert "| live 0 |" in printed and "live / offline: " in printed, printed

    # Again with one more repeat: only the new live run runs.
    stamp = (out / "live_0" / "metrics.json").stat().st_mtime_ns
    monkeypatch.setattr("sys.argv", [*argv[:7], "2", *argv[8:]])
    assert live.main() == 0
    assert (out / "live_0" / "metrics.json").stat().st_mtime_ns == stamp
    assert len(json.loads(figures.read_text())["runs"]) == 2

    # The same folder at another rate would mix two benchmarks.
    said = usage_error(monkeypatch, capsys, live.main, [*argv, "--fps", "30"])
    assert "holds runs of other settings" in said
    # So would runs on another device.
    said = usage_error(monkeypatch, capsys, live.main, [*argv, "--device", "cuda:0"])
    assert "holds runs of other settings" in said


def test_bad_arguments_are_refused_before_anything_runs(live, tmp_path, monkeypatch, capsys):
    out = tmp_path / "out"
    for args, said in (
        ([str(tmp_path / "nowhere")], "no dataset folder"),
        ([str(tmp_path), "--repeats", "0"], "--repeats at least 1"),
        ([str(tmp_path), "--set", "mapper.no_such=1"], "unknown setting"),
    ):
        argv = ["live.py", *args, "--out", str(out)]
        assert said in usage_error(monkeypatch, capsys, live.main, argv)
    assert not out.exists()

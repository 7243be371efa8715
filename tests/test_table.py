"""benchmarks/table.py: the development table for one preset and settings."""

import json

import pytest
from repo import benchmark, usage_error

from dimslam.common.io.synth import write_sequence


@pytest.fixture
def table(monkeypatch):
    return benchmark(monkeypatch, "table")


def test_a_table_runs_with_its_settings_resumes_and_refuses_other_settings(
    table, tmp_path, monkeypatch, capsys
):
    scene = tmp_path / "scene"
    write_sequence(scene, frames=16, width=160, height=120, seed=0)
    out, figures = tmp_path / "out", tmp_path / "figures.json"
    argv = ["table.py", "--out", str(out), "--datasets", str(scene), "--seeds", "0",
            "--preset", "tiny", "--set", "tracker.iters=7", "--json", str(figures)]  # fmt: skip
    monkeypatch.setattr("sys.argv", argv)
    assert table.main() == 0
    run = out / "scene_st1_s0"
    assert json.loads((run / "config.json").read_text())["tracker"]["iters"] == 7
    first = json.loads(figures.read_text())
    cell = first["results"][str(scene)]["1"]
    assert cell["mean_m"] == cell["seeds"]["0"]["ate_m"] < 0.1, cell
    assert first["set"] == {"tracker.iters": "7"}
    capsys.readouterr()

    # Again, against itself: nothing run, the same figures, a ratio of one.
    stamp = (run / "metrics.json").stat().st_mtime_ns
    monkeypatch.setattr("sys.argv", [*argv, "--against", str(out)])
    assert table.main() == 0
    assert (run / "metrics.json").stat().st_mtime_ns == stamp
    printed = capsys.readouterr().out
    assert "| scene | 1 |" in printed and "| 1.00x |" in printed, printed

    # The same folder with other settings would mix two tables.
    other = [*argv[:-4], "--set", "tracker.iters=8"]
    said = usage_error(monkeypatch, capsys, table.main, other)
    assert "holds runs of other settings" in said


def test_settings_are_checked_before_anything_runs(table, tmp_path, monkeypatch, capsys):
    out = tmp_path / "out"
    for bad, said in (
        ("render.normalize_floor", "want KEY=VALUE"),
        ("render.no_such=1", "unknown setting"),
        ("tracker.iters=many", "cannot use"),
    ):
        argv = ["table.py", "--out", str(out), "--datasets", str(tmp_path), "--set", bad]
        assert said in usage_error(monkeypatch, capsys, table.main, argv)
    assert not out.exists()

"""benchmarks/branch.py: one run up to a frame, then the rest once per tracker variant."""

import argparse
import json

import pytest
from repo import benchmark, usage_error

from dimslam.common.io.synth import write_sequence


@pytest.fixture
def branch(monkeypatch):
    return benchmark(monkeypatch, "branch")


def test_branches_from_one_state_repeat_exactly_and_a_variant_changes_the_rest(
    branch, tmp_path, monkeypatch, capsys
):
    scene = tmp_path / "scene"
    write_sequence(scene, frames=18, width=160, height=120, seed=0)
    figures = tmp_path / "figures.json"
    argv = ["branch.py", str(scene), "--preset", "tiny", "--at", "12", "--out", str(tmp_path)]
    # The colour variant compares colours where the run compared grey: its references are
    # rendered anew. A branch's pyramid may be shorter than the run's, not taller.
    variants = [
        "",
        "",
        "tracker.solver=adam;loss.patch_sizes=1",
        "tracker.colour=true",
        "tracker.levels=1",
        "tracker.levels=9",
        "mapper.refine_keyframes=5;mapper.refine_apart_deg=180",
    ]
    monkeypatch.setattr(
        "sys.argv", [*argv, *(f"--variant={v}" for v in variants), "--json", str(figures)]
    )
    branch.main()
    results = json.loads(figures.read_text())["results"]
    assert [r["variant"] for r in results] == variants
    assert not any(r.get("failed") for r in results[:5]) and results[5]["failed"], results
    # Two children of one state, with nothing changed, are one computation.
    assert results[0] == results[1]
    # Keyframes refined but none replaced: the refinement's own pixel draws leave the run as
    # it was.
    assert {**results[6], "variant": ""} == results[0]
    # Another solver from frame 12 on: the last 6 poses differ, the first 12 do not.
    ours, theirs = (
        [ln.split() for ln in (tmp_path / k / "trajectory.txt").read_text().splitlines()[1:]]
        for k in ("0", "2")
    )
    assert ours[:12] == theirs[:12] and ours[12:] != theirs[12:]
    assert results[2]["lost"] == 0 and results[2]["ate_cm"] < 10.0, results[2]
    assert results[4] != results[0] and results[4]["ate_cm"] < 10.0, results[4]
    out = capsys.readouterr().out
    assert "[2] tracker.solver=adam;loss.patch_sizes=1" in out, out


def test_a_variant_outside_the_tracking_side_is_refused(branch):
    assert branch.parse_variant("tracker.huber=0.01; loss.min_views=2") == {
        "tracker.huber": "0.01",
        "loss.min_views": "2",
    }
    with pytest.raises(argparse.ArgumentTypeError, match="KEY=VALUE"):
        branch.parse_variant("tracker.huber")
    for bad in ("mapper.iters=5", "seed=1"):
        with pytest.raises(argparse.ArgumentTypeError, match="only keys in"):
            branch.parse_variant(bad)


def test_a_bad_variant_is_a_usage_error_before_anything_runs(branch, tmp_path, monkeypatch, capsys):
    out = tmp_path / "out"
    for bad, said in (
        ("tracker.huber", "want KEY=VALUE"),
        ("mapper.iters=5", "only keys in"),
        ("tracker.iters=many", "cannot use"),
    ):
        argv = ["branch.py", str(tmp_path / "no_sequence"), "--at", "5", "--out", str(out)]
        argv += ["--variant", "", "--variant", bad]
        assert said in usage_error(monkeypatch, capsys, branch.main, argv)
    assert not out.exists()


def test_the_truth_check_prints_each_frame_and_leaves_the_run_as_it_was(
    branch, tmp_path, monkeypatch, capfd
):
    scene = tmp_path / "scene"
    write_sequence(scene, frames=18, width=160, height=120, seed=0)
    runs = []
    for flags in ([], ["--truth"]):
        figures = tmp_path / f"figures{len(flags)}.json"
        monkeypatch.setattr(
            "sys.argv",
            ["branch.py", str(scene), "--preset", "tiny", "--at", "12", "--variant=",
             "--variant=tracker.solver=adam", "--out", str(tmp_path / str(len(flags))),
             "--json", str(figures), *flags],
        )  # fmt: skip
        branch.main()
        runs.append(json.loads(figures.read_text())["results"])
    assert runs[0] == runs[1]  # the checks draw no random numbers of the run's
    # The children print it: capfd, not capsys, sees what a forked process writes.
    out = capfd.readouterr().out.splitlines()
    direct = [ln for ln in out if "at the solution" in ln]
    adam = [ln for ln in out if "a direct solve from it ends" in ln]
    assert len(direct) >= 5 and len(adam) >= 5, out  # frames 12-17, but for a frame lost
    # On an exact synthetic scene a solve from the true pose ends where the run's did, and
    # a direct solve from the Adam tracker's pose ends near it.
    for line in direct:
        apart = float(line.split(" from it, ")[1].split(" cm")[0])
        assert apart < 2.0, line
    for line in adam:
        apart = float(line.split(" ends ")[1].split(" cm")[0])
        assert apart < 3.0, line

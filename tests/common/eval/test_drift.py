"""Segment drift: a path whose second half is scaled is found out segment by segment, and every
evaluation against ground truth (`dimslam eval`, a run's metrics.json) carries the spread."""

import json
import math
import re

import numpy as np
import pytest
from repo import benchmark

from dimslam.common.eval.drift import (
    frame_steps,
    scale_spread,
    segment_drift,
    segment_scale_spread,
)
from dimslam.common.eval.report import evaluate_files, format_metrics, report_run
from dimslam.common.io.synth import write_sequence
from dimslam.common.io.trajectory import Trajectory, read_tum, write_tum

SPREAD_LINE = re.compile(r"^segment scale spread +(\S+) %$", re.MULTILINE)


def helix(n: int) -> Trajectory:
    t = np.arange(n) / 30.0
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = np.cos(t * 2)
    poses[:, 1, 3] = np.sin(t * 2)
    poses[:, 2, 3] = 0.3 * t
    return Trajectory(t, poses)


def scaled_second_half(gt: Trajectory) -> Trajectory:
    """`gt` whose every step from its middle pose on is 20 % longer: the second half's scale is
    1.2 x the first's."""
    half = len(gt) // 2
    poses = gt.poses.copy()
    steps = np.diff(gt.poses[:, :3, 3], axis=0)
    steps[half - 1 :] *= 1.2
    poses[1:, :3, 3] = gt.poses[0, :3, 3] + np.cumsum(steps, axis=0)
    return Trajectory(gt.timestamps, poses)


def test_a_scaled_second_half_shows_as_scale_spread():
    gt = helix(120)
    whole, rows = segment_drift(scaled_second_half(gt), gt, 30)
    assert [(r.first, r.last) for r in rows] == [(0, 29), (30, 59), (60, 89), (90, 119)]
    assert all(r.local_ate_m < 1e-6 for r in rows)  # each segment is exact in itself
    scales = [r.local_scale for r in rows]
    assert scales[1] / scales[2] == pytest.approx(1.2, rel=1e-6)
    assert scale_spread(rows) == pytest.approx(0.2, rel=1e-6)
    assert whole.ate_rmse_m > 0.01
    shares = [r.share for r in rows]  # 120 poses in 4 segments: the whole error is theirs
    assert sum(shares) == pytest.approx(1.0, rel=1e-9)
    n = len(whole.errors_m)
    assert shares[0] == pytest.approx(np.sum(whole.errors_m[:30] ** 2) / n / whole.ate_rmse_m**2)
    # one alignment of a path bent in scale fits its middle and leaves both ends off
    assert min(shares[0], shares[3]) > 0.25 > max(shares[1], shares[2])


def test_steps_show_where_an_estimate_moves_back_while_turning_too_far():
    gt = helix(120)
    poses = gt.poses.copy()
    for i in range(100, 120):  # from pose 100 on: each step reversed, with a 3-degree turn
        step = gt.poses[i, :3, 3] - gt.poses[i - 1, :3, 3]
        poses[i, :3, 3] = poses[i - 1, :3, 3] - step
        c, s = math.cos(math.radians(3 * (i - 99))), math.sin(math.radians(3 * (i - 99)))
        poses[i, :3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    steps = frame_steps(Trajectory(gt.timestamps, poses), gt, 98, 130)
    assert [m.index for m in steps] == list(range(98, 120))  # clipped to the path
    before, after = steps[:2], steps[2:]
    assert all(m.cos > 0.9 and m.est_deg < 1e-3 for m in before)
    assert all(m.cos < -0.9 for m in after)
    assert all(m.est_deg == pytest.approx(3.0, abs=1e-3) and m.gt_deg < 1e-3 for m in after)
    assert after[-1].err_m > after[0].err_m


def test_an_exact_copy_has_no_spread_and_short_paths_have_none():
    gt = helix(90)
    _, rows = segment_drift(gt, gt, 30)
    assert scale_spread(rows) == pytest.approx(0.0, abs=1e-9)
    assert math.isnan(scale_spread(rows[:1]))
    with pytest.raises(ValueError, match="at least 3"):
        segment_drift(gt, gt, 2)


def evaluated(tmp_path, est: Trajectory, gt: Trajectory) -> dict:
    """`dimslam eval`'s figures for `est` against `gt`, both written as TUM files."""
    write_tum(tmp_path / "est.txt", est)
    write_tum(tmp_path / "gt.txt", gt)
    return evaluate_files(tmp_path / "est.txt", str(tmp_path / "gt.txt"))


@pytest.mark.parametrize(("scaled", "spread"), [(False, 0.0), (True, 0.2)])
def test_the_evaluation_reports_the_spread(tmp_path, scaled, spread):
    gt = helix(120)
    figures = evaluated(tmp_path, scaled_second_half(gt) if scaled else gt, gt)
    assert figures["segment_scale_spread"] == pytest.approx(spread, abs=1e-5)
    assert SPREAD_LINE.findall(format_metrics(figures)) == [f"{100 * spread:.1f}"]


def test_a_path_too_short_for_two_segments_has_no_spread(tmp_path):
    gt = helix(59)  # one segment of 30 poses and a remainder
    figures = evaluated(tmp_path, gt, gt)
    assert figures["segment_scale_spread"] is None
    assert figures["ate_rmse_m"] < 1e-6
    assert not SPREAD_LINE.search(format_metrics(figures))


def test_a_segment_without_its_own_alignment_has_no_spread():
    gt = helix(90)
    poses = gt.poses.copy()
    poses[30:60, :3, 3] = poses[30, :3, 3]  # the estimate stands still through segment 2
    assert segment_scale_spread(Trajectory(gt.timestamps, poses), gt) is None


@pytest.mark.parametrize("frames", [60, 40])
def test_a_runs_metrics_carry_the_spread(tmp_path, capsys, frames):
    scene, out = tmp_path / "scene", tmp_path / "run"
    write_sequence(scene, frames=frames, width=32, height=24, seed=3)
    out.mkdir()
    write_tum(out / "trajectory.txt", scaled_second_half(read_tum(scene / "groundtruth.txt")))
    report_run(str(scene), out, None, None, seconds=1.0, frames=frames)
    spread = json.loads((out / "metrics.json").read_text())["segment_scale_spread"]
    printed = SPREAD_LINE.findall(capsys.readouterr().out)
    if frames < 60:  # one segment: no spread, and no line for it
        assert spread is None and printed == []
    else:
        assert spread == pytest.approx(0.2, rel=1e-3) and printed == ["20.0"]


def test_the_benchmark_tells_steps_that_jump_onto_keyframes(monkeypatch, capsys):
    """A path whose every third step (onto a keyframe) is 50 % too long shows it on the steps
    onto keyframes and not on the others."""
    drift = benchmark(monkeypatch, "drift")
    gt = helix(90)
    steps = np.diff(gt.poses[:, :3, 3], axis=0)
    steps[2::3] *= 1.5  # the steps onto poses 3, 6, 9, ...
    poses = gt.poses.copy()
    poses[1:, :3, 3] = gt.poses[0, :3, 3] + np.cumsum(steps, axis=0)
    est = Trajectory(gt.timestamps, poses)
    keyframes = Trajectory(gt.timestamps[::3], poses[::3])
    figures = drift.keyframe_steps(est, gt, keyframes)
    onto, between = figures["onto keyframes"], figures["between"]
    assert (onto["steps"], between["steps"]) == (29, 60)
    # under the one alignment's scale the long steps come out long and the others short,
    # 1.5 times as long as each other
    assert (1 + onto["median"]) / (1 - between["median"]) == pytest.approx(1.5, rel=1e-6)
    assert onto["p90"] == pytest.approx(onto["median"], rel=1e-6)
    assert "step length error onto keyframes" in capsys.readouterr().out
    # Poses the ground truth lacks are no steps' ends: the steps are those of matched poses.
    partial = Trajectory(gt.timestamps[1:], gt.poses[1:])
    figures = drift.keyframe_steps(est, partial, keyframes)
    assert (figures["onto keyframes"]["steps"], figures["between"]["steps"]) == (29, 59)
    onto, between = figures["onto keyframes"], figures["between"]
    assert (1 + onto["median"]) / (1 - between["median"]) == pytest.approx(1.5, rel=1e-6)

"""Segment drift: a path whose second half is scaled is found out segment by segment."""

import math

import numpy as np
import pytest

from dimslam.common.eval.drift import scale_spread, segment_drift
from dimslam.common.io.trajectory import Trajectory


def helix(n: int) -> Trajectory:
    t = np.arange(n) / 30.0
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = np.cos(t * 2)
    poses[:, 1, 3] = np.sin(t * 2)
    poses[:, 2, 3] = 0.3 * t
    return Trajectory(t, poses)


def test_a_scaled_second_half_shows_as_scale_spread():
    gt = helix(120)
    est_poses = gt.poses.copy()
    # From pose 60 on, every step is 20 % longer: the second half's scale is 1.2 x the first's.
    steps = np.diff(gt.poses[:, :3, 3], axis=0)
    steps[59:] *= 1.2
    est_poses[1:, :3, 3] = gt.poses[0, :3, 3] + np.cumsum(steps, axis=0)
    whole, rows = segment_drift(Trajectory(gt.timestamps, est_poses), gt, 30)
    assert [(r.first, r.last) for r in rows] == [(0, 29), (30, 59), (60, 89), (90, 119)]
    assert all(r.local_ate_m < 1e-6 for r in rows)  # each segment is exact in itself
    scales = [r.local_scale for r in rows]
    assert scales[1] / scales[2] == pytest.approx(1.2, rel=1e-6)
    assert scale_spread(rows) == pytest.approx(0.2, rel=1e-6)
    assert whole.ate_rmse_m > 0.01


def test_an_exact_copy_has_no_spread_and_short_paths_have_none():
    gt = helix(90)
    _, rows = segment_drift(gt, gt, 30)
    assert scale_spread(rows) == pytest.approx(0.0, abs=1e-9)
    assert math.isnan(scale_spread(rows[:1]))
    with pytest.raises(ValueError, match="at least 3"):
        segment_drift(gt, gt, 2)

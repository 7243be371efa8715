"""Where along the path an estimate's error comes from: local accuracy and local scale.

The whole trajectory is aligned once (Sim(3), as the ATE is); then the matched poses are cut
into consecutive segments of `length` and each is aligned on its own. A small local ATE with a
large global error, and local scales away from 1, say the error is scale drift between
segments rather than tracking noise within them. `benchmarks/drift.py` prints the table; every
run's metrics carry the spread of the segments' scales.
"""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass
from typing import Literal

import numpy as np
import torch

from dimslam.common.errors import EvaluationError
from dimslam.common.eval.evaluation import (
    MIN_MATCHES,
    TrajectoryMetrics,
    associate,
    evaluate_trajectory,
    umeyama,
)
from dimslam.common.geometry import pose
from dimslam.common.io.trajectory import Trajectory

log = logging.getLogger(__name__)

SEGMENT = 30
"""Matched poses per segment by default: a second of video at 30 frames/s."""


@dataclass(frozen=True)
class Segment:
    """One segment of the path, in ground-truth units.

    Attributes:
        first, last: indices of its first and last matched pose.
        global_err_m: mean error of its poses under the whole trajectory's alignment.
        share: its poses' part of the whole trajectory's summed squared error (the ATE's
            square times the poses): how much of the ATE the segment makes.
        local_ate_m: RMSE after its own Sim(3) alignment.
        local_scale: its own alignment's scale relative to the whole one's (1: no drift).
        path_m: ground-truth distance travelled within it.
        turn_deg: ground-truth rotation between its first and last pose.
    """

    first: int
    last: int
    global_err_m: float
    share: float
    local_ate_m: float
    local_scale: float
    path_m: float
    turn_deg: float

    def to_dict(self) -> dict:
        return asdict(self)


def segment_drift(
    est: Trajectory,
    gt: Trajectory,
    length: int = SEGMENT,
    *,
    align: Literal["sim3", "se3"] = "sim3",
    max_dt: float = 0.02,
) -> tuple[TrajectoryMetrics, list[Segment]]:
    """The whole trajectory's metrics and its segments of `length` matched poses.

    `align` and `max_dt` are `evaluate_trajectory`'s: the whole alignment and the association.

    Raises:
        ValueError: `length` below 3 (a Sim(3) needs 3 points).
        EvaluationError: the trajectories cannot be compared (see `evaluate_trajectory`), or a
            segment's own alignment is undefined (see `umeyama`: e.g. its estimate stands still).
    """
    if length < MIN_MATCHES:
        raise ValueError(f"segments need at least {MIN_MATCHES} poses, got {length}")
    whole, E, G, _ = _aligned(est, gt, align, max_dt)
    squared = whole.errors_m**2
    rows = []
    for a in range(0, len(E) - length + 1, length):
        e, g = E[a : a + length, :3, 3], G[a : a + length, :3, 3]
        local = umeyama(e, g)
        err = np.linalg.norm(local.apply_points(e) - g, axis=1)
        turn = G[a, :3, :3].T @ G[a + length - 1, :3, :3]
        rows.append(
            Segment(
                first=a,
                last=a + length - 1,
                global_err_m=float(whole.errors_m[a : a + length].mean()),
                share=float(squared[a : a + length].sum() / max(squared.sum(), 1e-30)),
                local_ate_m=float(np.sqrt(np.mean(err**2))),
                local_scale=float(local.s),
                path_m=float(np.linalg.norm(np.diff(g, axis=0), axis=1).sum()),
                turn_deg=math.degrees(pose.rotation_angle(torch.from_numpy(turn)).item()),
            )
        )
    return whole, rows


def _aligned(
    est: Trajectory, gt: Trajectory, align: Literal["sim3", "se3"], max_dt: float
) -> tuple[TrajectoryMetrics, np.ndarray, np.ndarray, np.ndarray]:
    """The whole trajectory's metrics, and the matched poses: the estimate's under its
    alignment, the ground truth's, and the estimate's timestamps of them."""
    whole = evaluate_trajectory(est, gt, align=align, max_dt=max_dt)
    idx_est, idx_gt = associate(est.timestamps, gt.timestamps, max_dt)  # as evaluate_trajectory
    E = whole.alignment.apply_poses(est.poses[idx_est])
    return whole, E, gt.poses[idx_gt], est.timestamps[idx_est]


@dataclass(frozen=True)
class Step:
    """The motion from one matched pose to the next, estimate against ground truth.

    Attributes:
        index: the matched pose the step ends at.
        timestamp: that pose's timestamp in the estimate.
        err_m: that pose's error under the whole trajectory's alignment.
        est_m, gt_m: distance moved (estimate after the alignment, ground truth).
        cos: cosine between the two moves' directions (-1: the estimate went back).
        est_deg, gt_deg: rotation turned.
    """

    index: int
    timestamp: float
    err_m: float
    est_m: float
    gt_m: float
    cos: float
    est_deg: float
    gt_deg: float

    def to_dict(self) -> dict:
        return asdict(self)


def frame_steps(
    est: Trajectory, gt: Trajectory, first: int, last: int, *, max_dt: float = 0.02
) -> list[Step]:
    """Frame-to-frame motion of matched poses `first`..`last` (both included) under the whole
    trajectory's Sim(3): where a tracker turned too far or moved the wrong way."""
    whole, E, G, stamps = _aligned(est, gt, "sim3", max_dt)
    rows = []
    for i in range(max(first, 1), min(last, len(E) - 1) + 1):
        de, dg = E[i, :3, 3] - E[i - 1, :3, 3], G[i, :3, 3] - G[i - 1, :3, 3]
        norms = float(np.linalg.norm(de) * np.linalg.norm(dg))
        turns = [
            math.degrees(pose.rotation_angle(torch.from_numpy(T[i - 1, :3, :3].T @ T[i, :3, :3])))
            for T in (E, G)
        ]
        rows.append(
            Step(
                index=i,
                timestamp=float(stamps[i]),
                err_m=float(whole.errors_m[i]),
                est_m=float(np.linalg.norm(de)),
                gt_m=float(np.linalg.norm(dg)),
                cos=float(de @ dg) / norms if norms > 0 else math.nan,
                est_deg=turns[0],
                gt_deg=turns[1],
            )
        )
    return rows


def scale_spread(segments: list[Segment]) -> float:
    """How far the segments' scales disagree: largest over smallest, minus 1 (0.05: 5 %);
    NaN with fewer than two segments."""
    if len(segments) < 2:
        return math.nan
    scales = [s.local_scale for s in segments]
    return max(scales) / min(scales) - 1.0


def segment_scale_spread(
    est: Trajectory,
    gt: Trajectory,
    *,
    align: Literal["sim3", "se3"] = "sim3",
    max_dt: float = 0.02,
) -> float | None:
    """`scale_spread` of the `SEGMENT`-pose segments, as a run's metrics carry it: None where it
    is undefined (fewer than two segments, or a segment whose own alignment is undefined)."""
    try:
        _, segments = segment_drift(est, gt, align=align, max_dt=max_dt)
    except EvaluationError as e:
        log.warning("segment scale spread undefined: %s", e)
        return None
    spread = scale_spread(segments)
    return None if math.isnan(spread) else spread

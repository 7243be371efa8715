"""The project's own evaluator: what every accuracy figure in dimslam means (design.md section 6).

Trajectories:
    Estimated and ground-truth poses are associated one-to-one by nearest timestamp
    (`associate`), the estimate is aligned to the ground truth by the least-squares Sim(3)
    (`umeyama`, with scale; or SE(3)), and the absolute trajectory error (ATE) is the RMSE of the
    camera centres in ground-truth units. The relative pose error (RPE) compares consecutive
    matched pairs of the aligned estimate with the ground truth.

Meshes: `mesh_metrics.py`.

Meshes (the protocol):
    The trajectory's alignment (estimate -> ground truth) is applied to the estimated mesh; both
    surfaces are culled to the ground-truth camera frustums; `samples` points are drawn on each;
    accuracy is the mean distance estimate -> GT, completion the mean distance
    GT -> estimate, completion ratio the percentage of GT points within `threshold_m` of the
    estimate. Reported in cm.

    Distances are between sampled points, as in the paper's protocol, so two different samplings
    of one surface are about half a sample spacing apart, `0.5 / sqrt(samples / area)` (about
    1 cm for a 100 m^2 room at 200,000 samples): that is the resolution of the figures. Both
    meshes are sampled with the same seed, so a mesh compared with itself scores exactly 0.
    Compare figures only at equal `samples`.

Plotting lives in `plot.py` and is never imported from here.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from dimslam.common.errors import EvaluationError
from dimslam.common.geometry import pose
from dimslam.common.geometry.shapes import check_shape
from dimslam.common.io.trajectory import Trajectory

log = logging.getLogger(__name__)

MIN_MATCHES = 3
"""Fewest associated poses that define a Sim(3) alignment (3 non-collinear points)."""


# eq=False on the classes holding arrays: the generated __eq__ would compare arrays and raise.
@dataclass(frozen=True, eq=False)
class Sim3:
    """A similarity transform `p -> s R p + t`, float64.

    Attributes:
        s: scale, > 0 (1 for an SE(3) alignment).
        R: `(3, 3)` rotation.
        t: `(3,)` translation.
    """

    s: float
    R: np.ndarray
    t: np.ndarray

    def __post_init__(self) -> None:
        # Frozen dataclass: normalise types through object.__setattr__ once, at construction.
        object.__setattr__(self, "s", float(self.s))
        object.__setattr__(self, "R", np.array(self.R, dtype=np.float64))
        object.__setattr__(self, "t", np.array(self.t, dtype=np.float64))
        check_shape("R", self.R, (3, 3))
        check_shape("t", self.t, (3,))
        if not (np.isfinite(self.s) and self.s > 0):
            raise ValueError(f"Sim3 scale must be positive and finite, got {self.s}")
        if not (np.all(np.isfinite(self.R)) and np.all(np.isfinite(self.t))):
            raise ValueError("Sim3 rotation and translation must be finite")

    @classmethod
    def identity(cls) -> Sim3:
        """The identity transform."""
        return cls(1.0, np.eye(3), np.zeros(3))

    @property
    def matrix(self) -> np.ndarray:
        """The `(4, 4)` homogeneous matrix `[[s R, t], [0, 1]]`."""
        M = np.eye(4)
        M[:3, :3] = self.s * self.R
        M[:3, 3] = self.t
        return M

    def inverse(self) -> Sim3:
        """The inverse transform `p -> (1/s) R^T (p - t)`."""
        R_inv = self.R.T
        return Sim3(1.0 / self.s, R_inv, -(R_inv @ self.t) / self.s)

    def apply_points(self, p: np.ndarray) -> np.ndarray:
        """Transform points.

        Args:
            p: `(..., 3)` points.

        Returns:
            `(..., 3)` float64 points `s R p + t`.
        """
        check_shape("p", p, (..., 3))
        return self.s * (np.asarray(p, dtype=np.float64) @ self.R.T) + self.t

    def apply_poses(self, T_wc: np.ndarray) -> np.ndarray:
        """Transform camera-to-world poses into the target world frame.

        The camera centre moves like a point (rotated, scaled, translated) and the orientation
        is rotated, `R_w'c = R @ R_wc`; the result is again a rigid pose.

        Args:
            T_wc: `(..., 4, 4)` poses.

        Returns:
            `(..., 4, 4)` float64 poses `T_w'c`.
        """
        check_shape("T_wc", T_wc, (..., 4, 4))
        T = torch.from_numpy(np.ascontiguousarray(T_wc, dtype=np.float64))
        # Scaling the camera centre first, then composing with the rigid part (R, t), is the
        # similarity expressed with pose.py's rigid operations only.
        T_scaled = pose.make_pose(T[..., :3, :3], self.s * T[..., :3, 3])
        T_rigid = pose.make_pose(torch.from_numpy(self.R), torch.from_numpy(self.t))
        return pose.compose(T_rigid, T_scaled).numpy()

    def apply_trajectory(self, traj: Trajectory) -> Trajectory:
        """The trajectory with `apply_poses` applied, same timestamps."""
        return Trajectory(traj.timestamps.copy(), self.apply_poses(traj.poses))


@dataclass(frozen=True, eq=False)
class TrajectoryMetrics:
    """Trajectory accuracy of an estimate against ground truth, in ground-truth units.

    Attributes:
        ate_rmse_m: RMSE of the aligned camera centres.
        ate_mean_m: mean of the same errors.
        ate_median_m: median of the same errors.
        ate_max_m: largest of the same errors.
        rpe_trans_per_m: sum over consecutive matched pairs of the relative-translation error
            norm (estimate scaled by the alignment), divided by the ground-truth path length over
            the same pairs; NaN if the ground truth does not move.
        rpe_rot_deg_per_frame: mean relative-rotation error angle over the same pairs, degrees.
        matched: number of associated poses.
        est_count: number of estimated poses.
        gt_count: number of ground-truth poses.
        align: "sim3" or "se3".
        alignment: the estimate -> ground-truth transform.
        timestamps: `(matched,)` estimate timestamps of the associated poses.
        errors_m: `(matched,)` per-pose ATE, in the same order.
    """

    ate_rmse_m: float
    ate_mean_m: float
    ate_median_m: float
    ate_max_m: float
    rpe_trans_per_m: float
    rpe_rot_deg_per_frame: float
    matched: int
    est_count: int
    gt_count: int
    align: str
    alignment: Sim3
    timestamps: np.ndarray = field(repr=False)
    errors_m: np.ndarray = field(repr=False)

    def to_dict(self) -> dict[str, float | int | str]:
        """Scalar results for JSON/CSV reports (arrays and the full transform left out).

        Keys: `ate_rmse_m`, `ate_mean_m`, `ate_median_m`, `ate_max_m`, `rpe_trans_per_m`,
        `rpe_rot_deg_per_frame`, `matched`, `est_count`, `gt_count`, `align`, `scale`.
        """
        return {
            "ate_rmse_m": self.ate_rmse_m,
            "ate_mean_m": self.ate_mean_m,
            "ate_median_m": self.ate_median_m,
            "ate_max_m": self.ate_max_m,
            "rpe_trans_per_m": self.rpe_trans_per_m,
            "rpe_rot_deg_per_frame": self.rpe_rot_deg_per_frame,
            "matched": self.matched,
            "est_count": self.est_count,
            "gt_count": self.gt_count,
            "align": self.align,
            "scale": self.alignment.s,
        }


def associate(
    est_ts: np.ndarray, gt_ts: np.ndarray, max_dt: float = 0.02
) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one nearest-timestamp association.

    Candidate pairs are all `(i, j)` with `|est_ts[i] - gt_ts[j]| <= max_dt`; they are accepted
    greedily by increasing `|dt|` (ties by index), skipping any pair whose estimate or
    ground-truth index is already used.

    Args:
        est_ts: `(N,)` estimate timestamps, seconds, any order.
        gt_ts: `(M,)` ground-truth timestamps, seconds, any order.
        max_dt: largest accepted time difference, seconds.

    Returns:
        `(idx_est, idx_gt)`: `(K,)` int64 indices into the inputs, ordered by estimate time.
    """
    if not max_dt >= 0:
        raise ValueError(f"max_dt must be >= 0, got {max_dt}")
    est_ts = np.asarray(est_ts, dtype=np.float64)
    gt_ts = np.asarray(gt_ts, dtype=np.float64)
    check_shape("est_ts", est_ts, (None,))
    check_shape("gt_ts", gt_ts, (None,))
    if not (np.all(np.isfinite(est_ts)) and np.all(np.isfinite(gt_ts))):
        raise EvaluationError("timestamps must be finite")
    empty = np.zeros(0, dtype=np.int64)
    if len(est_ts) == 0 or len(gt_ts) == 0:
        return empty, empty

    gt_order = np.argsort(gt_ts, kind="stable")
    gt_sorted = gt_ts[gt_order]
    lo = np.searchsorted(gt_sorted, est_ts - max_dt, side="left")
    hi = np.searchsorted(gt_sorted, est_ts + max_dt, side="right")
    counts = hi - lo
    ii = np.repeat(np.arange(len(est_ts)), counts)
    # Position of each candidate within its estimate's window [lo, hi).
    offsets = np.arange(len(ii)) - np.repeat(np.cumsum(counts) - counts, counts)
    jj = gt_order[np.repeat(lo, counts) + offsets]
    dt = np.abs(est_ts[ii] - gt_ts[jj])
    keep = dt <= max_dt  # float rounding of ts +/- max_dt can admit a hair more
    ii, jj, dt = ii[keep], jj[keep], dt[keep]

    order = np.lexsort((jj, ii, dt))
    used_est = np.zeros(len(est_ts), dtype=bool)
    used_gt = np.zeros(len(gt_ts), dtype=bool)
    pairs = []
    for i, j in zip(ii[order].tolist(), jj[order].tolist(), strict=True):
        if not used_est[i] and not used_gt[j]:
            used_est[i] = used_gt[j] = True
            pairs.append((i, j))
    if not pairs:
        return empty, empty
    idx = np.asarray(pairs, dtype=np.int64)
    by_time = np.lexsort((idx[:, 0], est_ts[idx[:, 0]]))
    return idx[by_time, 0], idx[by_time, 1]


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> Sim3:
    """Least-squares similarity (or rigid) transform between corresponding points.

    Minimizes `sum_i |dst_i - (s R src_i + t)|^2` in closed form (Umeyama 1991): SVD of the
    cross-covariance, with the sign fix that keeps `det(R) = +1` (no reflections).

    Args:
        src: `(N, 3)` points, N >= 3.
        dst: `(N, 3)` corresponding points.
        with_scale: estimate `s`; False gives SE(3) (`s = 1`).

    Returns:
        The `Sim3` mapping `src` onto `dst`.

    Raises:
        EvaluationError: if fewer than 3 points, non-finite values, or all `src` points coincide.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    check_shape("src", src, (None, 3))
    check_shape("dst", dst, (len(src), 3))
    n = len(src)
    if n < MIN_MATCHES:
        raise EvaluationError(f"alignment needs at least {MIN_MATCHES} points, got {n}")
    if not (np.all(np.isfinite(src)) and np.all(np.isfinite(dst))):
        raise EvaluationError("alignment points must be finite")
    mu_src, mu_dst = src.mean(0), dst.mean(0)
    x, y = src - mu_src, dst - mu_dst
    var_src = (x * x).sum() / n
    if var_src < 1e-24:
        raise EvaluationError("alignment undefined: all estimated positions coincide")
    cov = y.T @ x / n  # Sigma_xy of the paper: dst against src
    U, D, Vt = np.linalg.svd(cov)
    S = np.ones(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2] = -1.0
    R = U @ np.diag(S) @ Vt
    s = float((D * S).sum() / var_src) if with_scale else 1.0
    if s <= 0:
        # Only when the cross-covariance vanishes (estimate uncorrelated with the ground truth).
        raise EvaluationError("alignment undefined: estimate and ground truth are uncorrelated")
    return Sim3(s, R, mu_dst - s * R @ mu_src)


def _check_finite_poses(name: str, traj: Trajectory) -> None:
    bad = ~np.all(np.isfinite(traj.poses.reshape(len(traj), 16)), axis=1)
    if not np.all(np.isfinite(traj.timestamps)):
        raise EvaluationError(f"{name} trajectory has non-finite timestamps")
    if bad.any():
        first = int(np.argmax(bad))
        raise EvaluationError(
            f"{name} trajectory has {int(bad.sum())} non-finite poses of {len(traj)} "
            f"(first at index {first}, t={traj.timestamps[first]:.6f})"
        )


def _time_range(ts: np.ndarray) -> str:
    return f"[{ts.min():.6f}, {ts.max():.6f}] s" if len(ts) else "(empty)"


def evaluate_trajectory(
    est: Trajectory,
    gt: Trajectory,
    align: Literal["sim3", "se3"] = "sim3",
    max_dt: float = 0.02,
) -> TrajectoryMetrics:
    """ATE and RPE of an estimated trajectory against ground truth.

    Args:
        est: estimated trajectory, `T_wc` in its own world frame and scale.
        gt: ground-truth trajectory.
        align: "sim3" (with scale; monocular) or "se3" (rigid).
        max_dt: association tolerance in seconds (see `associate`).

    Returns:
        The metrics; `alignment` maps the estimate's world frame onto the ground truth's.

    Raises:
        EvaluationError: on non-finite poses, or if fewer than 3 poses associate.
    """
    if align not in ("sim3", "se3"):
        raise ValueError(f"align must be 'sim3' or 'se3', got {align!r}")
    _check_finite_poses("estimated", est)
    _check_finite_poses("ground-truth", gt)
    idx_est, idx_gt = associate(est.timestamps, gt.timestamps, max_dt)
    if len(idx_est) < MIN_MATCHES:
        raise EvaluationError(
            f"only {len(idx_est)} poses associate within {max_dt} s (need {MIN_MATCHES}): "
            f"{len(est)} estimated poses over {_time_range(est.timestamps)}, "
            f"{len(gt)} ground-truth poses over {_time_range(gt.timestamps)}; "
            "do both files use the same time base (seconds, same origin)?"
        )
    E = est.poses[idx_est]
    G = gt.poses[idx_gt]
    alignment = umeyama(E[:, :3, 3], G[:, :3, 3], with_scale=align == "sim3")
    E_aligned = alignment.apply_poses(E)

    errors = np.linalg.norm(E_aligned[:, :3, 3] - G[:, :3, 3], axis=1)
    rpe_trans, rpe_rot = _relative_errors(E_aligned, G)
    metrics = TrajectoryMetrics(
        ate_rmse_m=float(np.sqrt(np.mean(errors**2))),
        ate_mean_m=float(errors.mean()),
        ate_median_m=float(np.median(errors)),
        ate_max_m=float(errors.max()),
        rpe_trans_per_m=rpe_trans,
        rpe_rot_deg_per_frame=rpe_rot,
        matched=len(idx_est),
        est_count=len(est),
        gt_count=len(gt),
        align=align,
        alignment=alignment,
        timestamps=est.timestamps[idx_est].copy(),
        errors_m=errors,
    )
    log.debug("trajectory metrics: %s", metrics.to_dict())
    return metrics


def _relative_errors(E: np.ndarray, G: np.ndarray) -> tuple[float, float]:
    """RPE over consecutive pairs of aligned estimate `E` and ground truth `G`, `(K, 4, 4)`.

    The error of pair (k, k+1) is `(G_k^-1 G_k+1)^-1 (E_k^-1 E_k+1)`; it does not depend on a
    global rigid alignment, only on the scale, which is why `E` is the aligned estimate.
    """
    E_t = torch.from_numpy(np.ascontiguousarray(E))
    G_t = torch.from_numpy(np.ascontiguousarray(G))
    rel_E = pose.compose(pose.invert(E_t[:-1]), E_t[1:])
    rel_G = pose.compose(pose.invert(G_t[:-1]), G_t[1:])
    err = pose.compose(pose.invert(rel_G), rel_E)
    trans = err[:, :3, 3].norm(dim=-1).sum().item()
    path = rel_G[:, :3, 3].norm(dim=-1).sum().item()
    angles = pose.rotation_angle(err[:, :3, :3])
    rpe_rot = math.degrees(angles.mean().item())
    if path <= 0:
        log.warning("ground truth does not move over the matched poses: rpe_trans_per_m is NaN")
        return math.nan, rpe_rot
    return trans / path, rpe_rot


def write_metrics(path: str | Path, figures: dict) -> None:
    """Write figures as strict JSON (NaN, e.g. an undefined RPE, becomes null)."""
    clean = {
        k: None if isinstance(v, float) and not math.isfinite(v) else v for k, v in figures.items()
    }
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(clean, indent=2, allow_nan=False) + "\n")

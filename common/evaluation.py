"""The project's own evaluator: what every accuracy figure in dimslam means (design.md section 6).

Trajectories:
    Estimated and ground-truth poses are associated one-to-one by nearest timestamp
    (`associate`), the estimate is aligned to the ground truth by the least-squares Sim(3)
    (`umeyama`, with scale; or SE(3)), and the absolute trajectory error (ATE) is the RMSE of the
    camera centres in ground-truth units. The relative pose error (RPE) compares consecutive
    matched pairs of the aligned estimate with the ground truth.

Meshes:
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
import trimesh
from scipy.spatial import cKDTree

from dimslam.common import pose
from dimslam.common.camera import Camera
from dimslam.common.errors import EvaluationError
from dimslam.common.shapes import check_shape
from dimslam.common.trajectory import Trajectory

log = logging.getLogger(__name__)

MIN_MATCHES = 3
"""Fewest associated poses that define a Sim(3) alignment (3 non-collinear points)."""

# Frustum culling projects (frames x points) at a time. About 1M keeps the dozen temporary
# float32 arrays in cache (measured 2x faster than 8M on room0), and memory bounded whatever the
# number of frames.
_CULL_CHUNK_ELEMENTS = 1_000_000
# Culling draws extra points until `samples` survive. Each round sizes itself from the
# surviving fraction so far (2 rounds is the usual case) but draws at most _CULL_MAX_DRAW points,
# to bound memory; after _CULL_MAX_ROUNDS it gives up.
_CULL_MAX_ROUNDS = 16
_CULL_MAX_DRAW = 4_000_000
# A surface that keeps less than this fraction of its sampled points is reported as not seen:
# most likely the poses and the mesh are in different frames.
_CULL_MIN_FRACTION = 1e-3


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


@dataclass(frozen=True)
class MeshMetrics:
    """Reconstruction accuracy of an estimated mesh against the ground-truth mesh.

    Attributes:
        accuracy_cm: mean distance from estimate samples to GT samples.
        completion_cm: mean distance from GT samples to estimate samples.
        completion_ratio: percentage (0-100) of GT samples within `threshold_cm` of the estimate.
        threshold_cm: the completion-ratio threshold.
        samples: points sampled on each surface.
        culled: whether both surfaces were culled to the GT camera frustums (False when no
            poses/camera were given: then the whole GT surface counts, including parts no camera
            saw, and so does everything the estimate extrapolates).
        gt_visible_fraction: fraction of the GT surface area inside some frustum (1 if not
            culled).
    """

    accuracy_cm: float
    completion_cm: float
    completion_ratio: float
    threshold_cm: float
    samples: int
    culled: bool
    gt_visible_fraction: float

    def to_dict(self) -> dict[str, float | int | bool]:
        """All fields, keys as the attribute names."""
        return {
            "accuracy_cm": self.accuracy_cm,
            "completion_cm": self.completion_cm,
            "completion_ratio": self.completion_ratio,
            "threshold_cm": self.threshold_cm,
            "samples": self.samples,
            "culled": self.culled,
            "gt_visible_fraction": self.gt_visible_fraction,
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


def load_mesh(path: str | Path) -> trimesh.Trimesh:
    """Read a triangle mesh (PLY, OBJ, ...) for evaluation.

    Raises:
        EvaluationError: naming the file if it is missing, unreadable or has no triangles.
    """
    path = Path(path)
    if not path.is_file():
        raise EvaluationError(f"{path}: mesh file not found")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except (ValueError, KeyError, IndexError, OSError) as e:
        raise EvaluationError(f"{path}: cannot read mesh ({e})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise EvaluationError(f"{path}: no triangles in the file")
    return mesh


def _check_mesh(name: str, mesh: trimesh.Trimesh) -> None:
    if not isinstance(mesh, trimesh.Trimesh):
        raise EvaluationError(f"{name} mesh must be a triangle mesh, got {type(mesh).__name__}")
    if len(mesh.faces) == 0 or not np.isfinite(mesh.area) or mesh.area <= 0:
        raise EvaluationError(f"{name} mesh has no surface ({len(mesh.faces)} faces)")
    if not np.all(np.isfinite(mesh.vertices)):
        raise EvaluationError(f"{name} mesh has non-finite vertices")


def _sample(mesh: trimesh.Trimesh, count: int, rng: np.random.Generator) -> np.ndarray:
    """`(count, 3)` float64 points uniformly on the surface, seeded from `rng`."""
    seed = int(rng.integers(2**63 - 1))
    points, _ = trimesh.sample.sample_surface(mesh, count, seed=seed)
    return np.asarray(points, dtype=np.float64)


def frustum_mask(
    points: np.ndarray, T_wc: np.ndarray, camera: Camera, max_depth: float = math.inf
) -> np.ndarray:
    """Which points some camera sees: in front of it (0 < z <= max_depth), inside its image.

    No occlusion test: a point behind a wall but inside the frustum counts as seen.

    Args:
        points: `(P, 3)` world points.
        T_wc: `(N, 4, 4)` camera-to-world poses.
        camera: the intrinsics of every pose.
        max_depth: far limit of the frustums (the evaluation protocol uses none; mesh
            extraction does).

    Returns:
        `(P,)` bool.
    """
    check_shape("points", points, (None, 3))
    check_shape("T_wc", T_wc, (None, 4, 4))
    # float32 is ample for a visibility test (sub-mm at 10 m) and halves the work.
    T_wc = T_wc.detach().cpu().numpy() if isinstance(T_wc, torch.Tensor) else T_wc
    T_cw = pose.invert(torch.from_numpy(np.ascontiguousarray(T_wc, dtype=np.float64))).float()
    # Frames in a golden-ratio stride order rather than in time: the first chunks then span the
    # whole trajectory, so most seen points drop out early (any order gives the same mask).
    T_cw = T_cw[np.argsort((np.arange(len(T_cw)) * 0.6180339887498949) % 1.0, kind="stable")]
    p_w = torch.from_numpy(np.ascontiguousarray(points, dtype=np.float32))
    seen = torch.zeros(len(p_w), dtype=torch.bool)
    remaining = torch.arange(len(p_w))
    frame = 0
    # Points once seen are dropped from later tests, so the cost falls as the surface is covered.
    while frame < len(T_cw) and len(remaining):
        n_frames = max(1, _CULL_CHUNK_ELEMENTS // len(remaining))
        T_chunk = T_cw[frame : frame + n_frames]
        frame += len(T_chunk)
        p_c = pose.transform_points(T_chunk, p_w[remaining])  # (F, P', 3)
        uv, z = camera.project(p_c)
        visible = ((z > 0) & (z <= max_depth) & camera.inside(uv)).any(dim=0)
        seen[remaining[visible]] = True
        remaining = remaining[~visible]
    return seen.numpy()


def _sample_visible(
    mesh: trimesh.Trimesh,
    count: int,
    to_world: Sim3,
    T_wc: np.ndarray,
    camera: Camera,
    rng: np.random.Generator,
    name: str,
) -> tuple[np.ndarray, float]:
    """`count` world points uniform on the part of `mesh` that some camera sees.

    Culls sampled points rather than faces: a ground-truth mesh may have a few huge triangles
    (a whole wall), which a per-face test would keep or drop as a whole. Draws rounds of points
    until `count` survive, then keeps `count` of them at random.

    Args:
        mesh: the surface, in its own frame.
        count: points wanted.
        to_world: maps the mesh's frame into the frame of `T_wc`.
        T_wc: `(N, 4, 4)` camera-to-world poses.
        camera: their intrinsics.
        rng: the seeded generator all draws come from.
        name: "estimated" or "ground-truth", for messages.

    Returns:
        `(count, 3)` world points and the fraction of the surface area that is seen.
    """
    kept: list[np.ndarray] = []
    n_kept = n_drawn = 0
    draw = count
    for _ in range(_CULL_MAX_ROUNDS):
        points = to_world.apply_points(_sample(mesh, draw, rng))
        visible = points[frustum_mask(points, T_wc, camera)]
        kept.append(visible)
        n_kept += len(visible)
        n_drawn += draw
        fraction = n_kept / n_drawn
        if n_kept >= count:
            break
        if fraction < _CULL_MIN_FRACTION:
            raise EvaluationError(
                f"the ground-truth cameras see almost none of the {name} mesh "
                f"({n_kept} of {n_drawn} sampled points): are the poses and the mesh in the same "
                "world frame (and the alignment right), and the intrinsics those of these poses?"
            )
        # 10% more than the fraction seen so far predicts, so one more round usually suffices.
        draw = min(int(math.ceil((count - n_kept) / fraction * 1.1)) + 100, _CULL_MAX_DRAW)
    else:
        raise EvaluationError(
            f"could not draw {count} visible {name} points in {n_drawn} samples "
            f"({fraction:.2%} of the mesh is visible); use fewer samples"
        )
    points = np.concatenate(kept)
    choice = np.sort(rng.choice(len(points), size=count, replace=False))
    return points[choice], fraction


def evaluate_mesh(
    est_mesh: trimesh.Trimesh,
    gt_mesh: trimesh.Trimesh,
    alignment: Sim3,
    gt_poses: np.ndarray | None,
    camera: Camera | None,
    samples: int = 200_000,
    threshold_m: float = 0.05,
    seed: int = 0,
) -> MeshMetrics:
    """Accuracy, completion and completion ratio of an estimated mesh (design.md section 6).

    With `gt_poses` and `camera`, both surfaces are culled to the ground-truth camera frustums
    (the estimate after alignment): a point counts if some camera has it in front (z > 0) and
    inside its image; there is no occlusion test. Culling the estimate too keeps what the map
    extrapolates into space no camera saw (marching cubes over the whole grid) out of the
    accuracy, and makes a perfect reconstruction score ~0 cm. Without them nothing is culled and
    completion counts surface that no camera saw.

    Args:
        est_mesh: the reconstruction, in the estimate's world frame and scale.
        gt_mesh: the ground-truth surface, in the ground-truth world frame.
        alignment: estimate -> ground truth, usually `evaluate_trajectory(...).alignment`.
        gt_poses: `(N, 4, 4)` ground-truth `T_wc` of the sequence (all frames are used);
            None: no culling.
        camera: the intrinsics of `gt_poses` (image size included); None: no culling.
        samples: points sampled on each (culled) surface.
        threshold_m: completion-ratio distance, metres.
        seed: sampling seed; equal seeds give equal results.

    Returns:
        The metrics, in cm and percent.

    Raises:
        EvaluationError: on an empty or non-finite mesh, or if the cameras see (almost) none of
            a surface.
    """
    _check_mesh("estimated", est_mesh)
    _check_mesh("ground-truth", gt_mesh)
    if samples < 1:
        raise ValueError(f"samples must be positive, got {samples}")
    if (gt_poses is None) != (camera is None):
        log.warning("mesh evaluation: culling needs both gt_poses and camera; not culling")
    cull = gt_poses is not None and camera is not None

    # Each surface draws from its own generator with the same seed: a mesh compared with itself
    # gets the very same points and scores exactly 0 cm, instead of half a sample spacing.
    def rng() -> np.random.Generator:
        return np.random.default_rng(seed)

    if cull:
        gt_poses = np.asarray(gt_poses, dtype=np.float64)
        check_shape("gt_poses", gt_poses, (None, 4, 4))
        if len(gt_poses) == 0 or not np.all(np.isfinite(gt_poses)):
            raise EvaluationError("ground-truth poses for culling must be non-empty and finite")
        gt_points, gt_fraction = _sample_visible(
            gt_mesh, samples, Sim3.identity(), gt_poses, camera, rng(), "ground-truth"
        )
        est_points, _ = _sample_visible(
            est_mesh, samples, alignment, gt_poses, camera, rng(), "estimated"
        )
    else:
        gt_points, gt_fraction = _sample(gt_mesh, samples, rng()), 1.0
        est_points = alignment.apply_points(_sample(est_mesh, samples, rng()))

    # workers=-1: the two queries dominate the unculled run time and parallelize perfectly.
    d_acc, _ = cKDTree(gt_points).query(est_points, workers=-1)
    d_comp, _ = cKDTree(est_points).query(gt_points, workers=-1)
    metrics = MeshMetrics(
        accuracy_cm=float(d_acc.mean() * 100),
        completion_cm=float(d_comp.mean() * 100),
        completion_ratio=float((d_comp < threshold_m).mean() * 100),
        threshold_cm=threshold_m * 100,
        samples=samples,
        culled=cull,
        gt_visible_fraction=float(gt_fraction),
    )
    log.debug("mesh metrics: %s", metrics.to_dict())
    return metrics

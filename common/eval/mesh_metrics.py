"""Mesh accuracy, completion and completion ratio (design.md section 6; protocol in
`evaluation.py`'s docstring): both surfaces sampled, culled to the ground-truth frustums,
compared by nearest sampled point."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from dimslam.common.errors import EvaluationError
from dimslam.common.eval.evaluation import Sim3
from dimslam.common.geometry.camera import Camera, frustum_mask
from dimslam.common.geometry.shapes import check_shape

log = logging.getLogger(__name__)

# Culling draws extra points until `samples` survive. Each round sizes itself from the
# surviving fraction so far (2 rounds is the usual case) but draws at most _CULL_MAX_DRAW points,
# to bound memory; after _CULL_MAX_ROUNDS it gives up.
_CULL_MAX_ROUNDS = 16
_CULL_MAX_DRAW = 4_000_000
# A surface that keeps less than this fraction of its sampled points is reported as not seen:
# most likely the poses and the mesh are in different frames.
_CULL_MIN_FRACTION = 1e-3


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


def sample_visible(
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
        gt_points, gt_fraction = sample_visible(
            gt_mesh, samples, Sim3.identity(), gt_poses, camera, rng(), "ground-truth"
        )
        est_points, _ = sample_visible(
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

"""Mesh extraction from the implicit map (design.md section 5, "Mesh").

Marching cubes (scikit-image) at the occupancy level 0.5 on a regular grid over the observed part
of the scene bound, faces culled to the estimated camera frustums, vertex colours from the
decoder, binary PLY via trimesh.

The map enters as two callables, so that any field (the learned map, an analytic test scene) can
be meshed:

- `occupancy_fn(points (N, 3) float32) -> (N,)` occupancy probability in [0, 1] (already a
  sigmoid; 0 outside the bound),
- `color_fn(points (N, 3) float32) -> (N, 3)` RGB in [0, 1].

Both receive CPU tensors in map coordinates, `chunk` points at a time, under `torch.no_grad()`;
a callable whose map lives on a GPU moves them there itself (and may return GPU tensors).

An extraction that finds no surface (the occupancy never crosses the level in the observed
region, or no face lies in a frustum) raises `EmptyMeshError`, a `DimslamError`: a broken map
ends a run with that message rather than with an empty file or a crash inside scikit-image.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from skimage import measure

from dimslam.common.errors import DimslamError
from dimslam.common.geometry import pose
from dimslam.common.geometry.camera import Camera, frustum_mask
from dimslam.common.geometry.shapes import check_shape

if TYPE_CHECKING:  # imported where used: trimesh and scipy take 0.5 s to load, a
    # restarted mapper or tracker serves sooner without them
    import trimesh

log = logging.getLogger(__name__)

FieldFn = Callable[[torch.Tensor], torch.Tensor]

MAX_GRID_CELLS = 512**3
"""Largest marching-cubes grid: its float32 volume alone takes ~0.5 GB."""


class EmptyMeshError(DimslamError):
    """The map has no surface where the cameras looked."""


def fused_occupancy(
    depths: torch.Tensor,
    T_wc: torch.Tensor,
    camera: Camera,
    truncation: float,
    weights: torch.Tensor | None = None,
) -> FieldFn:
    """An occupancy built from depth maps: 0.5 on the fused surface, 0 where nothing was seen.

    Each view says a point is free if it lies in front of the view's depth at its pixel and
    occupied just behind it (signed distance `depth - z`, truncated); the mean signed distance
    over the views that see the point (not beyond `truncation` behind their surface) becomes
    `sigmoid(-sdf / (truncation / 4))`, so the 0.5 level is the fused surface (TSDF fusion with
    equal weights). A point no view sees within `truncation` of its surface or in front of it
    is unknown (NaN: mesh with `unknown_nan=True`). Used to mesh a map whose learned occupancy
    forms no 0.5 surface.

    Args:
        depths: `(V, H, W)` z-depth maps (non-positive or non-finite: no depth).
        T_wc: `(V, 4, 4)` their camera-to-world poses.
        camera: intrinsics of the depth maps.
        truncation: signed distances are clamped to +-truncation, map units.
        weights: `(V, H, W)` each depth's weight in the mean (default: equal).
    """
    check_shape("depths", depths, (None, camera.height, camera.width))
    check_shape("T_wc", T_wc, (depths.shape[0], 4, 4))
    T_cw = pose.invert(T_wc.double())
    if weights is None:
        weights = torch.ones_like(depths)
    check_shape("weights", weights, tuple(depths.shape))
    maps = torch.stack([depths.float(), weights.float()], 1)  # (V, 2, H, W) for grid_sample
    scale = torch.tensor([2.0 / camera.width, 2.0 / camera.height], dtype=torch.float32)

    def occupancy(p: torch.Tensor) -> torch.Tensor:
        total = torch.zeros(p.shape[0], dtype=torch.float32)
        count = torch.zeros(p.shape[0], dtype=torch.float32)
        for v in range(T_cw.shape[0]):
            uv, z = camera.project(pose.transform_points(T_cw[v], p.double()).float())
            grid = (uv + 0.5) * scale - 1  # pixel centres at integer coordinates
            d, w = torch.nn.functional.grid_sample(
                maps[v : v + 1], grid.view(1, 1, -1, 2), mode="nearest", align_corners=False
            ).view(2, -1)
            inside = (grid.abs() <= 1).all(-1) & (z > 0) & torch.isfinite(d) & (d > 0)
            sdf = (d - z).clamp(-truncation, truncation)
            seen = inside & (d - z > -truncation)
            total += torch.where(seen, w * sdf, 0.0)
            count += torch.where(seen, w, 0.0)
        sdf = total / count.clamp(min=1e-6)
        # Never seen within the truncation band (outside every view, or deep behind every
        # surface that sees it): unknown, so no surface forms between what was seen and what
        # was not (neither a false inner shell nor walls at the edges of the views).
        return torch.where(count > 0, torch.sigmoid(-sdf / (truncation / 4)), float("nan"))

    return occupancy


class GridTooLarge(DimslamError):
    """The observed region needs more than `MAX_GRID_CELLS` cells at the asked voxel size."""

    def __init__(self, suggest: float, cells: int, voxel: float) -> None:
        super().__init__(
            f"mesh grid of {cells:,} cells at voxel {voxel} exceeds {MAX_GRID_CELLS:,}: "
            f"use a voxel of at least {suggest:.3g}"
        )
        self.suggest = suggest


def extract_mesh(
    occupancy_fn: FieldFn,
    color_fn: FieldFn,
    bound: torch.Tensor | np.ndarray,
    voxel: float,
    T_wc: torch.Tensor | np.ndarray,
    camera: Camera,
    max_depth: float,
    chunk: int = 65536,
    level: float = 0.5,
    progress: Callable[[int, int], None] | None = None,
    unknown_nan: bool = False,
    coarse: bool = False,
) -> trimesh.Trimesh:
    """Mesh the `level` set of the occupancy where the cameras looked.

    The grid is aligned with `bound[0]` at spacing `voxel` and covers only the part of the bound
    inside the axis-aligned box around all camera frustums (apex to `max_depth`). Faces are kept
    if all three vertices lie in some camera's frustum: `0 < z <= max_depth`, inside the image
    (no occlusion test). Face normals point out of the occupied region, towards free space.

    Args:
        occupancy_fn: points `(N, 3)` float32 -> occupancy `(N,)` in [0, 1] (see module doc).
        color_fn: points `(N, 3)` float32 -> RGB `(N, 3)` in [0, 1].
        bound: `(2, 3)` scene bound `[min; max]`, map units.
        voxel: grid spacing, map units.
        T_wc: `(N, 4, 4)` estimated camera-to-world poses.
        camera: intrinsics of every pose (image size included).
        max_depth: far limit of the frustums (z-depth), map units.
        chunk: points per call of `occupancy_fn` / `color_fn`.
        level: the surface's occupancy value.
        progress: called as `progress(points_done, points_total)` after each occupancy chunk.
        unknown_nan: the occupancy is NaN where the field knows nothing (see
            `fused_occupancy`); no face is made in a cube that touches such a point.
        coarse: evaluate the occupancy on every other grid point first and at full resolution
            only where a surface or the edge of the known region may pass (`_coarse_to_fine`):
            for occupancies without features thinner than two voxels, such as
            `fused_occupancy`'s; False evaluates every point.

    Returns:
        The mesh in map coordinates, float64 vertices, uint8 RGBA vertex colours.

    Raises:
        EmptyMeshError: no surface in the observed region (empty or saturated map).
        DimslamError: bad arguments, a grid over `MAX_GRID_CELLS`, cameras that see nothing of
            the bound, or non-finite field values.
    """
    bound = torch.as_tensor(bound, dtype=torch.float64).cpu()
    T_wc = torch.as_tensor(T_wc, dtype=torch.float64).cpu()
    check_shape("bound", bound, (2, 3))
    check_shape("T_wc", T_wc, (None, 4, 4))
    if not (math.isfinite(voxel) and voxel > 0 and math.isfinite(max_depth) and max_depth > 0):
        raise DimslamError(f"voxel and max_depth must be positive, got {voxel}, {max_depth}")
    if chunk < 1 or not 0 < level < 1:
        raise DimslamError(f"need chunk >= 1 and 0 < level < 1, got {chunk}, {level}")
    if len(T_wc) == 0 or not torch.isfinite(T_wc).all() or not torch.isfinite(bound).all():
        raise DimslamError("meshing needs at least one pose; poses and bound must be finite")
    start = time.perf_counter()
    origin, shape = _observed_grid(bound, voxel, T_wc, camera, max_depth)

    done = 0
    total = math.prod(shape)

    def evaluate(ijk: np.ndarray) -> np.ndarray:
        """The occupancy at grid points `ijk` `(N, 3)`, `chunk` at a time."""
        nonlocal done
        out = np.empty(len(ijk), np.float32)
        with torch.no_grad():
            for first in range(0, len(ijk), chunk):
                part = torch.from_numpy(ijk[first : first + chunk])
                points = (origin + part * voxel).float()
                out[first : first + len(part)] = _call(
                    occupancy_fn, points, (len(part),), "occupancy", allow_nan=unknown_nan
                )
                done += len(part)
                if progress is not None:
                    progress(min(done, total), total)
        return out

    if coarse:
        volume = _coarse_to_fine(evaluate, shape, level).reshape(-1)
    else:
        volume = evaluate(np.indices(shape).reshape(3, -1).T)
    known = np.isfinite(volume)
    volume[~known] = 0.0
    lo, hi = (float(volume[known].min()), float(volume[known].max())) if known.any() else (0, 0)
    if not lo < level < hi:
        raise EmptyMeshError(
            f"no surface to mesh: occupancy over the observed region ranges over [{lo:.3g}, "
            f"{hi:.3g}] and never crosses {level}; the map is empty or saturated there"
        )
    # Occupancy grows into matter: skimage's "ascent" then winds the triangles counter-clockwise
    # seen from free space (trimesh's convention), so face normals point out of the occupied
    # region; its default "descent" gives the reverse (test_mesh checks the orientation).
    verts, faces, _, _ = measure.marching_cubes(
        volume.reshape(shape),
        level,
        gradient_direction="ascent",
        allow_degenerate=False,
        mask=None if known.all() else _cubes_known(known.reshape(shape)),
    )
    # marching_cubes works in index units; the grid's origin and spacing make them map units.
    verts = origin.numpy() + verts.astype(np.float64) * voxel

    level_faces = len(faces)
    faces = faces[frustum_mask(verts, T_wc, camera, max_depth)[faces].all(axis=1)]
    if len(faces) == 0:
        raise EmptyMeshError(
            f"no surface to mesh: none of the {level_faces} faces of the level set lies in a "
            f"camera frustum within max_depth {max_depth}"
        )
    used = np.zeros(len(verts), bool)
    used[faces] = True
    faces = (np.cumsum(used) - 1)[faces]
    verts = verts[used]

    with torch.no_grad():
        rgb = np.concatenate(
            [
                _call(color_fn, torch.from_numpy(verts[i : i + chunk]).float(), (None, 3), "colour")
                for i in range(0, len(verts), chunk)
            ]
        )
    rgba = np.full((len(verts), 4), 255, np.uint8)
    rgba[:, :3] = np.round(np.clip(rgb, 0, 1) * 255)
    import trimesh

    mesh = trimesh.Trimesh(verts, faces, vertex_colors=rgba, process=False)
    log.info(
        "mesh: %d vertices, %d faces from a %dx%dx%d grid at voxel %g in %.1f s",
        len(verts),
        len(faces),
        *shape,
        voxel,
        time.perf_counter() - start,
    )
    return mesh


def extract_mesh_in_budget(
    occupancy_fn: FieldFn, color_fn: FieldFn, bound, voxel: float, *args, **kwargs
) -> trimesh.Trimesh:
    """`extract_mesh`, at the coarsest voxel the grid's budget allows where the observed
    region needs more than `MAX_GRID_CELLS` cells at `voxel` (a coarser mesh beats none;
    logged as a warning)."""
    try:
        return extract_mesh(occupancy_fn, color_fn, bound, voxel, *args, **kwargs)
    except GridTooLarge as e:
        log.warning("%s; meshing at %.3g instead", e, e.suggest)
        return extract_mesh(occupancy_fn, color_fn, bound, e.suggest, *args, **kwargs)


def write_mesh(mesh: trimesh.Trimesh, path: str | Path) -> None:
    """Write `mesh` as binary PLY with its uint8 vertex colours; creates the parent folder.

    Raises:
        DimslamError: naming the file if it cannot be written.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(mesh.export(file_type="ply", encoding="binary"))
    except OSError as e:
        raise DimslamError(f"{path}: cannot write mesh ({e.strerror})") from None


def _observed_grid(
    bound: torch.Tensor, voxel: float, T_wc: torch.Tensor, camera: Camera, max_depth: float
) -> tuple[torch.Tensor, tuple[int, int, int]]:
    """Origin `(3,)` float64 and sample counts of the grid over the bound part cameras can see."""
    w, h = camera.width - 0.5, camera.height - 0.5
    uv = torch.tensor([[-0.5, -0.5], [w, -0.5], [-0.5, h], [w, h]], dtype=torch.float64)
    # A frustum is the hull of its apex and its four far corners.
    far = camera.unproject(uv, torch.full((4,), max_depth, dtype=torch.float64))
    p_c = torch.cat([torch.zeros(1, 3, dtype=torch.float64), far])
    p_w = pose.transform_points(T_wc, p_c).reshape(-1, 3)
    # Indices on the lattice `bound[0] + i * voxel`, so that the grid does not move with the
    # cameras; the last index stays inside the bound, where the field is defined.
    last = torch.floor((bound[1] - bound[0]) / voxel + 1e-9)
    i0 = torch.floor((p_w.min(0).values - bound[0]) / voxel).clamp(0, None)
    i1 = torch.minimum(torch.ceil((p_w.max(0).values - bound[0]) / voxel), last)
    counts = (i1 - i0 + 1).long()
    if (counts < 2).any():
        raise DimslamError(
            f"the cameras see no part of the bound {bound.tolist()} at least one voxel "
            f"({voxel}) thick: are the poses in the map frame, and the voxel small enough?"
        )
    cells = math.prod(int(c) - 1 for c in counts)
    if cells > MAX_GRID_CELLS:
        raise GridTooLarge(voxel * (cells / MAX_GRID_CELLS) ** (1 / 3) * 1.01, cells, voxel)
    return bound[0] + i0 * voxel, tuple(int(c) for c in counts)


def _coarse_to_fine(
    evaluate: Callable[[np.ndarray], np.ndarray], shape: tuple[int, int, int], level: float
) -> np.ndarray:
    """The grid's values, `evaluate`d (grid indices `(N, 3)` -> values) exactly where the mesh
    can pass and interpolated elsewhere.

    First every other point along each axis (an eighth of them). A coarse cell is *active*
    where its corners straddle `level` or mix known and unknown (NaN) values; the active
    cells and their neighbours are evaluated at every point, and so is the last layer along an
    axis of even length (the coarse lattice ends one point short of it). Elsewhere the points
    take the trilinear mean of their coarse cell's corners, which stays on the corners' side
    of `level` (or NaN with them): marching cubes makes no face there, as with exact values. A
    surface that enters and leaves a coarse cell between its corners (thinner than two
    voxels) is missed: the synthetic room's analytic occupancy, whose sigmoid saturates within
    a voxel, lost 2 % of its vertices at a table top. Fused depth changes over the truncation
    band (3 voxels in `Mapper.extract_mesh`) instead: on the final map of a cpu-preset room0
    run it made the same 23 184 faces as every point evaluated, in 25 s instead of 37 s for
    the whole extraction (docs/benchmarks.md); islands of a voxel or two can be lost.
    """
    n = np.array(shape)
    m = (n + 1) // 2  # coarse points at fine indices 0, 2, ..., 2 (m - 1) <= n - 1
    coarse = evaluate(np.indices(m).reshape(3, -1).T * 2).reshape(m)
    corners = np.stack(
        [
            coarse[a : m[0] - 1 + a, b : m[1] - 1 + b, c : m[2] - 1 + c]
            for a in (0, 1)
            for b in (0, 1)
            for c in (0, 1)
        ]
    )
    unknown = np.isnan(corners)
    with np.errstate(invalid="ignore"):
        lo, hi = np.fmin.reduce(corners), np.fmax.reduce(corners)
    active = (unknown.any(0) & ~unknown.all(0)) | ((lo < level) & (level < hi))
    from scipy import ndimage

    active = ndimage.binary_dilation(active, structure=np.ones((3, 3, 3), bool))
    # Upsample: even fine indices are the coarse points, odd ones the mean of their two
    # neighbours, axis by axis (the trilinear mean of the cell's corners).
    fine = coarse
    for axis in range(3):
        size = list(fine.shape)
        size[axis] = 2 * m[axis] - 1
        out = np.empty(size, np.float32)
        even = [slice(None)] * 3
        odd = [slice(None)] * 3
        even[axis], odd[axis] = slice(0, None, 2), slice(1, None, 2)
        out[tuple(even)] = fine
        lower = [slice(None)] * 3
        upper = [slice(None)] * 3
        lower[axis], upper[axis] = slice(0, -1), slice(1, None)
        out[tuple(odd)] = 0.5 * (fine[tuple(lower)] + fine[tuple(upper)])
        fine = out
    volume = np.full(shape, np.nan, np.float32)
    volume[: fine.shape[0], : fine.shape[1], : fine.shape[2]] = fine
    # Every fine point of an active cell: the cell's points [2a, 2a + 2] along each axis.
    exact = np.zeros(shape, bool)
    cells = np.repeat(np.repeat(np.repeat(active, 2, 0), 2, 1), 2, 2)
    exact[: cells.shape[0], : cells.shape[1], : cells.shape[2]] = cells
    for axis in range(3):
        shifted = np.zeros_like(exact)
        src = [slice(None)] * 3
        dst = [slice(None)] * 3
        src[axis], dst[axis] = slice(0, -1), slice(1, None)
        shifted[tuple(dst)] = exact[tuple(src)]
        exact |= shifted
    for axis in range(3):
        if shape[axis] % 2 == 0:
            last = [slice(None)] * 3
            last[axis] = shape[axis] - 1
            exact[tuple(last)] = True
    exact[::2, ::2, ::2] = False  # the coarse points: evaluated already
    ijk = np.argwhere(exact)
    volume[tuple(ijk.T)] = evaluate(ijk)
    return volume


def _cubes_known(known: np.ndarray) -> np.ndarray:
    """Grid points all of whose 26 neighbours are known: every cube that touches the point has
    only known corners, whichever corner of its cubes marching cubes' mask refers to."""
    from scipy import ndimage

    return ndimage.binary_erosion(known, structure=np.ones((3, 3, 3), bool), border_value=0)


def _call(
    fn: FieldFn, points: torch.Tensor, shape: tuple, name: str, allow_nan: bool = False
) -> np.ndarray:
    """`fn(points)` as a float32 numpy array of `shape`, checked to be finite (or NaN)."""
    out = fn(points)
    check_shape(f"{name} output", out, shape)
    out = out.detach().float().cpu().numpy()
    if not (np.isfinite(out) | (allow_nan & np.isnan(out))).all():
        raise DimslamError(f"the map's {name} is not finite (NaN/inf): has the map diverged?")
    return out

"""Pictures of a mesh, headless: a few views rendered in numpy and written as one PNG.

A run writes `mesh_views.png` next to `mesh.ply` and `trajectory.png`, so that a person can
look at the map without a 3D viewer: three views from the estimated path (a quarter, half and
three quarters of the way along it, each pulled back to show more than the camera saw) and one
from above and behind the whole mesh.

The rasterizer is a z-buffer over pixel centres: each face is tested at every pixel of its
bounding box (faces grouped by box size, so that small faces, nearly all of a map's, cost
little), depth is interpolated perspective-correctly, and the nearest fragment wins. A face is
flat-shaded: the mean of its vertex colours times a headlight term (`AMBIENT` + the rest by the
cosine between its normal and the ray).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from dimslam.common.errors import DimslamError
from dimslam.common.geometry.camera import Camera

if TYPE_CHECKING:  # imported where a mesh is made: trimesh and scipy take 0.5 s to load
    import trimesh

log = logging.getLogger(__name__)

NEAR = 0.05
"""Faces with a vertex closer to the camera than this (metres, or map units) are not drawn."""
AMBIENT = 0.3
"""Share of a face's colour it keeps when seen edge-on."""
BACKGROUND = (40, 40, 40)
"""RGB of pixels no face covers."""
CHUNK_PIXELS = 1 << 21
"""Candidate pixels tested at once (bounds the rasterizer's memory to ~100 MB)."""
VIEW_WIDTH = 320
"""Width of each view in pixels, whatever the run's frames."""
PULL_BACK = 0.5
"""A path view's camera moves back along its optical axis by this share of the median depth
of the mesh in front of it."""


def render_mesh(
    mesh: trimesh.Trimesh, camera: Camera, T_wc: np.ndarray, cull: int = 0
) -> np.ndarray:
    """The mesh seen by `camera` at pose `T_wc` (camera to world, x right, y down, z forward).

    Args:
        cull: 0 draws every face; 1 (-1) only those whose winding is counter-clockwise
            (clockwise) on screen, i.e. that face the camera if the mesh's normals point (do
            not point) towards where its cameras were (`facing`). Seen from outside, a room
            culled so shows its inside through the walls that face away.

    Returns:
        `(height, width, 3)` uint8 RGB.
    """
    corners, faces = _front_faces(mesh, T_wc)
    z = corners[..., 2]
    uv = np.stack(
        [camera.fx * corners[..., 0] / z + camera.cx, camera.fy * corners[..., 1] / z + camera.cy],
        axis=-1,
    )  # (F, 3, 2)
    lo = np.clip(np.ceil(uv.min(axis=1)), 0, [camera.width, camera.height]).astype(np.int64)
    hi = np.clip(np.floor(uv.max(axis=1)), -1, [camera.width - 1, camera.height - 1])
    hi = hi.astype(np.int64)
    area = _edge(uv[:, 0], uv[:, 1], uv[:, 2])
    keep = (hi >= lo).all(axis=1) & (np.abs(area) > 1e-12) & (cull * area >= 0)
    colors = _face_colors(mesh, faces, corners)
    image = np.empty((camera.height, camera.width, 3), np.uint8)
    image[:] = BACKGROUND
    pixels, depths, which = [], [], []
    span = (hi - lo + 1).max(axis=1)
    k = 1
    while True:
        group = np.flatnonzero(keep & (span <= k) & (span > k // 2))
        for chunk in np.array_split(group, max(1, math.ceil(len(group) * k * k / CHUNK_PIXELS))):
            pixel, depth, face = _fragments(uv[chunk], z[chunk], area[chunk], lo[chunk], k)
            on = (pixel[:, 0] < camera.width) & (pixel[:, 1] < camera.height)  # boxes clipped
            pixel, depth, face = pixel[on], depth[on], face[on]
            pixels.append(pixel[:, 1] * camera.width + pixel[:, 0])
            depths.append(depth)
            which.append(chunk[face])
        if k >= max(camera.width, camera.height):
            break
        k *= 2
    if pixels:
        pixel, depth, face = np.concatenate(pixels), np.concatenate(depths), np.concatenate(which)
        order = np.lexsort((depth, pixel))
        first = np.ones(len(order), bool)
        first[1:] = pixel[order][1:] != pixel[order][:-1]
        nearest = order[first]
        image.reshape(-1, 3)[pixel[nearest]] = colors[face[nearest]]
    return image


def _front_faces(mesh: trimesh.Trimesh, T_wc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The faces wholly in front of the camera at `T_wc` (every corner beyond `NEAR`): their
    corners in the camera frame `(F, 3, 3)` and their vertex indices `(F, 3)`."""
    R, t = T_wc[:3, :3], T_wc[:3, 3]
    p = (np.asarray(mesh.vertices, dtype=np.float64) - t) @ R  # world to camera: R^T (v - t)
    faces = np.asarray(mesh.faces)
    corners = p[faces]
    front = (corners[..., 2] > NEAR).all(axis=1)
    return corners[front], faces[front]


def _edge(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Twice the signed area of the triangles `a b c` (each `(..., 2)`)."""
    return (b[..., 0] - a[..., 0]) * (c[..., 1] - a[..., 1]) - (b[..., 1] - a[..., 1]) * (
        c[..., 0] - a[..., 0]
    )


def _fragments(
    uv: np.ndarray, z: np.ndarray, area: np.ndarray, lo: np.ndarray, k: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pixel centres inside each face of a group whose boxes are at most `k` pixels wide,
    found among the `k x k` pixels from each box's corner `lo`: `(pixel (n, 2), depth (n,),
    face (n,))`, face indexing the group."""
    steps = np.stack(np.meshgrid(np.arange(k), np.arange(k), indexing="xy"), -1).reshape(-1, 2)
    q = (lo[:, None, :] + steps[None]).astype(np.float64)  # (G, k*k, 2)
    a, b, c = (uv[:, None, i] for i in range(3))
    w = np.stack([_edge(b, c, q), _edge(c, a, q), _edge(a, b, q)], -1) / area[:, None, None]
    inside = (w >= 0).all(axis=-1)
    face, cell = np.nonzero(inside)
    w = w[face, cell]
    depth = 1.0 / (w / z[face]).sum(axis=-1)  # perspective-correct: 1/z is linear on screen
    return q[face, cell].astype(np.int64), depth, face


def _face_colors(mesh: trimesh.Trimesh, faces: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """`(F, 3)` uint8: each face's mean vertex colour (grey without colours), headlit."""
    if mesh.visual.kind == "vertex":
        base = np.asarray(mesh.visual.vertex_colors)[:, :3].astype(np.float64)[faces].mean(1)
    else:
        base = np.full((len(faces), 3), 200.0)
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    ray = corners.mean(axis=1)
    cos = np.abs((normal * ray).sum(-1)) / np.maximum(
        np.linalg.norm(normal, axis=-1) * np.linalg.norm(ray, axis=-1), 1e-12
    )
    return np.clip(base * (AMBIENT + (1 - AMBIENT) * cos[:, None]), 0, 255).astype(np.uint8)


def facing(mesh: trimesh.Trimesh, T_wc: np.ndarray) -> int:
    """1 if most faces in front of the camera at `T_wc` wind counter-clockwise on its screen
    (y down), else -1: the `cull` under which a camera on the observed side sees them."""
    corners, _ = _front_faces(mesh, T_wc)
    uv = corners[..., :2] / corners[..., 2:]
    area = _edge(uv[:, 0], uv[:, 1], uv[:, 2])
    return 1 if (area > 0).sum() >= (area < 0).sum() else -1


def view_poses(mesh: trimesh.Trimesh, poses: np.ndarray) -> list[np.ndarray]:
    """The poses the views are rendered from: three along the path `poses` (`(N, 4, 4)`
    camera to world), pulled back, and one from above and behind the mesh's centre.

    "Above" is the cameras' mean up (-y); "behind" is against their mean viewing direction.
    """
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    views = []
    for share in (0.25, 0.5, 0.75):
        T = poses[min(len(poses) - 1, int(share * len(poses)))].copy()
        depth = (vertices - T[:3, 3]) @ T[:3, 2]
        ahead = depth[depth > NEAR]
        back = PULL_BACK * float(np.median(ahead)) if len(ahead) else 0.0
        T[:3, 3] -= back * T[:3, 2]
        views.append(T)
    up = -poses[:, :3, 1].mean(axis=0)
    forward = poses[:, :3, 2].mean(axis=0)
    # Robust to the few stray faces far out that a map has: the middle 90 % of the vertices.
    centre = np.median(vertices, axis=0)
    low, high = np.percentile(vertices, [5, 95], axis=0)
    extent = float(np.linalg.norm(high - low))
    up /= max(np.linalg.norm(up), 1e-12)
    forward -= (forward @ up) * up
    if np.linalg.norm(forward) < 1e-6:  # cameras looking straight down: any horizontal axis
        forward = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    forward /= np.linalg.norm(forward)
    eye = centre + extent * (0.7 * up - 0.7 * forward)
    views.append(look_at(eye, centre, up))
    return views


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """The camera-to-world pose at `eye` looking at `target`, `up` towards the image's top."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(-up, z)
    x = x / np.linalg.norm(x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, np.cross(z, x), z, eye
    return T


def write_mesh_views(
    mesh: trimesh.Trimesh, camera: Camera, poses: np.ndarray, path: str | Path
) -> Path:
    """Render the views of `view_poses` through `camera`'s field of view, `VIEW_WIDTH` pixels
    wide, and write them as one 2 x 2 PNG. Returns the path.

    Raises:
        DimslamError: no pose, or the file cannot be written.
    """
    path = Path(path)
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or len(poses) == 0:
        raise DimslamError("mesh views need at least one camera pose")
    small = camera.resized(VIEW_WIDTH)
    *path_views, overview = view_poses(mesh, poses)
    tiles = [render_mesh(mesh, small, T) for T in path_views]
    # From outside, the faces the cameras saw from within: the near walls drop away.
    tiles.append(render_mesh(mesh, small, overview, facing(mesh, poses[len(poses) // 2])))
    rows = [np.concatenate(tiles[i : i + 2], axis=1) for i in range(0, len(tiles), 2)]
    picture = np.concatenate(rows, axis=0)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), cv2.cvtColor(picture, cv2.COLOR_RGB2BGR)):
        raise DimslamError(f"{path}: cannot write the mesh views")
    covered = float((picture != BACKGROUND).any(axis=-1).mean())
    log.info("mesh views -> %s (%.0f%% of the pixels show the mesh)", path, 100 * covered)
    if math.isclose(covered, 0.0):
        log.warning("the mesh views show no surface: every view missed the mesh")
    return path

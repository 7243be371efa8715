"""The built-in synthetic scene: a textured box room, ray cast exactly, written as TUM RGB-D.

The scene is a 5 x 4 x 2.8 m room (world z up, floor at z = 0) seen from inside, with box
furniture against the walls. Every surface carries a photograph that ships inside the
scikit-image wheel (no downloads), tiled at a physical scale and sampled with trilinear
mip-mapping so that distant surfaces do not alias. Shading is Lambertian with a fixed light, one
factor per face, so a surface point has the same colour from every view.

Rendering is analytic: each pixel's ray is intersected with the room and the boxes (slab test),
which gives exact z-depth. A seed fixes the furniture, the texture assignment and a smooth
handheld-like camera path through the free middle of the room.

Why one module of ~560 lines: the room, its textures, its camera path and the writer of its
files define one scene together (the writer records the scene's own constants in calib.txt
and the mesh); split, a change of the scene would touch several files at once.
"""

from __future__ import annotations

import functools
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import trimesh

from dimslam.common.errors import DimslamError
from dimslam.common.geometry.camera import Camera
from dimslam.common.geometry.shapes import check_shape
from dimslam.common.io.trajectory import Trajectory, write_tum

log = logging.getLogger(__name__)

ROOM = np.array([[0.0, 0.0, 0.0], [5.0, 4.0, 2.8]])
"""`(2, 3)` room corners `[min, max]` in metres."""
FPS = 30.0
DEPTH_SCALE = 5000.0
"""Depth PNG units per metre (TUM RGB-D)."""
PATHS = ("walk", "loop")
"""Camera paths `write_sequence` renders."""

# Furniture reaches at most this far from its wall, and camera centres stay in _CAMERA_BOX,
# which keeps them >= 0.65 m from any furniture and >= 1.45 m from the walls.
_FURNITURE_REACH = 0.8
_CAMERA_BOX = np.array([[1.5, 1.45, 1.15], [3.5, 2.55, 1.75]])
# (length along the wall, depth, height) ranges in metres.
_FURNITURE = {
    "table": ((1.1, 1.5), (0.6, 0.7), (0.72, 0.78)),
    "cabinet": ((0.5, 0.8), (0.45, 0.6), (1.6, 2.0)),
    "shelf": ((0.8, 1.2), (0.3, 0.4), (1.2, 1.8)),
    "sofa": ((1.6, 2.0), (0.6, 0.7), (0.45, 0.55)),
    "desk": ((1.0, 1.3), (0.5, 0.65), (0.72, 0.76)),
    "crate": ((0.4, 0.6), (0.4, 0.6), (0.4, 0.6)),
}
# skimage.data images bundled in the wheel, with metres per horizontal texture repeat. Images
# with large flat areas (camera's sky, page's paper) are left out: SLAM needs texture everywhere.
_TEXTURES = {
    "brick": 1.2,
    "grass": 1.5,
    "gravel": 1.2,
    "text": 1.5,
    "coins": 1.2,
    "astronaut": 1.6,
    "chelsea": 1.5,
    "coffee": 1.5,
    "hubble_deep_field": 1.6,
    "immunohistochemistry": 1.2,
    "stereo_motorcycle": 1.8,
}
_TEX_WIDTH = 512
_MIP_LEVELS = 6  # texture sizes are multiples of 2**(_MIP_LEVELS - 1), so levels halve exactly
_LIGHT = np.array([0.4, 0.25, 0.88]) / np.linalg.norm([0.4, 0.25, 0.88])
_OUTPUT_NAMES = {"rgb", "depth", "rgb.txt", "depth.txt", "groundtruth.txt", "calib.txt", "mesh.ply"}
_MARKER = "# dimslam synthetic room"


def default_camera(width: int, height: int) -> Camera:
    """The synthetic camera: about 62 degrees horizontal field of view, centred, square pixels."""
    f = 0.82 * width
    return Camera(width, height, f, f, (width - 1) / 2, (height - 1) / 2)


@functools.cache
def _texture_image(name: str) -> np.ndarray:
    """`(h, 512, 3)` uint8 RGB, h a multiple of the coarsest mip step."""
    import skimage.data

    image = getattr(skimage.data, name)()
    if isinstance(image, tuple):  # stereo pairs
        image = image[0]
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    step = 2 ** (_MIP_LEVELS - 1)
    height = max(step, round(_TEX_WIDTH * image.shape[0] / image.shape[1] / step) * step)
    return cv2.resize(image[..., :3], (_TEX_WIDTH, height), interpolation=cv2.INTER_AREA)


class _Atlas:
    """All textures and their mip levels packed in one image, sampled with `cv2.remap`.

    Texture `t` fills a band of rows: level 0 on the left, the coarser levels stacked to its
    right. Every level carries a one-texel border copied from its opposite edge, so bilinear
    reads across a tile's edge see the wrapped texture instead of a neighbour.
    """

    def __init__(self, names: list[str]) -> None:
        self.height = np.array([_texture_image(n).shape[0] for n in names], np.float32)
        self.origin = np.zeros((len(names), _MIP_LEVELS, 2), np.float32)  # texel (0, 0) x, y
        bands = []
        for t, name in enumerate(names):
            levels = [_texture_image(name)]
            for _ in range(1, _MIP_LEVELS):
                h, w = levels[-1].shape[:2]
                levels.append(
                    cv2.resize(levels[-1], (w // 2, h // 2), interpolation=cv2.INTER_AREA)
                )
            padded = [cv2.copyMakeBorder(im, 1, 1, 1, 1, cv2.BORDER_WRAP) for im in levels]
            band_h = max(padded[0].shape[0], sum(p.shape[0] for p in padded[1:]))
            band = np.zeros((band_h, _TEX_WIDTH + 2 + padded[1].shape[1], 3), np.uint8)
            band[: padded[0].shape[0], : _TEX_WIDTH + 2] = padded[0]
            y = 0
            for m, p in enumerate(padded[1:], 1):
                band[y : y + p.shape[0], _TEX_WIDTH + 2 : _TEX_WIDTH + 2 + p.shape[1]] = p
                self.origin[t, m] = (_TEX_WIDTH + 3, y + 1)
                y += p.shape[0]
            self.origin[t, 0] = (1, 1)
            self.origin[t, :, 1] += sum(b.shape[0] for b in bands)
            bands.append(band)
        self.image = np.concatenate(bands)

    def sample(self, tex: np.ndarray, level: np.ndarray, u: np.ndarray, v: np.ndarray):
        """Bilinear colours `(H, W, 3)` uint8 at level-0 texel coordinates `(H, W)`, tiled."""
        u = u - np.floor(u / _TEX_WIDTH) * _TEX_WIDTH
        v = v - np.floor(v / self.height[tex]) * self.height[tex]
        scale = np.ldexp(np.float32(1), -level)
        # Texel centres sit at integers: level-0 coordinate u maps to (u + 0.5) / 2^m - 0.5.
        x = (u + 0.5) * scale - 0.5 + self.origin[tex, level, 0]
        y = (v + 0.5) * scale - 0.5 + self.origin[tex, level, 1]
        return cv2.remap(self.image, x, y, cv2.INTER_LINEAR)


@functools.cache
def _atlas() -> _Atlas:
    return _Atlas(list(_TEXTURES))


class SynthScene:
    """The seeded synthetic room: geometry, textures, renderer and camera path.

    Faces are numbered per box: `2 * axis + side` (side 1 is the face at the box's maximum along
    `axis`); the room is box 0 and is seen from inside, furniture box `b` is box `b + 1`.

    Attributes:
        seed: the seed everything is drawn from.
        room: `(2, 3)` float64 room corners `[min, max]`.
        furniture: `(B, 2, 3)` float64 furniture boxes `[min, max]`, standing on the floor.
        names: `B` furniture names.
    """

    def __init__(self, seed: int = 0) -> None:
        _check_count("seed", seed, 0)
        self.seed = int(seed)
        rng = np.random.default_rng([self.seed, 0])
        self.room = ROOM.copy()
        self.names, boxes = _place_furniture(rng)
        self.furniture = np.array(boxes, np.float64).reshape(-1, 2, 3)
        textures = list(_TEXTURES)
        self._atlas = _atlas()
        faces = 6 * (1 + len(self.furniture))
        # Walls get distinct textures; each furniture piece gets one for its sides, one for its top.
        order = rng.permutation(len(textures))
        tex = np.zeros(faces, np.int64)
        tex[:6] = order[:6]
        picks = rng.integers(0, len(textures), size=(len(self.furniture), 2))
        for b, (sides, top) in enumerate(picks):
            tex[6 * (b + 1) : 6 * (b + 2)] = sides
            tex[6 * (b + 1) + 5] = top
        self._tex = tex
        self._axis = np.tile(np.repeat(np.arange(3), 2), 1 + len(self.furniture))
        side = np.tile([-1.0, 1.0], 3 * (1 + len(self.furniture)))
        side[:6] *= -1  # room faces point inward
        self._normal = np.eye(3)[self._axis] * side[:, None]
        up = np.array([0.0, 0.0, 1.0])
        vertical = (self._axis < 2)[:, None]
        # Texture axes: on walls u runs to the viewer's right and v downwards, so no photo is
        # mirrored or upside down; floor and ceiling use world x, y. Each is +-1 world axis.
        u_dir = np.where(vertical, np.cross(up, self._normal), np.eye(3)[0])
        v_dir = np.where(vertical, -up, np.eye(3)[1])
        metres = np.array([_TEXTURES[textures[t]] for t in tex]) * rng.uniform(0.8, 1.2, faces)
        density = _TEX_WIDTH / metres  # level-0 texels per metre
        self._log_density = np.log2(density).astype(np.float32)
        self._tex_axes = np.stack([np.abs(u_dir).argmax(1), np.abs(v_dir).argmax(1)], 1)
        self._tex_scale = (np.stack([u_dir.sum(1), v_dir.sum(1)], 1) * density[:, None]).astype(
            np.float32
        )
        self._tex_shift = rng.uniform(0, _TEX_WIDTH, (faces, 2)).astype(np.float32)
        tint = 1 - rng.uniform(0, 0.25, (faces, 3))
        shade = 0.45 + 0.55 * np.clip(self._normal @ _LIGHT, 0, None)
        self._colour = (tint / tint.max(1, keepdims=True) * shade[:, None] / 255).astype(np.float32)
        corner = np.array([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)])  # min/max per axis
        self._corners = self.furniture[:, corner, np.arange(3)]  # (B, 8, 3)
        self._rays_for: Camera | None = None

    def _rays(self, camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Camera-frame ray `x`, `y` `(H, W)` float32 (z = 1) and half the log2 ray norm."""
        if self._rays_for != camera:
            u, v = np.meshgrid(np.arange(camera.width), np.arange(camera.height))
            x = ((u - camera.cx) / camera.fx).astype(np.float32)
            y = ((v - camera.cy) / camera.fy).astype(np.float32)
            self._ray_cache = x, y, (0.25 * np.log2(x * x + y * y + 1)).astype(np.float32)
            self._rays_for = camera
        return self._ray_cache

    def render(self, T_wc: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
        """Render the scene without noise (distortion coefficients are ignored).

        Args:
            T_wc: `(4, 4)` camera-to-world pose, OpenCV camera axes; must lie inside the room.
            camera: pinhole intrinsics and image size.

        Returns:
            `rgb` `(H, W, 3)` float32 in [0, 1] and `depth` `(H, W)` float32 z-depth in metres.
        """
        check_shape("T_wc", T_wc, (4, 4))
        T = np.asarray(T_wc, np.float64)
        if not np.all((T[:3, 3] > self.room[0]) & (T[:3, 3] < self.room[1])):
            raise ValueError(f"camera centre {T[:3, 3]} is outside the room {self.room.tolist()}")
        x, y, half_log_norm = self._rays(camera)
        R, o = T[:3, :3].astype(np.float32), T[:3, 3].astype(np.float32)
        # World ray directions, one (H, W) array per axis (numpy reduces slowly over a last axis
        # of 3). With camera-frame z = 1, the ray parameter t of a hit is its z-depth. An
        # axis-parallel ray gets a tiny component on that axis, so its t there is huge.
        d = [R[k, 0] * x + R[k, 1] * y + R[k, 2] for k in range(3)]
        d = [np.where(np.abs(c) < 1e-9, np.float32(1e-9), c) for c in d]
        t, face = self._intersect(o, d, T, camera)
        p = [o[k] + t * d[k] for k in range(3)]
        u = (
            np.choose(self._tex_axes[face, 0], p) * self._tex_scale[face, 0]
            + self._tex_shift[face, 0]
        )
        v = (
            np.choose(self._tex_axes[face, 1], p) * self._tex_scale[face, 1]
            + self._tex_shift[face, 1]
        )
        # Mip level from the pixel footprint on the surface: t / (fx |d.n|) along the slant,
        # t / (fx |d|) across; their geometric mean trades blur against aliasing at grazing angles.
        d_normal = np.abs(np.choose(self._axis[face], d))
        level = (
            np.log2(t)
            + self._log_density[face]
            - np.float32(np.log2(camera.fx))
            - 0.5 * np.log2(d_normal)
            - half_log_norm
        )
        level = np.clip(level, 0, _MIP_LEVELS - 1)
        fine = np.minimum(level.astype(np.int64), _MIP_LEVELS - 2)
        blend = (level - fine)[..., None]
        tex = self._tex[face]
        colour = self._atlas.sample(tex, fine, u, v) * (1 - blend)
        colour += self._atlas.sample(tex, fine + 1, u, v) * blend
        return np.minimum(colour * self._colour[face], 1).astype(np.float32, copy=False), t

    def _intersect(
        self, o: np.ndarray, d: list[np.ndarray], T_wc: np.ndarray, camera: Camera
    ) -> tuple[np.ndarray, np.ndarray]:
        """Nearest hit `t` (H, W) float32 and face index (H, W) of rays `o + t d` from inside."""
        inv = [1 / c for c in d]
        forward = [c > 0 for c in d]
        # Inside the room, a ray leaves through the nearest of the three walls it heads for.
        lo, hi = (self.room - o).astype(np.float32)
        tx, ty, tz = (np.where(forward[k], hi[k], lo[k]) * inv[k] for k in range(3))
        t = np.minimum(tx, np.minimum(ty, tz))
        face = np.where(tx == t, forward[0], np.where(ty == t, 2 + forward[1], 4 + forward[2]))
        for b, (box, win) in enumerate(
            zip(self.furniture, self._windows(T_wc, camera), strict=True)
        ):
            if win is None:
                continue
            lo, hi = (box - o).astype(np.float32)
            ends = [(lo[k] * inv[k][win], hi[k] * inv[k][win]) for k in range(3)]
            ex, ey, ez = (np.minimum(*e) for e in ends)
            t_near = np.maximum(ex, np.maximum(ey, ez))
            fx, fy, fz = (np.maximum(*e) for e in ends)
            t_far = np.minimum(fx, np.minimum(fy, fz))
            closer = (t_near <= t_far) & (t_near > 0) & (t_near < t[win])
            # A forward-moving ray enters a box through its minimum face.
            entry = np.where(
                ex == t_near,
                ~forward[0][win],
                np.where(ey == t_near, 2 + ~forward[1][win], 4 + ~forward[2][win]),
            )
            t[win] = np.where(closer, t_near, t[win])
            face[win] = np.where(closer, 6 * (b + 1) + entry, face[win])
        return t, face

    def _windows(self, T_wc: np.ndarray, camera: Camera) -> list[tuple[slice, slice] | None]:
        """Per furniture box, the pixel slices `(rows, columns)` whose rays may hit it."""
        p_c = (self._corners - T_wc[:3, 3]) @ T_wc[:3, :3]  # (B, 8, 3)
        z = np.maximum(p_c[..., 2], 1e-3)
        # A box in front of the camera projects inside the hull of its corners; one pixel of
        # margin covers rounding. A box straddling the camera plane may cover any pixel.
        u = camera.fx * p_c[..., 0] / z + camera.cx
        v = camera.fy * p_c[..., 1] / z + camera.cy
        u0 = np.clip(np.floor(u.min(1)) - 1, 0, camera.width).astype(int)
        u1 = np.clip(np.ceil(u.max(1)) + 2, 0, camera.width).astype(int)
        v0 = np.clip(np.floor(v.min(1)) - 1, 0, camera.height).astype(int)
        v1 = np.clip(np.ceil(v.max(1)) + 2, 0, camera.height).astype(int)
        windows = []
        for b, depths in enumerate(p_c[..., 2]):
            if depths.max() <= 0 or (depths.min() >= 1e-3 and (u0[b] >= u1[b] or v0[b] >= v1[b])):
                windows.append(None)
            elif depths.min() < 1e-3:
                windows.append((slice(None), slice(None)))
            else:
                windows.append((slice(v0[b], v1[b]), slice(u0[b], u1[b])))
        return windows

    def mesh(self) -> trimesh.Trimesh:
        """The exact scene surface in world metres: room faces point inward, furniture outward.

        Furniture bottoms (lying on the floor) are left out; each face is coloured with its
        texture's mean colour.
        """
        boxes = np.concatenate([self.room[None], self.furniture])
        vertices, triangles, colours = [], [], []
        for f, normal in enumerate(self._normal):
            b, k = divmod(f, 6)
            axis, a, c = k // 2, (k // 2 + 1) % 3, (k // 2 + 2) % 3
            if b > 0 and axis == 2 and k % 2 == 0:
                continue
            lo, hi = boxes[b]
            quad = np.zeros((4, 3))
            quad[:, axis] = boxes[b][k % 2, axis]
            quad[:, a] = [lo[a], hi[a], hi[a], lo[a]]
            quad[:, c] = [lo[c], lo[c], hi[c], hi[c]]
            # The quad winds counter-clockwise about +axis; flipped for faces facing the other way.
            tris = (
                np.array([[0, 1, 2], [0, 2, 3]])
                if normal[axis] > 0
                else np.array([[0, 2, 1], [0, 3, 2]])
            )
            triangles.append(tris + 4 * len(vertices))
            vertices.append(quad)
            mean = _texture_image(list(_TEXTURES)[self._tex[f]]).reshape(-1, 3).mean(0)
            colour = np.clip(mean * self._colour[f], 0, 1)
            colours += [np.append(colour * 255, 255).astype(np.uint8)] * 2
        return trimesh.Trimesh(
            np.concatenate(vertices), np.concatenate(triangles), face_colors=colours, process=False
        )

    def path(self, frames: int) -> np.ndarray:
        """A smooth handheld-like camera path at 30 Hz.

        The centre walks a closed loop through the free middle of the room at about 1 to 2 cm per
        frame; the view pans steadily round the walls with smooth sway in yaw, pitch and roll,
        staying under 1 degree per frame and looking slightly down.

        Args:
            frames: number of poses, >= 1.

        Returns:
            `(frames, 4, 4)` float64 `T_wc`, OpenCV camera axes.
        """
        _check_count("frames", frames, 1)
        rng = np.random.default_rng([self.seed, 1])
        i = np.arange(frames, dtype=np.float64)
        # An ellipse, either way round, with too little of its 2nd and 3rd harmonics to make a
        # cusp; stretched to fill the camera box and walked by arc length.
        theta = np.linspace(0, 2 * np.pi, 4097) * rng.choice([-1, 1])
        amp, phase = rng.uniform([0.05, 0.0], [0.15, 0.05]), rng.uniform(0, 2 * np.pi, (2, 2))
        loop = [np.cos(theta), np.sin(theta)]
        for k in range(2):
            loop[0] = loop[0] + amp[k] * np.cos((k + 2) * theta + phase[0, k])
            loop[1] = loop[1] + amp[k] * np.sin((k + 2) * theta + phase[1, k])
        loop.append(np.sin(rng.integers(1, 3) * theta + rng.uniform(0, 2 * np.pi)))
        lo, hi = _CAMERA_BOX[0] + 0.02, _CAMERA_BOX[1] - 0.02  # room for the hand's bob
        loop = np.stack(
            [lo[j] + (c - c.min()) / np.ptp(c) * (hi[j] - lo[j]) for j, c in enumerate(loop)], 1
        )
        arc = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(loop, axis=0), axis=1))])
        s = (
            rng.uniform(0, arc[-1])
            + 0.015 * i
            + 0.09 * np.sin(2 * np.pi * i / 150 + rng.uniform(0, 2 * np.pi))
        )
        centre = np.stack([np.interp(s % arc[-1], arc, loop[:, j]) for j in range(3)], 1)
        centre[:, 2] += 0.01 * np.sin(2 * np.pi * i / 28)

        yaw = (
            rng.uniform(0, 2 * np.pi)
            + rng.choice([-1, 1]) * np.radians(0.4) * i
            + _sway(rng, i, 15, rng.uniform(280, 340))
        )
        pitch = np.radians(-12) + _sway(rng, i, 7, rng.uniform(200, 260)) + _sway(rng, i, 1, 45)
        roll = _sway(rng, i, 3, rng.uniform(150, 190)) + _sway(rng, i, 0.7, 37)
        return _orient(centre, yaw, pitch, roll)

    def loop_path(self, frames: int, turns: float = 1.1) -> np.ndarray:
        """A walk once round the room that comes back to where it started, looking outwards.

        The centre goes `turns` times round an ellipse through the free middle of the room,
        the view always facing away from the room's middle (so the heading turns with it), with
        gentle sway; the frames after the first turn see again what the first frames saw, which
        is what a loop closure needs. `frames` sets the speed: 300 frames walk about 1.7 cm and
        turn about 1.3 degrees per frame.

        Args:
            frames: number of poses, >= 2.
            turns: rounds walked, > 0.

        Returns:
            `(frames, 4, 4)` float64 `T_wc`, OpenCV camera axes.
        """
        _check_count("frames", frames, 2)
        if not np.isfinite(turns) or turns <= 0:
            raise DimslamError(f"turns must be > 0, got {turns}")
        rng = np.random.default_rng([self.seed, 3])
        i = np.arange(frames, dtype=np.float64)
        phi = rng.uniform(0, 2 * np.pi) + rng.choice([-1, 1]) * 2 * np.pi * turns * i / (frames - 1)
        mid, half = _CAMERA_BOX.mean(0), 0.45 * np.ptp(_CAMERA_BOX, axis=0)
        centre = np.stack(
            [
                mid[0] + half[0] * np.cos(phi),
                mid[1] + half[1] * np.sin(phi),
                mid[2] + 0.05 * np.sin(2 * np.pi * i / 40),
            ],
            1,
        )

        yaw = phi + _sway(rng, i, 8, rng.uniform(90, 130))
        pitch = np.radians(-10) + _sway(rng, i, 4, rng.uniform(70, 110))
        roll = _sway(rng, i, 2, rng.uniform(60, 90))
        return _orient(centre, yaw, pitch, roll)


def _sway(rng: np.random.Generator, i: np.ndarray, degrees: float, period: float) -> np.ndarray:
    """A hand's slow sway: `degrees` amplitude over `period` frames at frames `i`, in radians,
    with a random phase drawn from `rng`."""
    return np.radians(degrees) * np.sin(2 * np.pi * i / period + rng.uniform(0, 2 * np.pi))


def _orient(centre: np.ndarray, yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """`(n, 4, 4)` camera-to-world poses (OpenCV axes, world z up) at `centre` looking along
    `yaw` (about z, from +x), `pitch` (up positive) and `roll` (about the optical axis)."""
    forward = np.stack([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)], 1)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right, axis=1, keepdims=True)
    down = np.cross(forward, right)
    c, s = np.cos(roll)[:, None], np.sin(roll)[:, None]
    T = np.zeros((len(centre), 4, 4))
    T[:, :3, 0] = c * right + s * down  # roll about the optical axis
    T[:, :3, 1] = -s * right + c * down
    T[:, :3, 2] = forward
    T[:, :3, 3] = centre
    T[:, 3, 3] = 1
    return T


def _place_furniture(rng: np.random.Generator) -> tuple[list[str], list[np.ndarray]]:
    """Five or six non-overlapping boxes against the walls, each within reach of its wall."""
    names, boxes = [], []
    wanted = rng.choice(list(_FURNITURE), size=rng.integers(5, 7), replace=True)
    for name in wanted:
        (l0, l1), (d0, d1), (h0, h1) = _FURNITURE[name]
        for _ in range(100):
            length, depth, height = rng.uniform(l0, l1), rng.uniform(d0, d1), rng.uniform(h0, h1)
            wall = rng.integers(4)  # y = min, y = max, x = min, x = max
            along, across = (0, 1) if wall < 2 else (1, 0)
            side = wall % 2
            lo, hi = np.zeros(3), np.array([0, 0, height])
            start = rng.uniform(0.05, ROOM[1, along] - length - 0.05)
            lo[along], hi[along] = start, start + length
            gap = rng.uniform(0.02, _FURNITURE_REACH - depth)
            edge = ROOM[1, across] - gap if side else gap
            lo[across], hi[across] = (edge - depth, edge) if side else (edge, edge + depth)
            # 15 cm between pieces so that no two faces touch or interpenetrate.
            if all(np.any((lo[:2] > b[1, :2] + 0.15) | (hi[:2] < b[0, :2] - 0.15)) for b in boxes):
                names.append(str(name))
                boxes.append(np.stack([lo, hi]))
                break
    return names, boxes


@dataclass(frozen=True)
class SynthSummary:
    """What `write_sequence` wrote and how fast.

    Attributes:
        out_dir: the sequence folder.
        frames: frames written.
        width: image width in pixels.
        height: image height in pixels.
        seed: scene and path seed.
        camera: the intrinsics written to `calib.txt`.
        seconds: wall time to render and write everything.
        fps: frames per second over `seconds`.
    """

    out_dir: Path
    frames: int
    width: int
    height: int
    seed: int
    camera: Camera
    seconds: float
    fps: float


def write_sequence(
    out_dir: str | Path,
    frames: int = 300,
    width: int = 320,
    height: int = 240,
    seed: int = 0,
    noise: float = 1.0,
    progress: Callable[[int, int], None] | None = None,
    path: str = "walk",
) -> SynthSummary:
    """Render the scene along its path and write a TUM RGB-D sequence.

    Writes `rgb/<ts>.png` (8-bit RGB), `depth/<ts>.png` (uint16 z-depth, 5000 per metre),
    `rgb.txt`, `depth.txt`, `groundtruth.txt` (TUM, camera-to-world), `calib.txt` (`fx fy cx cy`)
    and `mesh.ply` (world metres). Timestamps are `1.0 + i / 30` s, written `%.6f`.

    Args:
        out_dir: output folder; created if missing, else empty or a previous synth output
            (whose frames are replaced).
        frames: number of frames, >= 1.
        width: image width in pixels, >= 8.
        height: image height in pixels, >= 8.
        seed: scene and path seed.
        noise: Gaussian sensor noise sigma in 8-bit levels (0 for none), drawn from `seed`.
        progress: called as `progress(i, frames)` after frame `i` (0-based) is written.
        path: `walk` (`SynthScene.path`) or `loop` (`SynthScene.loop_path`: round the room and
            back to the start).

    Returns:
        The summary, with timing.

    Raises:
        DimslamError: on bad arguments or an output folder that holds other files.
    """
    out = Path(out_dir)
    start = time.perf_counter()
    _check_arguments(out, frames, width, height, noise)
    if path not in PATHS:
        raise DimslamError(f"path must be one of {', '.join(PATHS)}, got {path!r}")
    scene = SynthScene(seed)
    camera = default_camera(width, height)
    poses = scene.path(frames) if path == "walk" else scene.loop_path(frames)
    stamps = 1.0 + np.arange(frames) / FPS
    names = [f"{ts:.6f}" for ts in stamps]
    for folder in ("rgb", "depth"):
        (out / folder).mkdir(parents=True, exist_ok=True)
        for old in (out / folder).glob("*.png"):
            old.unlink()
    # The index files go first: they mark the folder as ours even if rendering is interrupted.
    header = (
        f"{_MARKER}, seed {seed}, {width}x{height}, noise {noise:g}, path {path}\n"
        "# timestamp filename\n"
    )
    for folder in ("rgb", "depth"):
        lines = "".join(f"{n} {folder}/{n}.png\n" for n in names)
        (out / f"{folder}.txt").write_text(header + lines)
    (out / "calib.txt").write_text(
        f"{camera.fx:.4f} {camera.fy:.4f} {camera.cx:.4f} {camera.cy:.4f}\n"
    )
    write_tum(
        out / "groundtruth.txt",
        Trajectory(stamps, poses),
        header=f"dimslam synthetic room, seed {seed}: camera-to-world, OpenCV camera axes",
    )
    scene.mesh().export(out / "mesh.ply")
    rng = np.random.default_rng([int(seed), 2])
    for i, name in enumerate(names):
        rgb, depth = scene.render(poses[i], camera)
        levels = rgb * 255 + 0.5
        if noise > 0:
            levels += rng.standard_normal(levels.shape, dtype=np.float32) * np.float32(noise)
        bgr = np.clip(levels, 0, 255).astype(np.uint8)[..., ::-1]
        cv2.imwrite(str(out / "rgb" / f"{name}.png"), bgr)
        depth_units = np.clip(depth * DEPTH_SCALE + 0.5, 0, 65535).astype(np.uint16)
        cv2.imwrite(str(out / "depth" / f"{name}.png"), depth_units)
        if progress is not None:
            progress(i, frames)
    seconds = time.perf_counter() - start
    log.debug(
        "wrote %d synthetic frames %dx%d to %s in %.2f s", frames, width, height, out, seconds
    )
    return SynthSummary(out, frames, width, height, int(seed), camera, seconds, frames / seconds)


def _check_count(name: str, value: int, least: int) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
        raise DimslamError(f"{name} must be an integer >= {least}, got {value!r}")


def _check_arguments(out: Path, frames: int, width: int, height: int, noise: float) -> None:
    _check_count("frames", frames, 1)
    _check_count("width", width, 8)
    _check_count("height", height, 8)
    if not np.isfinite(noise) or noise < 0:
        raise DimslamError(f"noise must be a finite sigma >= 0 (8-bit levels), got {noise}")
    if out.exists() and not out.is_dir():
        raise DimslamError(f"{out}: exists and is not a folder")
    if not out.exists() or not any(out.iterdir()):
        return
    entries = {p.name for p in out.iterdir()}
    index = out / "rgb.txt"
    ours = entries <= _OUTPUT_NAMES and index.is_file() and index.read_text().startswith(_MARKER)
    if not ours:
        raise DimslamError(
            f"{out}: folder is not empty and is not a previous synthetic sequence; "
            "choose an empty or new folder"
        )

"""Direct tracking of the newest frame: Gauss-Newton on SE(3) over an image pyramid.

The cost of a frame is set by the frame, not by a window: the newest pose is solved against
the keyframes' points, whose depth the map rendered once and whose intensities the keyframes
observed (DSO's coarse tracker, with the map in place of DSO's keyframe depth):

- A *reference* is one keyframe's high-gradient pixels with the depth the map renders for
  them, stored in the keyframe's own camera frame, so refined keyframe poses carry them along.
  References are rendered when a new map arrives (`map_changed`: the newest keyframes) or on
  demand when no rendered keyframe overlaps the frame enough; never on every frame.
- A frame is tracked against the few references that overlap its motion guess best. The
  solve is Levenberg-Marquardt on the pose (a left increment on `T_cw`) and, per reference, an
  affine brightness `I_frame = a * I_keyframe + b` (real cameras change exposure), with
  analytic Jacobians (the frame's image gradient times the projection's), Huber weights, coarse
  to fine over a pyramid of the frame's grey image, and an early stop once the step is small.
- The solve fails (`TrackingLost`) when the frame has too little texture to align, when too
  few points stay in view, when the robust residual stays high or few points fit, or when
  anything turns non-finite; the front end then relocalizes.

Whether a frame becomes a keyframe is decided on the same points: their reprojection flow
between the last keyframe and the frame, and how many of those the last keyframe sees stay in
view. Nothing is rendered per frame.
"""

from __future__ import annotations

import math
import statistics
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F

from dimslam.common.geometry import pose
from dimslam.common.geometry.camera import Camera
from dimslam.common.map.render import FieldFn, RenderConfig, render_pixels
from dimslam.common.optim import losses
from dimslam.common.optim.window import FrameState, TrackingLost, WindowStats
from dimslam.tracker.tracker import TrackerConfig, TrackResult

GREY = (0.299, 0.587, 0.114)
PROBE = 64
"""Points of a reference that estimate its overlap with a view."""
MIN_POINTS = 30
"""Fewest points in view for a solve to count at all."""
BRIGHTNESS_PRIOR = 1e-2
"""Weight of the prior that holds each reference's affine brightness near (1, 0), against
the data's own weights of ~0.01-0.04 for the gain (the intensities' variance about their
mean) and ~1 for the offset: the offset follows an exposure change, the gain stays near 1
(a gain of 0.7 in a unit test came out at 0.97, the pose within 5 mm; with a prior of 1e-3
the pose was 1 cm off)."""
GAIN_RANGE = (0.75, 1 / 0.75)
OFFSET_RANGE = (-0.2, 0.2)
PRIOR_BRIGHTNESS = np.array([1.0, 0.0])
"""Bounds of a reference's brightness against the frame: a few frames apart, exposure changes
less than that. Unbounded, a misaligned solve can lower the gain towards 0, which flattens the
residuals of any pose: on room0's frame 111 (oracle map, prior 1e-4) the gain fell to 0.1 and
the pose slid 40 cm along a textured wall."""
MIN_TEXTURE = 0.25
"""A frame whose mean image gradient is below this share of its keyframes' has nothing to
align (a covered lens, a dark or heavily blurred frame): it is lost without a solve, which
would otherwise settle wherever the brightness model flattens the residuals best."""
RELOC_STEP = 0.05
"""The relocalization search's step along a camera axis, as a share of the scene's depth."""
RELOC_TURN = math.radians(5.0)
"""The relocalization search's turn about a camera axis."""
RELOC_COARSE_ITERS = 3
"""Iterations each move of the relocalization search gets on the coarsest level."""
RELOC_SOLVES = 3
"""Full solves from the best moves of the search."""
MARGIN = 2.0
"""Points closer than this (level pixels) to the border are out of view: their gradient is
one-sided there."""


@dataclass
class Reference:
    """One keyframe's points with the depth the map gave them.

    Attributes:
        keyframe: the keyframe (its current pose places the points in the world).
        p_k: `(N, 3)` points in the keyframe's camera frame.
        intensity: per pyramid level, `(N,)` the keyframe's grey value at each point.
        version: the map version the depth was rendered from.
        texture: the keyframe image's mean absolute gradient (`texture`).
    """

    keyframe: FrameState
    p_k: torch.Tensor
    intensity: list[torch.Tensor]
    version: int
    texture: float

    def world(self) -> torch.Tensor:
        """`(N, 3)` the points in the world at the keyframe's current pose."""
        return pose.transform_points(self.keyframe.T_wc, self.p_k)


@dataclass
class DirectStats(WindowStats):
    """What a direct solve did, beyond the window statistics."""

    points: int = 0
    inliers: float = math.nan
    residual: float = math.nan
    references: tuple[int, ...] = ()
    rendered: int = 0
    per_level: list[int] = field(default_factory=list)


def grey(rgb: torch.Tensor) -> torch.Tensor:
    """`(H, W)` grey image of an `(H, W, 3)` one."""
    return rgb @ rgb.new_tensor(GREY)


def pyramid(image: torch.Tensor, levels: int) -> list[torch.Tensor]:
    """`levels` grey images, each half the size of the one before (2x2 means)."""
    out = [image]
    for _ in range(levels - 1):
        if min(out[-1].shape) < 16:
            break
        out.append(F.avg_pool2d(out[-1][None, None], 2)[0, 0])
    return out


def with_gradients(image: torch.Tensor) -> torch.Tensor:
    """`(H, W, 3)`: the grey image and its central differences along u and v."""
    padded = F.pad(image[None, None], (1, 1, 1, 1), mode="replicate")[0, 0]
    gu = 0.5 * (padded[1:-1, 2:] - padded[1:-1, :-2])
    gv = 0.5 * (padded[2:, 1:-1] - padded[:-2, 1:-1])
    return torch.stack([image, gu, gv], dim=-1)


def texture(image: torch.Tensor) -> float:
    """Mean absolute gradient of a `with_gradients` image: how much there is to align."""
    return float(image[..., 1:].abs().mean())


def level_uv(uv: torch.Tensor, level: int) -> torch.Tensor:
    """Level-0 pixel coordinates at pyramid `level` (pixel centres stay pixel centres)."""
    s = 0.5**level
    return (uv + 0.5) * s - 0.5


class DirectTracker:
    """Solves the newest frame's pose against rendered keyframe points."""

    def __init__(
        self,
        cfg: TrackerConfig,
        render_cfg: RenderConfig,
        camera: Camera,
        generator: torch.Generator,
    ) -> None:
        self.cfg = cfg
        self.render_cfg = render_cfg
        self.camera = camera
        self.generator = generator
        self.cameras: list[Camera] = []
        size = camera
        for _ in range(cfg.levels):
            self.cameras.append(size)
            if min(size.width, size.height) < 32:
                break
            size = camera.resized(size.width // 2, size.height // 2)
        self.references: dict[int, Reference] = {}
        self.brightness: dict[int, tuple[float, float]] = {}
        self.version = 0
        self.last_points: torch.Tensor | None = None

    # -- references ---------------------------------------------------------------------------

    def map_changed(self, field: FieldFn, keyframes: list[FrameState], version: int) -> int:
        """A new map: render the newest keyframes' references again. Returns how many."""
        self.version = version
        keep = {kf.index for kf in keyframes}
        for index in [i for i in self.references if i not in keep]:
            del self.references[index]  # no longer a keyframe (a new stream, a reset)
        rendered = 0
        for kf in keyframes[-self.cfg.references :]:
            if kf.rgb is not None and self._stale(kf):
                self.render(field, kf)
                rendered += 1
        return rendered

    def _stale(self, kf: FrameState) -> bool:
        ref = self.references.get(kf.index)
        return ref is None or ref.version < self.version

    def render(self, field: FieldFn, kf: FrameState) -> Reference:
        """Render the depth of `kf`'s high-gradient pixels and keep them as a reference."""
        assert kf.rgb is not None
        uv = losses.high_gradient_pixels(kf.rgb, self.cfg.ref_points, self.generator, 2)
        uv = torch.unique(uv, dim=0).float()
        with torch.no_grad():
            out = render_pixels(field, self.camera, uv, kf.T_wc, self.render_cfg, with_color=False)
        good = torch.isfinite(out.depth) & (out.depth > 0) & (out.opacity > 0.5)
        uv, depth = uv[good], out.depth[good]
        images = pyramid(grey(kf.rgb), len(self.cameras))
        intensity = [
            losses.sample_images(img[..., None].expand(-1, -1, 3), level_uv(uv, lv))[:, 0]
            for lv, img in enumerate(images)
        ]
        ref = Reference(
            kf,
            self.camera.unproject(uv, depth),
            intensity,
            self.version,
            texture(with_gradients(images[0])),
        )
        self.references[kf.index] = ref
        return ref

    def _overlaps(self, refs: list[Reference], T_cw: torch.Tensor) -> list[float]:
        """Per reference, the share of its points in front of the camera at `T_cw` and inside
        its image, estimated on its first `PROBE` points (in random order), all in one pass."""
        if not refs:
            return []
        T_ck = pose.compose(T_cw, torch.stack([r.keyframe.T_wc for r in refs]))  # (R, 4, 4)
        probes = torch.stack([r.p_k[torch.arange(PROBE) % len(r.p_k)] for r in refs])
        uv, z = self.camera.project(pose.transform_points(T_ck, probes))  # (R, PROBE, ...)
        return ((z > 0) & self.camera.inside(uv)).float().mean(dim=1).tolist()

    def choose(
        self, field: FieldFn, keyframes: list[FrameState], T_wc: torch.Tensor
    ) -> tuple[list[Reference], int]:
        """The newest keyframe's reference and the others that overlap the view at `T_wc`
        best, and how many were rendered for it.

        The newest keyframe is the one a new frame overlaps most, so it is rendered as soon as
        it is needed (the frame after it became a keyframe), not at the next map.
        """
        T_cw = pose.invert(T_wc)
        rendered = 0
        newest = keyframes[-1] if keyframes else None
        if newest is not None and newest.index not in self.references and newest.rgb is not None:
            self.render(field, newest)
            rendered = 1
        # A keyframe where the map has no surface yet has too few points to count.
        refs = [r for r in self.references.values() if len(r.p_k) >= MIN_POINTS]
        scored = list(zip(self._overlaps(refs, T_cw), refs, strict=True))
        first = [(s, r) for s, r in scored if newest is not None and r.keyframe is newest]
        others = sorted(
            ((s, r) for s, r in scored if r.keyframe is not newest and s > 0.05),
            key=lambda sr: (sr[0], sr[1].keyframe.index),
            reverse=True,
        )
        chosen = [r for s, r in [*first, *others] if s > 0.05]
        return chosen[: self.cfg.references], rendered

    # -- the solve ----------------------------------------------------------------------------

    def track(
        self, field: FieldFn, local: list[FrameState], keyframes: list[FrameState]
    ) -> TrackResult:
        """Solve the pose of `local[-1]` (it enters at its guess); write it back.

        Raises:
            TrackingLost: no reference overlaps the guess, too few points stay in view, the
                residual stays high, or the solve turns non-finite; the frame keeps its guess.
        """
        frame = local[-1]
        refs, rendered = self.choose(field, keyframes, frame.T_wc)
        if not refs:
            raise TrackingLost(f"frame {frame.index}: no rendered keyframe overlaps its view")
        solved = self.solve(frame, refs, self.images(frame))
        solved.stats.rendered = rendered
        return self._accept(frame, solved)

    def relocalize(
        self,
        field: FieldFn,
        local: list[FrameState],
        keyframes: list[FrameState],
        starts: list[torch.Tensor],
        max_residual: float,
    ) -> TrackResult:
        """Place `local[-1]` after a loss: a coarse search around each start, then full solves
        from the `RELOC_SOLVES` best, and the solution with the lowest residual if it is at
        most `max_residual`.

        The coarse search tries each start and `RELOC_STEPS` shifts of it (along the camera
        axes, by a share of the scene's depth, and turns about them), each for a few
        iterations on the coarsest level only, where a solve is cheapest and its basin widest.

        Raises:
            TrackingLost: no start leads to a solution that good.
        """
        frame = local[-1]
        images = self.images(frame)
        level = len(images) - 1
        coarse: list[tuple[float, np.ndarray, list[Reference]]] = []
        for start in starts:
            refs, _ = self.choose(field, keyframes, start)
            if not refs:
                continue
            problem = self._problem(images, refs, self._points(refs), level)
            depth = float(torch.cat([r.p_k[:, 2] for r in refs]).median())
            ab = self._brightness(refs)
            for shift in _shifts(depth):
                T_cw = shift @ np.linalg.inv(start.double().cpu().numpy())
                T_cw, _, _, cost = problem.minimize(T_cw, ab, RELOC_COARSE_ITERS)
                coarse.append((cost, T_cw, refs))
        coarse.sort(key=lambda c: c[0])
        best: _Solved | None = None
        error = f"frame {frame.index}: no rendered keyframe overlaps any start"
        for _, T_cw, refs in coarse[:RELOC_SOLVES]:
            frame.T_wc = _to_tensor(np.linalg.inv(T_cw), frame.T_wc)
            try:
                solved = self.solve(frame, refs, images)
            except TrackingLost as e:
                error = str(e)
                continue
            if best is None or solved.stats.residual < best.stats.residual:
                best = solved
        if best is None:
            raise TrackingLost(error)
        if best.stats.residual > max_residual:
            raise TrackingLost(
                f"frame {frame.index}: best residual {best.stats.residual:.3f} > "
                f"{max_residual:.3f} of the frames tracked before"
            )
        return self._accept(frame, best)

    def images(self, frame: FrameState) -> list[torch.Tensor]:
        """The frame's grey pyramid with the gradients, finest first."""
        assert frame.rgb is not None
        return [with_gradients(img) for img in pyramid(grey(frame.rgb), len(self.cameras))]

    def _brightness(self, refs: list[Reference]) -> np.ndarray:
        """`(R, 2)` the last gain and offset of each reference against the frames."""
        return np.array([self.brightness.get(r.keyframe.index, (1.0, 0.0)) for r in refs])

    def _points(self, refs: list[Reference]) -> _Points:
        """The references' points in one random order (the coarse levels use its first)."""
        order = torch.randperm(sum(len(r.p_k) for r in refs), generator=self.generator)
        ref_of = torch.cat(
            [torch.full((len(r.p_k),), k, dtype=torch.long) for k, r in enumerate(refs)]
        )
        # The brightness model works on intensities about each reference's mean, so that the
        # gain scales contrast only and the offset carries the shift of the mean.
        mean = torch.cat([r.intensity[0].mean().expand(len(r.p_k)) for r in refs])
        p_w = torch.cat([r.world() for r in refs])
        return _Points(order, p_w[order], ref_of[order], mean[order])

    def _problem(
        self, images: list[torch.Tensor], refs: list[Reference], pts: _Points, level: int
    ) -> _Problem:
        """The solve's problem at one pyramid level: the finest takes every point, each
        coarser one a quarter of those of the level below, at least 300."""
        total = len(pts.p_w)
        n = total if level == 0 else min(total, max(300, total >> (2 * level)))
        centred = torch.cat([r.intensity[level] for r in refs])[pts.order] - pts.mean
        return _Problem(
            images[level],
            self.cameras[level],
            pts.p_w[:n],
            centred[:n],
            pts.mean[:n],
            pts.ref_of[:n],
            len(refs),
            self.cfg,
        )

    def solve(
        self, frame: FrameState, refs: list[Reference], images: list[torch.Tensor]
    ) -> _Solved:
        """Levenberg-Marquardt from `frame.T_wc` against `refs`, coarse to fine; checked but
        not yet applied (`_accept`).

        Raises:
            TrackingLost: the solution is non-finite, sees too few points, jumped too far
                from the start, or leaves the residual high.
        """
        seen = texture(images[0]) / max(statistics.fmean(r.texture for r in refs), 1e-12)
        if seen < MIN_TEXTURE:
            raise TrackingLost(
                f"frame {frame.index}: {seen:.0%} of the keyframes' texture (covered, blurred "
                "or dark)"
            )
        pts = self._points(refs)
        ab = self._brightness(refs)
        T_cw = np.linalg.inv(frame.T_wc.double().cpu().numpy())
        stats = DirectStats(references=tuple(r.keyframe.index for r in refs), points=len(pts.p_w))
        budget = self.cfg.iters
        finest = None
        for level in reversed(range(len(images))):
            finest = self._problem(images, refs, pts, level)
            # A fair share of the iterations left; what a level leaves unused passes on.
            T_cw, ab, used, cost = finest.minimize(T_cw, ab, max(1, budget // (level + 1)))
            budget -= used
            stats.per_level.append(used)
            stats.iterations += used
            stats.history.append(cost)
        assert finest is not None
        check = finest.evaluate(T_cw, ab)
        n_valid = int(check.valid.sum())
        rv = check.r[check.valid]
        residual = math.sqrt(2 * finest.huber_mean(rv)) if n_valid else math.inf
        inliers = float((rv.abs() <= self.cfg.huber).float().mean()) if n_valid else 0.0
        stats.loss = stats.residual = residual
        stats.inliers = inliers
        if not (np.isfinite(T_cw).all() and math.isfinite(residual)):
            raise TrackingLost(f"frame {frame.index}: the solve became non-finite")
        T_wc = _to_tensor(np.linalg.inv(T_cw), frame.T_wc)
        if n_valid < MIN_POINTS:
            raise TrackingLost(f"frame {frame.index}: {n_valid} points in view")
        jump = self._flow(pts.p_w, pose.invert(frame.T_wc), pose.invert(T_wc))
        if jump > self.cfg.max_jump_px:
            raise TrackingLost(
                f"frame {frame.index}: the solve moved the view {jump:.0f} px from its guess"
            )
        if residual > self.cfg.lost_residual or inliers < self.cfg.min_inliers:
            raise TrackingLost(
                f"frame {frame.index}: residual {residual:.3f}, {inliers:.0%} inliers"
            )
        return _Solved(T_wc, ab, stats, refs, pts.p_w)

    def _accept(self, frame: FrameState, solved: _Solved) -> TrackResult:
        """Give the frame its solved pose; keep the brightness and points for the next."""
        frame.T_wc = solved.T_wc
        for k, r in enumerate(solved.refs):
            self.brightness[r.keyframe.index] = (float(solved.ab[k, 0]), float(solved.ab[k, 1]))
        self.last_points = solved.p_w
        stats = solved.stats
        return TrackResult(frame.index, frame.T_wc, stats, (*stats.references, frame.index))

    def _flow(self, p_w: torch.Tensor, T_a: torch.Tensor, T_b: torch.Tensor) -> float:
        """Mean displacement (pixels) of the points in view between cameras `T_a`, `T_b` (cw)."""
        uv_a, z_a = self.camera.project(pose.transform_points(T_a, p_w))
        uv_b, z_b = self.camera.project(pose.transform_points(T_b, p_w))
        both = (z_a > 0) & (z_b > 0) & self.camera.inside(uv_a) & self.camera.inside(uv_b)
        return float((uv_a[both] - uv_b[both]).norm(dim=-1).mean()) if both.any() else math.inf

    # -- keyframes ----------------------------------------------------------------------------

    def is_keyframe(self, field: FieldFn, frame: FrameState, last_keyframe: FrameState) -> bool:
        """Whether `frame` becomes a keyframe (rules as `Tracker.is_keyframe`), measured on the
        points of the last solve: their mean reprojection flow between the last keyframe and
        the frame, and the share of those the keyframe sees that the frame still sees."""
        if self.last_points is None:
            return False
        cam, points = self.camera, self.last_points

        def view(T_wc: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            uv, z = cam.project(pose.transform_points(pose.invert(T_wc), points))
            return uv, (z > 0) & cam.inside(uv)

        uv_k, in_k = view(last_keyframe.T_wc)
        uv_f, in_f = view(frame.T_wc)
        if not bool(in_k.any()):
            return True
        overlap = float(in_f[in_k].float().mean())
        if overlap < self.cfg.keyframe_overlap:
            return True
        both = in_k & in_f
        flow = (uv_f[both] - uv_k[both]).norm(dim=-1).mean()
        return float(flow) > self.cfg.keyframe_flow_px


@dataclass
class _Points:
    """The points of a solve's references, in one random order."""

    order: torch.Tensor
    p_w: torch.Tensor
    ref_of: torch.Tensor  # which reference each point is of
    mean: torch.Tensor  # its reference's mean intensity


@dataclass
class _Solved:
    """A checked solution, not yet applied."""

    T_wc: torch.Tensor
    ab: np.ndarray
    stats: DirectStats
    refs: list[Reference]
    p_w: torch.Tensor


def _to_tensor(T_wc: np.ndarray, like: torch.Tensor) -> torch.Tensor:
    return pose.normalize(torch.from_numpy(T_wc).float().to(like.device))


def _shifts(depth: float) -> list[np.ndarray]:
    """The relocalization search's moves of a start (left-multiplied onto `T_cw`): none,
    `RELOC_STEP` and twice that of the scene depth along each camera axis, and
    `RELOC_TURN` about each axis."""
    moves = [np.eye(4)]
    for axis in range(3):
        for sign in (-1.0, 1.0):
            for k in (1.0, 2.0):
                xi = np.zeros(6)
                xi[axis] = sign * k * RELOC_STEP * depth
                moves.append(se3_exp(xi))
            xi = np.zeros(6)
            xi[3 + axis] = sign * RELOC_TURN
            moves.append(se3_exp(xi))
    return moves


@dataclass
class _Evaluation:
    """The residuals of one pose and brightness, with what their Jacobian needs."""

    r: torch.Tensor
    valid: torch.Tensor
    w: torch.Tensor
    cost: float
    p_c: torch.Tensor
    inv_z: torch.Tensor
    gradient: torch.Tensor  # (2, N): the frame's intensity gradient along u and v


class _Problem:
    """One pyramid level of a solve: the frame's image and the points' constants.

    Written for few operations per iteration (each torch call costs microseconds on a CPU,
    whatever its size): the pose and brightness live in numpy, the per-point work in one pass
    of float32 tensors, the affine part of the Jacobian is built once.
    """

    def __init__(
        self,
        image: torch.Tensor,
        camera: Camera,
        p_w: torch.Tensor,
        centred: torch.Tensor,
        mean: torch.Tensor,
        ref_of: torch.Tensor,
        n_refs: int,
        cfg: TrackerConfig,
    ) -> None:
        self.chw = image.permute(2, 0, 1)[None].contiguous()  # (1, 3, H, W)
        h, w = image.shape[:2]
        self.fx, self.fy, self.cx, self.cy = camera.fx, camera.fy, camera.cx, camera.cy
        self.box = (MARGIN - 0.5, w - 0.5 - MARGIN, MARGIN - 0.5, h - 0.5 - MARGIN)
        self.scale = (2.0 / max(w - 1, 1), 2.0 / max(h - 1, 1))
        self.p_w, self.centred, self.mean, self.ref_of = p_w, centred, mean, ref_of
        self.huber = cfg.huber
        # A step this small moves no point by a tenth of a pixel at this level (at 2 map units
        # of depth): the level has converged.
        self.converged = 0.1 / camera.fx * 2.0
        self.n_refs = n_refs
        self.affine = cfg.affine
        if self.affine:  # columns: the gains of the references, then their offsets
            onehot = F.one_hot(ref_of, n_refs).to(p_w.dtype)
            self.A = torch.cat([-centred[:, None] * onehot, -onehot], dim=1)

    def huber_mean(self, r: torch.Tensor) -> float:
        k = self.huber
        a = r.abs()
        return float(torch.where(a <= k, 0.5 * r * r, k * (a - 0.5 * k)).mean())

    def evaluate(self, T_cw: np.ndarray, ab: np.ndarray) -> _Evaluation:
        R = torch.from_numpy(T_cw[:3, :3]).to(self.p_w.dtype)
        t = torch.from_numpy(T_cw[:3, 3]).to(self.p_w.dtype)
        p_c = torch.addmm(t, self.p_w, R.T)
        x, y, z = p_c.unbind(1)
        inv_z = 1.0 / z.clamp_min(1e-3)
        u = self.fx * x * inv_z + self.cx
        v = self.fy * y * inv_z + self.cy
        u0, u1, v0, v1 = self.box
        valid = (z > 1e-3) & (u >= u0) & (u <= u1) & (v >= v0) & (v <= v1)
        sx, sy = self.scale
        grid = torch.stack([u * sx - 1.0, v * sy - 1.0], dim=-1).view(1, 1, -1, 2)
        sample = F.grid_sample(self.chw, grid, mode="bilinear", align_corners=True)[0, :, 0]
        gains = torch.from_numpy(ab[:, 0]).to(self.p_w.dtype)[self.ref_of]
        offsets = torch.from_numpy(ab[:, 1]).to(self.p_w.dtype)[self.ref_of]
        r = sample[0] - (gains * self.centred + self.mean + offsets)
        k = self.huber
        a = r.abs()
        rho = torch.where(a <= k, 0.5 * r * r, k * (a - 0.5 * k))
        # Points out of view count as outliers at the threshold, so leaving it earns nothing.
        rho = torch.where(valid, rho, torch.full_like(rho, 0.5 * k * k))
        w = torch.where(a <= k, torch.ones_like(a), k / a.clamp_min(1e-12)) * valid
        drift = (ab - PRIOR_BRIGHTNESS).reshape(-1)
        cost = float(rho.mean()) + 0.5 * BRIGHTNESS_PRIOR * float(drift @ drift) * self.affine
        return _Evaluation(r, valid, w, cost, p_c, inv_z, sample[1:])

    def normal_equations(self, e: _Evaluation, ab: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """`H` and `g` of the weighted least squares in (pose increment, gains, offsets)."""
        x, y, z = e.p_c.unbind(1)
        gu = e.gradient[0] * self.fx * e.inv_z
        gv = e.gradient[1] * self.fy * e.inv_z
        gz = -(gu * x + gv * y) * e.inv_z  # d r / d p_c = (gu, gv, gz)
        # Left increment of T_cw: d p_c / d v = I, d p_c / d w = -[p_c]x.
        J = torch.stack([gu, gv, gz, y * gz - z * gv, z * gu - x * gz, x * gv - y * gu], dim=1)
        if self.affine:
            J = torch.cat([J, self.A], dim=1)
        Jw = J * e.w[:, None]
        n = len(e.r)
        H = (Jw.T @ J).double().numpy() / n
        g = (Jw.T @ e.r).double().numpy() / n
        if self.affine:
            H[6:, 6:] += BRIGHTNESS_PRIOR * np.eye(H.shape[0] - 6)
            g[6:] += BRIGHTNESS_PRIOR * (ab - PRIOR_BRIGHTNESS).T.reshape(-1)
        return H, g

    def minimize(
        self, T_cw: np.ndarray, ab: np.ndarray, budget: int
    ) -> tuple[np.ndarray, np.ndarray, int, float]:
        """Levenberg-Marquardt; returns pose, brightness, iterations used and final cost."""
        damping = 1e-3
        current = self.evaluate(T_cw, ab)
        used = 0
        while used < budget:
            used += 1
            H, g = self.normal_equations(current, ab)
            H_lm = H + damping * np.diag(np.maximum(np.diag(H), 1e-12))
            try:
                step = -np.linalg.solve(H_lm, g)
            except np.linalg.LinAlgError:
                break
            if not np.isfinite(step).all():
                break
            T_new = se3_exp(step[:6]) @ T_cw
            ab_new = ab
            if self.affine:
                ab_new = ab + step[6:].reshape(2, -1).T
                ab_new[:, 0] = ab_new[:, 0].clip(*GAIN_RANGE)
                ab_new[:, 1] = ab_new[:, 1].clip(*OFFSET_RANGE)
            candidate = self.evaluate(T_new, ab_new)
            if candidate.cost <= current.cost:
                T_cw, ab, current = T_new, ab_new, candidate
                damping = max(damping * 0.5, 1e-6)
                if max(np.abs(step[:6])) < self.converged:
                    break
            else:
                damping *= 8.0
                if damping > 1e4:
                    break
        return T_cw, ab, used, current.cost


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """`(4, 4)` float64 pose of a twist `(v, w)` (numpy; `pose.exp_se3` for tensors)."""
    v, w = xi[:3], xi[3:]
    th2 = float(w @ w)
    W = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if th2 < 1e-10:
        A, B, C = 1.0 - th2 / 6.0, 0.5 - th2 / 24.0, 1.0 / 6.0 - th2 / 120.0
    else:
        th = math.sqrt(th2)
        A, B, C = math.sin(th) / th, (1.0 - math.cos(th)) / th2, (th - math.sin(th)) / (th2 * th)
    WW = W @ W
    T = np.eye(4)
    T[:3, :3] = np.eye(3) + A * W + B * WW
    T[:3, 3] = (np.eye(3) + B * W + C * WW) @ v
    return T

"""Direct tracking of the newest frame: Gauss-Newton on SE(3) over an image pyramid.

The cost of a frame is set by the frame, not by a window: the newest pose is solved against
the keyframes' points, whose depth the map rendered once and whose intensities the keyframes
observed (DSO's coarse tracker, with the map in place of DSO's keyframe depth):

- A *reference* is one keyframe's high-gradient pixels with the depth the map renders for
  them, stored in the keyframe's own camera frame, so refined keyframe poses carry them along.
  References are rendered when a new map arrives (`map_changed`: the newest keyframes), when
  a keyframe is new, and again when a frame is tracked against one whose depth an older map
  rendered (`tracker.refresh` of them per frame: the map keeps improving where the camera
  returns, and stale depth let the scale drift: room5 seed 0, 26.5 cm ATE without, 12.7 with).
- A frame is tracked against the newest keyframe's reference and those that overlap its
  motion guess best (`tracker.references`, 6: with 3, room5 seed 0 gave 12.7 cm, with 6 and
  500 points each 7.6 cm; docs/results.md). The solve is Levenberg-Marquardt on the pose (a
  left increment on `T_cw`) and, per reference, an affine brightness
  `I_frame = a * I_keyframe + b` (real cameras change exposure), with analytic Jacobians (the
  frame's image gradient times the projection's), Huber weights, coarse to fine over a pyramid
  of the frame's grey image, and an early stop once the step is small (one level's problem:
  `tracker/photometric.py`).
- The solve fails (`TrackingLost`) when the frame has too little texture to align, when too
  few points stay in view, when the robust residual stays high or few points fit, or when
  anything turns non-finite; the front end then relocalizes.

Whether a frame becomes a keyframe is decided on the same points: their reprojection flow
between the last keyframe and the frame, and how many of those the last keyframe sees stay in
view. Nothing else is rendered per frame.
"""

from __future__ import annotations

import math
import statistics
from dataclasses import dataclass, field

import numpy as np
import torch

from dimslam.common.geometry import pose
from dimslam.common.geometry.camera import Camera
from dimslam.common.map.render import FieldFn, RenderConfig, render_pixels
from dimslam.common.optim import losses
from dimslam.common.optim.window import FrameState, TrackingLost, WindowStats
from dimslam.tracker.photometric import (
    LevelProblem,
    channels,
    huber_mean,
    level_uv,
    pyramid,
    se3_exp,
    texture,
    with_gradients,
)
from dimslam.tracker.tracker import TrackerConfig, TrackResult

PROBE = 64
"""Points of a reference that estimate its overlap with a view."""
MIN_POINTS = 30
"""Fewest points in view for a solve to count at all."""
FIT_POINTS = 100
"""Points in view a reference needs for its share of inliers to count on its own."""
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


@dataclass
class Reference:
    """One keyframe's points with the depth the map gave them.

    Attributes:
        keyframe: the keyframe (its current pose places the points in the world).
        p_k: `(N, 3)` points in the keyframe's camera frame.
        intensity: per pyramid level, `(N, C)` the keyframe's grey value (C = 1) or colour
            (C = 3, `tracker.colour`) at each point.
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
        for _ in range(cfg.pyramid_levels):
            self.cameras.append(size)
            if min(size.width, size.height) < 32:
                break
            size = camera.resized(size.width // 2, size.height // 2)
        self.references: dict[int, Reference] = {}
        self.brightness: dict[int, tuple[float, float]] = {}
        self.version = 0
        self.last_points: torch.Tensor | None = None

    # -- references ---------------------------------------------------------------------------

    def map_changed(
        self, field: FieldFn, keyframes: list[FrameState], version: int, renders: int = 0
    ) -> int:
        """A new map: render the `renders` newest keyframes' references again (0:
        `tracker.references`; the others wait for a frame to use them, `tracker.refresh`).
        Returns how many."""
        self.version = version
        keep = {kf.index for kf in keyframes}
        for index in [i for i in self.references if i not in keep]:
            del self.references[index]  # no longer a keyframe (a new stream, a reset)
        rendered = 0
        for kf in keyframes[-(renders or self.cfg.references) :]:
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
        depth = torch.where(out.opacity > 0.5, out.depth, math.nan)
        ref = self.references[kf.index] = self.reference(kf, uv, depth)
        return ref

    def reference(self, kf: FrameState, uv: torch.Tensor, depth: torch.Tensor) -> Reference:
        """`kf`'s pixels `uv` `(N, 2)` at `depth` `(N,)` (nan where unknown) as a reference,
        not kept."""
        assert kf.rgb is not None
        good = torch.isfinite(depth) & (depth > 0)
        uv, depth = uv[good], depth[good]
        images = pyramid(channels(kf.rgb, self.cfg.colour), len(self.cameras))
        intensity = [
            losses.sample_images(img.expand(-1, -1, 3), level_uv(uv, lv))[:, : img.shape[-1]]
            for lv, img in enumerate(images)
        ]
        return Reference(
            kf,
            self.camera.unproject(uv, depth),
            intensity,
            self.version,
            texture(with_gradients(images[0])),
        )

    def _overlaps(self, refs: list[Reference], T_cw: torch.Tensor) -> list[float]:
        """Per reference, the share of its first `PROBE` points in front of the camera at
        `T_cw` and inside its image, all in one pass.

        The points are stored in pixel order (`torch.unique` sorts them by u), so these lie
        along the keyframe image's left edge: a keyframe counts as seen when its left edge is,
        and of those `choose` takes the newest. Measured on points spread over the whole image
        instead (e9e62ec), 8 of the 12 development runs came out worse, room0's three by
        2.2-3.9 cm (docs/results.md, session 15), so this stays until a rule that says what it
        prefers (the newest keyframes that overlap enough, say) is measured against it."""
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
        chosen = [r for s, r in [*first, *others] if s > 0.05][: self.cfg.references]
        # The map keeps improving where the camera returns: depth an older map gave a chosen
        # keyframe is rendered again, a few per frame so that no frame pays for many.
        stale = sorted((r for r in chosen if r.version < self.version), key=lambda r: r.version)
        for r in stale[: self.cfg.refresh]:
            chosen[chosen.index(r)] = self.render(field, r.keyframe)
            rendered += 1
        return chosen, rendered

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
        views = None
        if self.cfg.min_views > 0:
            views = list({id(f): f for f in [*local, *(r.keyframe for r in refs)]}.values())
        solved = self.solve(frame, refs, self.images(frame), self.cfg.hold, views)
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
        images = self.images(frame, len(self.cameras))
        level = min(self.cfg.reloc_levels, len(images)) - 1
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
        error = TrackingLost(f"frame {frame.index}: no rendered keyframe overlaps any start")
        for _, T_cw, refs in coarse[:RELOC_SOLVES]:
            frame.T_wc = _to_tensor(np.linalg.inv(T_cw), frame.T_wc)
            try:
                solved = self.solve(frame, refs, images)
            except TrackingLost as e:
                if error.best is None:  # the first that ended somewhere: the search's best
                    error = e
                continue
            if best is None or solved.stats.residual < best.stats.residual:
                best = solved
        if best is None:
            raise error
        if best.stats.residual > max_residual:
            raise TrackingLost(
                f"frame {frame.index}: best residual {best.stats.residual:.3f} > "
                f"{max_residual:.3f} of the frames tracked before",
                best.T_wc,
            )
        return self._accept(frame, best)

    def images(self, frame: FrameState, levels: int | None = None) -> list[torch.Tensor]:
        """The frame's pyramid (grey or colour) with the gradients, finest first: the solve's
        levels, or `levels` (a lost frame's search takes the whole pyramid)."""
        assert frame.rgb is not None
        levels = min(levels or self.cfg.levels, len(self.cameras))
        images = pyramid(channels(frame.rgb, self.cfg.colour), levels)
        return [with_gradients(img) for img in images]

    def _brightness(self, refs: list[Reference]) -> np.ndarray:
        """`(R, 2)` the last gain and offset of each reference against the frames."""
        return np.array([self.brightness.get(r.keyframe.index, (1.0, 0.0)) for r in refs])

    def _points(self, refs: list[Reference], views: list[FrameState] | None = None) -> _Points:
        """The references' points in one random order (the coarse levels use its first);
        with `views`, only those that more than `tracker.min_views` of them see (`_seen`)."""
        p_w = torch.cat([r.world() for r in refs])
        ref_of = torch.cat(
            [
                torch.full((len(r.p_k),), k, dtype=torch.long, device=p_w.device)
                for k, r in enumerate(refs)
            ]
        )
        order = torch.randperm(len(p_w), generator=self.generator, device=self.generator.device)
        order = order.to(p_w.device)
        if views is not None:
            keep = self._seen(p_w, ref_of, refs, views)
            order = order[keep[order]]
        # The brightness model works on intensities about each reference's mean, so that the
        # gain scales contrast only and the offset carries the shift of the mean.
        mean = torch.cat([r.intensity[0].mean(0).expand(len(r.p_k), -1) for r in refs])
        return _Points(order, p_w[order], ref_of[order], mean[order])

    def _seen(
        self,
        p_w: torch.Tensor,
        ref_of: torch.Tensor,
        refs: list[Reference],
        views: list[FrameState],
    ) -> torch.Tensor:
        """`(N,)` which points land inside more than `tracker.min_views` of `views` (at most
        all but two of them) other than their own reference's frame: the paper's visibility
        mask over the tracking window. A part of the scene only the newest frames have seen
        (where the map has had the least time to form) does not pull the pose."""
        _, inside = self._view(p_w, pose.invert(torch.stack([v.T_wc for v in views])))  # (V, N)
        own = torch.tensor([[v is r.keyframe for r in refs] for v in views], device=p_w.device)
        own = own[:, ref_of]
        count = (inside & ~own).sum(0)
        return count > min(self.cfg.min_views, len(views) - 2)

    def _problem(
        self, images: list[torch.Tensor], refs: list[Reference], pts: _Points, level: int
    ) -> LevelProblem:
        """The solve's problem at one pyramid level: the finest takes every point, each
        coarser one a quarter of those of the level below, at least 300."""
        total = len(pts.p_w)
        n = total if level == 0 else min(total, max(300, total >> (2 * level)))
        centred = torch.cat([r.intensity[level] for r in refs])[pts.order] - pts.mean
        return LevelProblem(
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
        self,
        frame: FrameState,
        refs: list[Reference],
        images: list[torch.Tensor],
        hold: float = 0.0,
        views: list[FrameState] | None = None,
    ) -> _Solved:
        """Levenberg-Marquardt from `frame.T_wc` against `refs`, coarse to fine; checked but
        not yet applied (`_accept`). `hold` (`tracker.hold`) keeps the directions the data
        leave loose near the start (`LevelProblem.minimize`); with `views` (the frame among
        them, at its start) only the points enough of them see count (`_seen`).

        Raises:
            TrackingLost: too few points to solve against, or the solution is non-finite,
                sees too few points, jumped too far from the start, or leaves the residual
                high.
        """
        seen = texture(images[0]) / max(statistics.fmean(r.texture for r in refs), 1e-12)
        if seen < MIN_TEXTURE:
            raise TrackingLost(
                f"frame {frame.index}: {seen:.0%} of the keyframes' texture (covered, blurred "
                "or dark)"
            )
        pts = self._points(refs, views)
        if len(pts.p_w) < MIN_POINTS:  # nothing to solve against (a level's mean would be 0/0)
            where = "seen by enough of the window" if views is not None else "in the keyframes"
            raise TrackingLost(f"frame {frame.index}: {len(pts.p_w)} points {where}")
        ab = self._brightness(refs)
        T_cw = np.linalg.inv(frame.T_wc.double().cpu().numpy())
        anchor = T_cw.copy()
        stats = DirectStats(references=tuple(r.keyframe.index for r in refs), points=len(pts.p_w))
        budget = self.cfg.iters
        finest = None
        for level in reversed(range(min(self.cfg.levels, len(images)))):
            finest = self._problem(images, refs, pts, level)
            # A fair share of the iterations left; what a level leaves unused passes on.
            share = max(1, budget // (level + 1))
            T_cw, ab, used, cost = finest.minimize(T_cw, ab, share, hold, anchor)
            budget -= used
            stats.per_level.append(used)
            stats.iterations += used
            stats.history.append(cost)
        assert finest is not None
        check = finest.evaluate(T_cw, ab)
        n_valid = int(check.valid.sum())
        rv = check.r[check.valid]
        residual = math.sqrt(2 * huber_mean(rv, self.cfg.fit)) if n_valid else math.inf
        fits = check.r.abs().mean(dim=1) <= self.cfg.fit  # a point's channels on average
        inliers = _best_fit(fits, check.valid, finest.ref_of, len(refs))
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
                f"frame {frame.index}: residual {residual:.3f}, {inliers:.0%} inliers", T_wc
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

    def _view(self, p_w: torch.Tensor, T_cw: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Pixels of world points `(N, 3)` in camera `T_cw` (or in each of `(V, 4, 4)`
        cameras: `(V, N, ...)`), and which of them it sees."""
        uv, z = self.camera.project(pose.transform_points(T_cw, p_w))
        return uv, (z > 0) & self.camera.inside(uv)

    def _flow(self, p_w: torch.Tensor, T_a: torch.Tensor, T_b: torch.Tensor) -> float:
        """Mean displacement (pixels) of the points in view between cameras `T_a`, `T_b` (cw)."""
        (uv_a, in_a), (uv_b, in_b) = self._view(p_w, T_a), self._view(p_w, T_b)
        both = in_a & in_b
        return float((uv_a[both] - uv_b[both]).norm(dim=-1).mean()) if both.any() else math.inf

    # -- keyframes ----------------------------------------------------------------------------

    def is_keyframe(self, field: FieldFn, frame: FrameState, last_keyframe: FrameState) -> bool:
        """Whether `frame` becomes a keyframe (rules as `Tracker.is_keyframe`), measured on the
        points of the last solve: their mean reprojection flow between the last keyframe and
        the frame, and the share of those the keyframe sees that the frame still sees."""
        if self.last_points is None:
            return False
        uv_k, in_k = self._view(self.last_points, pose.invert(last_keyframe.T_wc))
        uv_f, in_f = self._view(self.last_points, pose.invert(frame.T_wc))
        if not bool(in_k.any()):
            return True
        if float(in_f[in_k].float().mean()) < self.cfg.keyframe_overlap:
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


def _best_fit(
    inlier: torch.Tensor, valid: torch.Tensor, ref_of: torch.Tensor, n_refs: int
) -> float:
    """The largest share of inliers among the references with `FIT_POINTS` points in view
    (among all points if none has): a frame is lost when it fits none of its references.

    Per reference, because where the map is poor some references' depth is off by more than
    others' (the older ones see the place from farther): on room0's frames 63-104 all points
    together fitted 23-30 %, as a frame of noise does (21-23 %), and with six references the
    frames stayed lost to the end (seeds 1 and 2: 236 and 233 of 300 frames lost); per
    reference, 42 and 10 frames are lost and tracking resumes.
    """
    counts = torch.bincount(ref_of[valid], minlength=n_refs)
    hits = torch.bincount(ref_of[valid & inlier], minlength=n_refs)
    enough = counts >= FIT_POINTS
    if not bool(enough.any()):
        n = int(valid.sum())
        return float(hits.sum()) / n if n else 0.0
    return float((hits[enough].float() / counts[enough].float()).max())


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

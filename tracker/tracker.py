"""The tracking step: window poses only, on high-gradient pixels, against a fixed map.

Paper section 3.3 / appendix "two threads": the window is the local frames (the newest
`local_frames`) plus up to `keyframes` global keyframes whose view overlaps the newest frame by
more than `overlap`. Only the poses of local non-keyframes move; the map and the keyframes stay
fixed. A new frame enters with a constant-velocity guess. After tracking, the newest frame
becomes a keyframe when the mean reprojection flow from the last keyframe exceeds
`keyframe_flow_px`.

The objective is the paper's warping loss over the window, restricted to the terms that depend
on a moving pose: patches of the *fixed* frames, at the depth the map renders for them, warped
into each moving frame. With the map and the source poses fixed, that depth and the source
patches are computed once per frame, so an iteration costs one warp and one bilinear lookup
per patch pixel and moving frame and renders nothing. The paper samples the pixels in the
moving frames instead and renders them at every iteration; on room0's first 100 frames (cpu
preset, seed 0) this form gave 1.6 cm ATE against 3.7 cm, in less time (docs/results.md).
The render term is left out of tracking: it needs a render per iteration, and it pulls towards
the map's blurred colours.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Literal

import torch

from dimslam.common.geometry.camera import Camera
from dimslam.common.map.render import FieldFn, RenderConfig, render_pixels
from dimslam.common.optim import losses
from dimslam.common.optim.objective import LossConfig, WindowLoss, patch_colors
from dimslam.common.optim.window import (
    FrameState,
    TrackingLost,
    WindowStats,
    minimize,
    overlapping_keyframes,
    project_into,
)
from dimslam.common.options import option

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrackerConfig:
    """Tracking: the solver, its budget and window (paper: the window objective on 3000 px,
    20 iterations, 11 local + 10 keyframes)."""

    solver: Literal["direct", "adam"] = option(
        "direct",
        "direct: Gauss-Newton on the newest pose against rendered keyframe points "
        "(tracker/direct.py); adam: the paper's window objective (this module).",
    )
    iters: int = option(
        20, "Iterations per frame: Adam steps, or Gauss-Newton steps over all pyramid levels."
    )
    levels: int = option(4, "direct: image pyramid levels of the solve, coarse to fine.")
    reloc_levels: int = option(
        4,
        "direct: pyramid levels of a lost frame's search (its coarse moves run on the coarsest, "
        "where the basin is widest); a solve on fewer `levels` keeps this wide search.",
    )
    ref_points: int = option(500, "direct: high-gradient points rendered per keyframe.")
    references: int = option(
        6,
        "direct: keyframes a frame is tracked against: the newest and those that see most of "
        "its view (more of them anchor it to older, better mapped keyframes).",
    )
    refresh: int = option(
        1,
        "direct: of the keyframes a frame is tracked against, how many whose depth an older "
        "map rendered are rendered again from the newest (the stalest first).",
    )
    min_views: int = option(
        0,
        "direct: a reference point counts where it lands inside more than this many of the "
        "window's frames (the `local_frames` newest, the references' keyframes) other than "
        "its own (paper's visibility mask; 0: every point counts).",
    )
    huber: float = option(
        9 / 255, "direct: Huber threshold of the solve's robust weights (intensities in [0, 1])."
    )
    fit: float = option(
        9 / 255,
        "direct: a point fits where its residual is within this (intensities in [0, 1]); the "
        "lost checks' robust residual and share of inliers are measured with it.",
    )
    affine: bool = option(True, "direct: estimate affine brightness per reference keyframe.")
    hold: float = option(
        0.0,
        "direct: hold the pose near the motion guess by this share of the data's curvature "
        "per pose direction (0: off): a direction the images leave loose stays at the guess.",
    )
    window_refine_deg: float = option(
        0.0,
        "direct: a frame whose solve ends more than this many degrees of rotation from its "
        "motion guess is solved again from the guess by the paper's window objective (Adam, "
        "`iters` steps, its pose alone, the frames before it and the overlapping keyframes "
        "as sources) and takes that end (0: never).",
    )
    window_refine_seen: float = option(
        0.0,
        "direct: solve again only where the images see less than this share of the turn "
        "from the guess: the translation of the same departure hides the rest (a narrow "
        "view's turn-or-slide; a hand-held jerk is a turn the images see), or right after "
        "a frame solved again. 0: every frame past `window_refine_deg`.",
    )
    colour: bool = option(
        False,
        "direct: solve on the three colour channels (three residuals per point, one "
        "brightness per reference) instead of the grey image.",
    )
    lost_residual: float = option(
        0.1, "direct: robust residual RMS above which a frame counts as lost."
    )
    min_inliers: float = option(
        0.3, "direct: share of points within the Huber threshold below which a frame is lost."
    )
    live_map_renders: int = option(
        0,
        "direct: for frames from a live camera, how many of the newest keyframes are rendered "
        "again as soon as a new map arrives (0: `references`, as offline); the others are "
        "rendered when a frame uses them (`refresh` a frame). Live, a map arrives about every "
        "second, and six renders at once (about 120 ms on one core) made the tracker drop the "
        "frames that came meanwhile; the cpu preset takes 1 (room0 at 10 FPS, 6 runs each: "
        "2-24 frames dropped against 10-46, 94 percent tracked at the median against 88; "
        "docs/results.md, session 53).",
    )
    live_min_inliers: float = option(
        0.0,
        "direct: `min_inliers` for frames from a live camera (0: the same). There a frame "
        "lost where the camera leaves what is mapped stays lost, since a lost frame never "
        "reaches the mapper; the cpu preset takes 0.2 (room0 at 10 FPS: none lost against "
        "12-27; offline 0.2 took room5 seed 0 from 7.6 to 14.9 cm; docs/results.md, "
        "session 52).",
    )
    max_jump_px: float = option(
        40.0,
        "direct: a solve that moves the view more than this (mean pixels) from the motion "
        "guess has locked onto something else: the frame counts as lost.",
    )
    reloc_candidates: int = option(
        6,
        "Starts of the search for a lost frame: its guess, the last motion over the gap, "
        "the nearest keyframes' poses.",
    )
    pixels: int = option(3000, "adam: high-gradient pixels per tracking step.")
    pose_lr: float = option(1e-2, "adam: learning rate of the pose increments.")
    local_frames: int = option(
        11,
        "Newest frames in the tracking window (paper: k-5..k+5); direct: the frames of its "
        "visibility mask (`min_views`).",
    )
    optimize_last: int = option(11, "adam: how many of the newest window frames move.")
    keyframes: int = option(10, "adam: overlapping keyframes added (fixed) to the window.")
    overlap: float = option(0.7, "View overlap a keyframe needs to join the window.")
    overlap_pixels: int = option(100, "Pixels reprojected to measure overlap and flow.")
    keyframe_flow_px: float = option(10.0, "Mean reprojection flow that makes a new keyframe.")
    keyframe_overlap: float = option(0.85, "New keyframe when the last one sees less than this.")
    max_loss: float = option(10.0, "adam: loss above which a frame counts as lost.")
    init_reference: bool = option(
        True,
        "Track the first frames after the initialization against its newest frame too, "
        "until the tracker makes a keyframe of its own (room3 at stride 3, 100 frames, 3 "
        "seeds: 38.9 cm with 9 frames lost -> 17.7 cm, none lost; docs/results.md).",
    )

    @property
    def pyramid_levels(self) -> int:
        """direct: levels of the pyramid kept per frame and reference: the solve's and the
        lost frames' search's, whichever is taller."""
        return max(self.levels, self.reloc_levels)


@dataclass(frozen=True)
class TrackResult:
    """The outcome of tracking one frame."""

    index: int
    T_wc: torch.Tensor
    stats: WindowStats
    window: tuple[int, ...]


class Tracker:
    """Optimizes the poses of the newest frames against the map."""

    def __init__(
        self,
        cfg: TrackerConfig,
        loss_cfg: LossConfig,
        render_cfg: RenderConfig,
        camera: Camera,
        generator: torch.Generator,
    ) -> None:
        self.cfg = cfg
        self.loss_cfg = loss_cfg
        self.render_cfg = render_cfg
        self.camera = camera
        self.generator = generator
        self.margin = loss_cfg.margin()

    def track(
        self, field: FieldFn, local: list[FrameState], keyframes: list[FrameState]
    ) -> TrackResult:
        """Optimize the poses of `local` (newest last) with overlapping `keyframes` fixed.

        Raises:
            TrackingLost: the loss diverged or the poses became non-finite.
        """
        newest = local[-1]
        window = self._window(field, local, keyframes)
        newest_ids = {id(f) for f in local[-self.cfg.optimize_last :]}
        movable = [not f.keyframe and id(f) in newest_ids for f in window]
        if all(movable):  # nothing fixed to warp from: the oldest frame anchors the rest
            movable[0] = False
        objective = self._objective(field, window, movable)
        stats = minimize(
            window, movable, objective, self.cfg.iters, self.cfg.pose_lr, max_loss=self.cfg.max_loss
        )
        return TrackResult(newest.index, newest.T_wc, stats, tuple(f.index for f in window))

    def refine(
        self,
        field: FieldFn,
        local: list[FrameState],
        keyframes: list[FrameState],
        iters: int,
        starts: list[torch.Tensor],
    ) -> list[tuple[torch.Tensor, float] | None]:
        """`iters` steps of the window objective on the pose of `local[-1]` alone (a keyframe
        or not), every other frame of the window fixed, from each of `starts` in turn: per
        start its end and the objective there (None where it diverged). One objective
        (pixels, depths and visibility mask, taken at the frame's pose as given) scores every
        end, so they compare; every frame keeps its pose as given."""
        newest = local[-1]
        window = self._window(field, local, keyframes)
        given = [f.T_wc for f in window]  # `minimize` writes every pose back, normalized
        movable = [f is newest for f in window]
        objective = self._objective(field, window, movable)
        ends: list[tuple[torch.Tensor, float] | None] = []
        for start in starts:
            newest.T_wc = start.clone()
            try:
                minimize(
                    window, movable, objective, iters, self.cfg.pose_lr, max_loss=self.cfg.max_loss
                )
            except TrackingLost as error:
                log.debug("frame %d: a refinement diverged: %s", newest.index, error)
                ends.append(None)
                continue
            with torch.no_grad():
                loss = objective(iters, torch.stack([f.T_wc for f in window]))[0].item()
            ends.append((newest.T_wc.clone(), loss))
        for f, T in zip(window, given, strict=True):
            f.T_wc = T
        return ends

    def _window(
        self, field: FieldFn, local: list[FrameState], keyframes: list[FrameState]
    ) -> list[FrameState]:
        """The keyframes (not in `local`) that overlap its newest frame best, then `local`."""
        in_local = {id(f) for f in local}
        candidates = [kf for kf in keyframes if id(kf) not in in_local]
        fixed = overlapping_keyframes(
            field,
            local[-1],
            candidates,
            self.camera,
            self.cfg.keyframes,
            self.cfg.overlap,
            self.cfg.overlap_pixels,
            self.render_cfg,
            self.generator,
        )
        return fixed + local

    def relocalize(
        self,
        field: FieldFn,
        local: list[FrameState],
        keyframes: list[FrameState],
        starts: list[torch.Tensor],
        max_residual: float,
    ) -> TrackResult:
        """Place `local[-1]` after a loss: `track` from each start in turn; the first whose
        loss is at most `max_residual` wins.

        Raises:
            TrackingLost: no start does.
        """
        error = TrackingLost(f"frame {local[-1].index}: no start to relocalize from")
        for start in starts:
            local[-1].T_wc = start.clone()
            try:
                result = self.track(field, local, keyframes)
            except TrackingLost as e:
                error = e
                continue
            if result.stats.loss <= max_residual:
                return result
            error = TrackingLost(
                f"frame {local[-1].index}: loss {result.stats.loss:.3f} > {max_residual:.3f}"
            )
        raise error

    def _objective(self, field: FieldFn, window: list[FrameState], movable: list[bool]):
        """The warping terms from the fixed frames of `window` into its moving frames.

        Each fixed frame gives an equal share of `pixels` high-gradient pixels; their depth is
        rendered once (deterministic samples: fixed map, fixed pose). A pixel counts where its
        centre lands inside more than `min_views` other window frames at the starting poses
        (the paper's visibility mask) and, per moving frame, where its whole patch lands inside.
        """
        sources = [i for i, m in enumerate(movable) if not m]
        targets = [i for i, m in enumerate(movable) if m]
        offsets = self.loss_cfg.offsets(device=window[0].rgb.device)
        per_frame = max(1, self.cfg.pixels // len(sources))
        uv = torch.cat(
            [
                losses.high_gradient_pixels(window[i].rgb, per_frame, self.generator, self.margin)
                for i in sources
            ]
        ).float()  # (S m, 2), source by source
        source = torch.tensor(sources, device=uv.device).repeat_interleave(per_frame)  # (S m,)
        poses = torch.stack([f.T_wc for f in window])
        T_src = poses[source]  # (S m, 4, 4)
        with torch.no_grad():
            depth = render_pixels(field, self.camera, uv, T_src, self.render_cfg).depth
            images = torch.stack([f.rgb for f in window])
            patches = patch_colors(images, source, uv, offsets)  # (S m, P, 3)
            centre = offsets.new_zeros(1, 2)
            warp = losses.warp_patches(uv, depth, T_src, poses, self.camera, centre)
            others = source != torch.arange(len(window), device=uv.device)[:, None]
            seen = losses.WarpResult(warp.uv, warp.valid & others[..., None])
            visible = losses.visibility_mask(seen, min(self.loss_cfg.min_views, len(window) - 2))
        images = images[targets]
        nan = float("nan")

        def objective(_: int, poses: torch.Tensor) -> tuple[torch.Tensor, WindowLoss]:
            warp = losses.warp_patches(uv, depth, T_src, poses[targets], self.camera, offsets)
            warped = losses.sample_images(images, warp.uv)
            term = losses.warping_loss(
                patches, warped, warp.valid, visible, self.loss_cfg.patch_sizes
            )
            total = self.loss_cfg.warp_weight * term.value
            stats = WindowLoss(total, term.value.item(), nan, 0.0, int(term.count), depth)
            return total, stats

        return objective

    def map_changed(
        self, field: FieldFn, keyframes: list[FrameState], version: int, renders: int = 0
    ) -> int:
        """A new map: nothing is cached here (every step renders what it needs). Returns 0."""
        return 0

    def is_keyframe(self, field: FieldFn, frame: FrameState, last_keyframe: FrameState) -> bool:
        """Whether `frame` becomes a keyframe (`keyframe_due` on the map)."""
        return keyframe_due(
            field, frame, last_keyframe, self.camera, self.cfg, self.render_cfg, self.generator
        )


def keyframe_due(
    field: FieldFn,
    frame: FrameState,
    last_keyframe: FrameState,
    camera: Camera,
    cfg: TrackerConfig,
    render_cfg: RenderConfig,
    generator: torch.Generator,
) -> bool:
    """Whether `frame` becomes a keyframe, measured on `cfg.overlap_pixels` random pixels of
    it placed at the map's depth.

    Either the mean reprojection flow from the last keyframe exceeds `keyframe_flow_px`
    (paper), or the last keyframe sees less than `keyframe_overlap` of the frame. The second
    rule keeps a fixed keyframe that overlaps enough to join the tracking window: forward
    motion loses overlap long before the flow near the image centre reaches the threshold,
    and a window of tracked frames alone lets errors grow (docs/status.md).
    """
    uv, uv_kf, valid = project_into(
        field, frame, [last_keyframe], camera, cfg.overlap_pixels, render_cfg, generator
    )
    ok = valid[0]
    if float(ok.float().mean()) < cfg.keyframe_overlap:
        return True
    flow = (uv_kf[0][ok] - uv[ok]).norm(dim=-1).mean()
    return float(flow) > cfg.keyframe_flow_px

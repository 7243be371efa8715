"""The tracking step: window poses only, on high-gradient pixels, against a fixed map.

Paper section 3.3 / appendix "two threads": the window is the local frames (the newest
`local_frames`) plus up to `keyframes` global keyframes whose view overlaps the newest frame by
more than `overlap`. Only the poses of local non-keyframes move; the map and the keyframes stay
fixed. A new frame enters with a constant-velocity guess. After tracking, the newest frame
becomes a keyframe when the mean reprojection flow from the last keyframe exceeds
`keyframe_flow_px`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import torch

from dimslam.common import losses
from dimslam.common.camera import Camera
from dimslam.common.objective import LossConfig
from dimslam.common.options import option
from dimslam.common.render import FieldFn, RenderConfig
from dimslam.common.window import (
    FrameState,
    WindowStats,
    optimize_window,
    overlapping_keyframes,
    project_into,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrackerConfig:
    """Tracking budget and window (paper: 3000 px, 20 iterations, 11 local + 10 keyframes)."""

    pixels: int = option(3000, "High-gradient pixels per tracking step.")
    iters: int = option(20, "Adam iterations per frame.")
    pose_lr: float = option(1e-2, "Learning rate of the pose increments.")
    local_frames: int = option(11, "Newest frames in the tracking window (paper: k-5..k+5).")
    optimize_last: int = option(11, "How many of the newest window frames move (the rest anchor).")
    keyframes: int = option(10, "Overlapping keyframes added (fixed) to the window.")
    overlap: float = option(0.7, "View overlap a keyframe needs to join the window.")
    overlap_pixels: int = option(100, "Pixels reprojected to measure overlap and flow.")
    keyframe_flow_px: float = option(10.0, "Mean reprojection flow that makes a new keyframe.")
    keyframe_overlap: float = option(0.85, "New keyframe when the last one sees less than this.")
    max_loss: float = option(10.0, "Loss above which tracking counts as lost.")


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
        self.margin = max(loss_cfg.patch_sizes) // 2

    def track(
        self, field: FieldFn, local: list[FrameState], keyframes: list[FrameState]
    ) -> TrackResult:
        """Optimize the poses of `local` (newest last) with overlapping `keyframes` fixed."""
        newest = local[-1]
        in_local = {id(f) for f in local}
        candidates = [kf for kf in keyframes if id(kf) not in in_local]
        fixed = overlapping_keyframes(
            field,
            newest,
            candidates,
            self.camera,
            self.cfg.keyframes,
            self.cfg.overlap,
            self.cfg.overlap_pixels,
            self.render_cfg,
            self.generator,
        )
        window = fixed + local
        newest_ids = {id(f) for f in local[-self.cfg.optimize_last :]}
        movable = [not f.keyframe and id(f) in newest_ids for f in window]
        moving = [i for i, m in enumerate(movable) if m]
        # One fixed set of high-gradient pixels, spread over the moving frames (design.md 5c).
        per_frame = max(1, self.cfg.pixels // max(1, len(moving)))
        frame_ids, uvs = [], []
        for i in moving:
            uv = losses.high_gradient_pixels(window[i].rgb, per_frame, self.generator, self.margin)
            frame_ids.append(torch.full((per_frame,), i, dtype=torch.long, device=uv.device))
            uvs.append(uv.float())
        frame = torch.cat(frame_ids)
        uv = torch.cat(uvs)
        stats = optimize_window(
            field,
            window,
            movable,
            self.camera,
            lambda it: (frame, uv),
            self.cfg.iters,
            self.cfg.pose_lr,
            self.loss_cfg,
            self.render_cfg,
            # Deterministic ray samples: with a fixed map and fixed pixels, jitter would only
            # add noise to the pose gradients (Adam turns noise into full-size steps).
            generator=None,
            max_loss=self.cfg.max_loss,
        )
        return TrackResult(newest.index, newest.T_wc, stats, tuple(f.index for f in window))

    def is_keyframe(self, field: FieldFn, frame: FrameState, last_keyframe: FrameState) -> bool:
        """Whether `frame` becomes a keyframe.

        Either the mean reprojection flow from the last keyframe exceeds `keyframe_flow_px`
        (paper), or the last keyframe sees less than `keyframe_overlap` of the frame. The second
        rule keeps a fixed keyframe that overlaps enough to join the tracking window: forward
        motion loses overlap long before the flow near the image centre reaches the threshold,
        and a window of tracked frames alone lets errors grow (docs/status.md).
        """
        uv, uv_kf, valid = project_into(
            field,
            frame,
            [last_keyframe],
            self.camera,
            self.cfg.overlap_pixels,
            self.render_cfg,
            self.generator,
        )
        ok = valid[0]
        if float(ok.float().mean()) < self.cfg.keyframe_overlap:
            return True
        flow = (uv_kf[0][ok] - uv[ok]).norm(dim=-1).mean()
        return float(flow) > self.cfg.keyframe_flow_px

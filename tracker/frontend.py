"""The tracker's half of the pipeline: a frame in, its pose and keyframe flag out.

What every frame goes through on the tracking side, written once for both drivers
(`common/slam.py` in one process, `tracker/service.py` as a process of its own):

1. Until the map exists, frames are collected at the identity; the first `init_frames` are
   handed to the mapper together (`collect`).
2. Then each frame enters at a motion guess (constant velocity, or the pose a continued map
   left, or the last pose across a gap in the stream), is tracked against the map
   (`Tracker.track`), and may become a keyframe (`Tracker.is_keyframe`).
3. Every `mapper.every` frames the frames tracked since the last hand-over are due to the
   mapper (`batch_due`, `take_batch`); how they get there is the driver's business (the same
   objects in one process, a message in the service).
4. Frames no window will use again lose their images.

Refined poses come back from the mapper: in one process they are the same objects; the
service applies a snapshot's poses with `apply_poses`.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

import torch

from dimslam.common.config import SlamConfig
from dimslam.common.geometry import pose
from dimslam.common.geometry.camera import Camera
from dimslam.common.map.render import FieldFn
from dimslam.common.optim.window import FrameState, TrackingLost, constant_velocity, release_images
from dimslam.tracker.tracker import Tracker, TrackResult


class FrontEnd:
    """The frames the tracker holds, and the steps that track each new one."""

    def __init__(self, cfg: SlamConfig, camera: Camera, generator: torch.Generator) -> None:
        self.cfg = cfg
        self.camera = camera
        self.tracker = Tracker(cfg.tracker, cfg.loss, cfg.render, camera, generator)
        self.frames: list[FrameState] = []
        self.pending: list[FrameState] = []
        self.next_guess: torch.Tensor | None = None
        self.last_result: TrackResult | None = None

    @property
    def keyframes(self) -> list[FrameState]:
        return [f for f in self.frames if f.keyframe]

    def collect(self, index: int, timestamp: float, rgb: torch.Tensor) -> bool:
        """Before the map exists: keep the frame at the identity; True once the frames for
        the initialization are complete (they are then pending, see `take_batch`)."""
        self.frames.append(FrameState(index, timestamp, rgb, torch.eye(4, device=rgb.device)))
        if len(self.frames) < self.cfg.mapper.init_frames:
            return False
        self.pending = list(self.frames)
        return True

    def collect_rest(self) -> bool:
        """At the end of a stream too short to fill the initialization: hand over all frames
        if there are enough to start a map (3). True if so."""
        if len(self.frames) < 3:
            return False
        self.pending = list(self.frames)
        return True

    def guess(self) -> torch.Tensor:
        """Where the next frame starts: a continued map's last pose, else constant velocity
        over the last two frames, else (across a gap in the stream) the last pose."""
        if self.next_guess is not None:
            guess, self.next_guess = self.next_guess, None
            return guess
        last = self.frames[-1]
        before = self.frames[-2] if len(self.frames) > 1 else None
        if before is not None and before.index == last.index - 1:
            return constant_velocity(last.T_wc, before.T_wc)
        return last.T_wc.clone()

    def track(self, field: FieldFn, index: int, timestamp: float, rgb: torch.Tensor) -> FrameState:
        """Track one frame against the map; it joins the frames and the next batch.

        Raises:
            TrackingLost: the motion model or the optimization diverged; the frame is not
                kept, every earlier frame keeps its pose.
        """
        guess = self.guess()
        if not torch.isfinite(guess).all():
            raise TrackingLost(f"frame {index}: the motion model gives a non-finite pose")
        state = FrameState(index, timestamp, rgb, guess)
        self.frames.append(state)
        keyframes = self.keyframes
        try:
            self.last_result = self.tracker.track(
                field, self.frames[-self.cfg.tracker.local_frames :], keyframes
            )
        except TrackingLost:
            self.frames.pop()
            raise
        if self.tracker.is_keyframe(field, state, keyframes[-1]):
            state.keyframe = True
        self.pending.append(state)
        release_images(self.frames, self.cfg.kept_images)
        return state

    def batch_due(self) -> bool:
        """Whether the frames tracked since the last hand-over make a mapping round."""
        every = self.cfg.mapper.every
        return bool(self.pending) and (
            self.pending[-1].index % every == 0 or len(self.pending) >= every
        )

    def take_batch(self) -> list[FrameState]:
        """The frames tracked since the last hand-over (now handed over)."""
        batch, self.pending = self.pending, []
        return batch

    def apply_poses(self, poses: Mapping[int, torch.Tensor], keyframes: Iterable[int]) -> None:
        """Take the mapper's refined poses (frame index -> `T_wc`) and keyframe flags.

        Frames tracked after the newest refined one move with its correction, so the motion
        model sees no jump.
        """
        by_index = {f.index: f for f in self.frames}
        known = [i for i in poses if i in by_index]
        if known:
            newest = max(known)
            correction = pose.compose(poses[newest], pose.invert(by_index[newest].T_wc))
            for i in known:
                by_index[i].T_wc = poses[i]
            for f in self.frames:
                if f.index > newest:
                    f.T_wc = pose.normalize(pose.compose(correction, f.T_wc))
        for i in keyframes:
            if i in by_index:
                by_index[i].keyframe = True

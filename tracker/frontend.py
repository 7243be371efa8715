"""The tracker's half of the pipeline: a frame in, its pose and keyframe flag out.

What every frame goes through on the tracking side, written once for both drivers
(`common/slam.py` in one process, `tracker/service.py` as a process of its own):

1. Until the map exists, frames are collected at the identity; the first `init_frames` are
   handed to the mapper together (`collect`).
2. Then each frame enters at a motion guess (constant velocity, or the pose a continued map
   left, or the last pose across a longer gap in the stream), is tracked against the map by
   the configured solver (`tracker.solver`: `DirectTracker` or the window `Tracker`), and may
   become a keyframe. A frame the solver cannot place is *lost*: it gets no pose (none is
   invented), and the next frames are searched for (`relocalize`) from their guess, the last
   motion carried over the gap and the nearest keyframes' poses, until one aligns with a
   residual like the frames tracked before the loss (relocalization). Where a lost frame's
   solve ended (`TrackingLost.best`) still feeds the motion model, so that through a stretch
   where the map is too poor to accept a solve the guesses keep following the camera.
3. Every `mapper.every` frames the frames tracked since the last hand-over are due to the
   mapper (`batch_due`, `take_batch`), and at once when a frame is lost; how they get there
   is the driver's business (the same objects in one process, a message in the service).
4. Frames no window will use again lose their images.

Refined poses come back from the mapper: in one process they are the same objects; the
service applies a snapshot's poses with `apply_poses`. Either way `map_changed` tells the
solver a new map arrived (the direct solver renders its references again then).
"""

from __future__ import annotations

import logging
import math
import statistics
from collections import deque
from collections.abc import Iterable, Mapping
from dataclasses import replace

import torch

from dimslam.common.config import SlamConfig
from dimslam.common.geometry import pose
from dimslam.common.geometry.camera import Camera
from dimslam.common.map.render import FieldFn
from dimslam.common.optim.window import FrameState, TrackingLost, release_images
from dimslam.tracker.direct import DirectTracker
from dimslam.tracker.tracker import Tracker, TrackResult

log = logging.getLogger(__name__)

MAX_VELOCITY_STEPS = 4
"""A gap of up to this many frames (dropped live frames) is bridged by repeating the last
motion; across a longer one the last pose is the guess."""
MAX_EXTRAPOLATION = 30
"""While relocalizing, the last motion is also repeated over the whole gap, up to this many
frames (a second at 30 FPS)."""


def carry_motion(recent: list[tuple[int, torch.Tensor]], index: int, limit: int) -> torch.Tensor:
    """The motion between the two poses `recent` (`(frame index, T_wc)`, older first), per
    frame, carried on to frame `index`: the last pose when either gap (between those two, or
    on to `index`) exceeds `limit` frames, or when there is only one."""
    (last, T_last), before = recent[-1], recent[-2] if len(recent) > 1 else None
    steps = index - last
    if before is None or not 0 < last - before[0] <= limit or not 0 < steps <= limit:
        return T_last.clone()
    twist = pose.log_se3(pose.compose(pose.invert(before[1]), T_last))
    per_frame = twist / (last - before[0])
    return pose.normalize(pose.compose(T_last, pose.exp_se3(per_frame * steps)))


RESIDUAL_HISTORY = 20
RELOC_RESIDUAL = 1.5
"""A relocalization is accepted when its residual is at most this times the median residual
of the last `RESIDUAL_HISTORY` frames tracked: a wrong pose that passes the solver's own
checks still leaves more residual than tracking did (on a synthetic sequence blanked for
10 frames: 0.046 at the true pose, 0.073 at the wrong ones, 0.036-0.042 before the gap)."""


class FrontEnd:
    """The frames the tracker holds, and the steps that track each new one."""

    def __init__(self, cfg: SlamConfig, camera: Camera, generator: torch.Generator) -> None:
        self.cfg = cfg
        self.camera = camera
        self.tracker: Tracker | DirectTracker
        # Pixels of its own for `_refine`: a run where no frame is refined is the run without.
        self.refine_generator = torch.Generator(generator.device).manual_seed(
            generator.initial_seed() + 2
        )
        if cfg.tracker.solver == "direct":
            self.tracker = DirectTracker(cfg.tracker, cfg.render, camera, generator)
        else:
            self.tracker = Tracker(cfg.tracker, cfg.loss, cfg.render, camera, generator)
        self.frames: list[FrameState] = []
        self.pending: list[FrameState] = []
        self.next_guess: torch.Tensor | None = None
        self.last_result: TrackResult | None = None
        self.lost: list[tuple[int, float]] = []  # (index, timestamp) of the frames lost
        self.residuals: deque[float] = deque(maxlen=RESIDUAL_HISTORY)
        self.gap = 0  # frames lost since the last one tracked
        # (index, T_wc) where the solves of the frames lost since the last one tracked ended,
        # when they ended somewhere (`TrackingLost.best`): followed by the motion model only.
        self.followed: list[tuple[int, torch.Tensor]] = []
        self.init_last = -1  # index of the newest frame the initialization mapped
        self.refined: list[int] = []  # frames solved again by the window objective (`_refine`)
        self.live = False  # frames come from a live camera (`go_live`)

    def go_live(self) -> None:
        """The frames from now on come from a live camera: a new map renders only
        `tracker.live_map_renders` keyframes at once (where set), and a frame is lost under
        `tracker.live_min_inliers` of inliers (where set) instead of `min_inliers`. Live, a
        frame lost where the camera leaves what is mapped stays lost: a lost frame never
        reaches the mapper, so the map never grows to where the camera went."""
        self.live = True
        share = self.cfg.tracker.live_min_inliers
        if share > 0:
            self.tracker.cfg = replace(self.tracker.cfg, min_inliers=share)
        share = self.tracker.cfg.min_inliers
        log.info("a live stream: a frame is lost under %.0f %% inliers", 100 * share)

    @property
    def relocalizing(self) -> bool:
        """Whether the last frame was lost: the next one is searched for, not just tracked."""
        return self.gap > 0

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
        self.init_last = index
        return True

    def collect_rest(self) -> bool:
        """At the end of a stream too short to fill the initialization: hand over all frames
        if there are enough to start a map (3). True if so."""
        if len(self.frames) < 3:
            return False
        self.pending = list(self.frames)
        self.init_last = self.frames[-1].index
        return True

    def guess(self, index: int) -> torch.Tensor:
        """Where frame `index` starts: a continued map's last pose, else the last motion
        carried on to it (`extrapolate`, up to `MAX_VELOCITY_STEPS` frames), else the last
        pose."""
        if self.next_guess is not None:
            guess, self.next_guess = self.next_guess, None
            return guess
        return self.extrapolate(index, MAX_VELOCITY_STEPS)

    def extrapolate(self, index: int, limit: int) -> torch.Tensor:
        """The motion between the last two poses, per frame, carried on to frame `index`:
        the last pose when either gap (between those two, or on to `index`) exceeds `limit`
        frames, or when there is only one. The poses are the frames' and, after them, where
        the solves of the frames lost since ended (`followed`): through a stretch where the
        map is too poor to accept a solve, the guesses still follow the camera."""
        recent = [(f.index, f.T_wc) for f in self.frames[-2:]] + self.followed[-2:]
        return carry_motion(recent[-2:], index, limit)

    def track(
        self, field: FieldFn, index: int, timestamp: float, rgb: torch.Tensor
    ) -> FrameState | None:
        """Track one frame against the map; it joins the frames and the next batch.

        Returns:
            The frame with its pose, or None if it is lost (it is then only counted in `lost`:
            no pose is invented for it; the next frames relocalize).
        """
        keyframes = self.keyframes
        state = FrameState(index, timestamp, rgb, self.guess(index))
        if not torch.isfinite(state.T_wc).all():
            state.T_wc = self.frames[-1].T_wc.clone()
        guess = state.T_wc.clone()
        starts = self._starts(index, state.T_wc, keyframes) if self.relocalizing else []
        self.frames.append(state)
        local = self.frames[-self.cfg.tracker.local_frames :]
        refs = self._references(keyframes)
        try:
            if self.relocalizing:
                typical = statistics.median(self.residuals) if self.residuals else math.inf
                limit = RELOC_RESIDUAL * typical
                self.last_result = self.tracker.relocalize(field, local, refs, starts, limit)
            else:
                self.last_result = self.tracker.track(field, local, refs)
        except TrackingLost as error:
            self.frames.pop()
            self.lost.append((index, timestamp))
            if error.best is not None:
                self.followed.append((index, error.best))
            if not self.relocalizing:
                log.warning("tracking lost at frame %d (%s): relocalizing", index, error)
            else:
                log.debug("still lost at frame %d: %s", index, error)
            self.gap += 1
            return None
        self.residuals.append(self.last_result.stats.loss)
        if self.relocalizing:
            log.info("relocalized at frame %d after %d lost frames", index, self.gap)
        else:
            self._refine(field, local, refs, guess)
        self.gap = 0
        self.followed.clear()
        if self.tracker.is_keyframe(field, state, keyframes[-1]):
            state.keyframe = True
        stats = self.last_result.stats
        log.debug(
            "frame %d: %d iterations, loss %.4f, window %s%s",
            index,
            stats.iterations,
            stats.loss,
            self.last_result.window,
            " (keyframe)" if state.keyframe else "",
        )
        self.pending.append(state)
        release_images(self.frames, self.cfg.kept_images)
        return state

    def _refine(
        self,
        field: FieldFn,
        local: list[FrameState],
        keyframes: list[FrameState],
        guess: torch.Tensor,
    ) -> None:
        """`tracker.window_refine_deg`: where the solve turned the newest frame away from
        its motion guess by more than that, solve it again from the guess by the window
        objective and take that end.

        In a fast turn of a narrow view the direct solve against keyframes can slide (turn
        too far and step back) into a minimum of its cost; the window objective, with the
        frames before it as sources and its visibility mask, holds such a turn from the
        motion guess, where the Adam tracker starts every frame (docs/results.md, sessions
        17-18). With `window_refine_seen`, only a departure whose turn the images hardly see
        starts such a stretch (a jerk of a hand-held camera is a turn they see), and every
        departure right after a frame solved again continues it: within a slide the share
        seen swings (room5 seed 0: 0.16-1.06)."""
        cfg = self.cfg
        if cfg.tracker.window_refine_deg <= 0 or not isinstance(self.tracker, DirectTracker):
            return
        newest = local[-1]
        turned = pose.angle_between(guess, newest.T_wc)
        if math.degrees(turned) <= cfg.tracker.window_refine_deg:
            return
        seen = self._turn_seen(guess, newest.T_wc, keyframes)
        sliding = len(self.frames) > 1 and self.refined[-1:] == [self.frames[-2].index]
        if 0 < cfg.tracker.window_refine_seen <= seen and not sliding:
            log.info(
                "frame %d: %.2f deg from its guess, %.2f of it seen: kept",
                newest.index,
                math.degrees(turned),
                seen,
            )
            return
        sources = [f for f in local if f.rgb is not None]
        if len(sources) < 2:
            return
        refiner = Tracker(cfg.tracker, cfg.loss, cfg.render, self.camera, self.refine_generator)
        end = refiner.refine(field, sources, keyframes, cfg.tracker.iters, [guess])[0]
        if end is None:
            return
        newest.T_wc = end[0]
        self.refined.append(newest.index)
        log.info(
            "frame %d: %.2f deg from its guess, %.2f of it seen; refined from the guess by the "
            "window objective",
            newest.index,
            math.degrees(turned),
            seen,
        )

    def _turn_seen(
        self, guess: torch.Tensor, end: torch.Tensor, keyframes: list[FrameState]
    ) -> float:
        """How much of the image motion that the rotation from `guess` to `end` alone gives
        the reference points is left with the translation between them added (medians over
        the points): near 0 where the translation hides the turn (the turn-or-slide of a
        narrow view), near 1 or above for a turn the images see. NaN without points."""
        refs = getattr(self.tracker, "references", {})
        points = [refs[kf.index].world() for kf in keyframes if kf.index in refs]
        if not points:
            return math.nan
        p = pose.transform_points(pose.invert(guess), torch.cat(points))
        p = p[p[:, 2] > 0]
        delta = pose.compose(pose.invert(end), guess)  # guess camera -> end camera
        turned = p @ delta[:3, :3].T
        moved = turned + delta[:3, 3]

        def flow(q: torch.Tensor) -> torch.Tensor:
            return (q[:, :2] / q[:, 2:] - p[:, :2] / p[:, 2:]).norm(dim=-1).median()

        return float(flow(moved) / flow(turned).clamp_min(1e-12))

    def _references(self, keyframes: list[FrameState]) -> list[FrameState]:
        """The keyframes a frame is tracked against, and, while frame 0 is the only one
        (`tracker.init_reference`), the newest frame the initialization mapped: a camera that
        moved far during the initialization has it beside its first tracked frames."""
        newest = self.frames[-2] if len(self.frames) > 1 else None  # before the new frame
        if (
            not self.cfg.tracker.init_reference
            or len(keyframes) != 1
            or newest is None
            or newest.keyframe
            or newest.index != self.init_last
        ):
            return keyframes
        return [*keyframes, newest]

    def _starts(
        self, index: int, guess: torch.Tensor, keyframes: list[FrameState]
    ) -> list[torch.Tensor]:
        """Poses a lost frame's search starts from (`tracker.reloc_candidates` in all): its
        guess, the last motion carried over the whole gap, and the poses of the keyframes
        nearest to the guess (called before the frame joins `frames`)."""
        starts = [guess, self.extrapolate(index, MAX_EXTRAPOLATION)]
        centre = guess[:3, 3]
        near = sorted(keyframes, key=lambda kf: float((kf.T_wc[:3, 3] - centre).norm()))
        starts += [kf.T_wc for kf in near]
        starts = starts[: self.cfg.tracker.reloc_candidates]
        # Across a short gap the carried motion is the guess itself: search from it once.
        return [s for i, s in enumerate(starts) if not any(torch.equal(s, t) for t in starts[:i])]

    def map_changed(self, field: FieldFn, version: int) -> int:
        """A new map (after a mapping round, or a snapshot swapped in): let the solver refresh
        what it caches of it (live: `tracker.live_map_renders` keyframes at once). Returns how
        many keyframes it rendered."""
        renders = self.cfg.tracker.live_map_renders if self.live else 0
        return self.tracker.map_changed(field, self.keyframes, version, renders)

    def batch_due(self) -> bool:
        """Whether the frames tracked since the last hand-over make a mapping round: every
        `mapper.every` frames, and at once when the tracker is lost. A frame is mostly lost
        where the camera has run ahead of the map (the residual climbs over the frames before
        the loss), and no later frame can be placed until the map there improves: the frames
        tracked up to the loss are what it needs."""
        every = self.cfg.mapper.every
        return bool(self.pending) and (
            self.relocalizing or self.pending[-1].index % every == 0 or len(self.pending) >= every
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

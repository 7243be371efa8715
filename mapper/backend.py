"""The mapper's half of the pipeline: tracked frames in, map rounds, refined poses out.

What the mapping side does with the frames the tracker hands over, written once for both
drivers (`common/slam.py` in one process, `mapper/service.py` as a process of its own):

1. The first hand-over initializes the map on its frames (`Mapper.initialize`).
2. Every later one is followed by a mapping round on the newest `every` frames plus the
   keyframes overlapping the newest (`Mapper.map`). Frames handed over in between rounds
   (a mapper that fell behind, a stop) are not mapped: they keep their tracked poses
   relative to their keyframes.
3. After each round, every non-keyframe of the round, and every other one received since the
   previous round, records its pose relative to the keyframe before it, so the final
   trajectory follows later refinements of that keyframe.
   Every `mapper.global_every` rounds a global refinement round follows (`refine_global`):
   a window about a random keyframe, anywhere on the path, with its overlapping keyframes,
   poses and map optimized together.
4. Each new keyframe is described for place recognition and matched against the old ones;
   a verified loop that disagrees with the poses is closed: a Sim(3) pose graph over the
   keyframes moves them, the frames anchored to them follow, and the map is refitted to the
   corrected poses (`mapper/loop.py`).
5. Frames no window will use again lose their images.
"""

from __future__ import annotations

import logging
import math
import time
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from dimslam.common.config import SlamConfig
from dimslam.common.eval.evaluation import umeyama
from dimslam.common.eval.mesh_views import write_mesh_views
from dimslam.common.geometry import pose, sim3
from dimslam.common.geometry.camera import Camera
from dimslam.common.io.trajectory import Trajectory
from dimslam.common.map.mesh import EmptyMeshError, write_mesh
from dimslam.common.optim.window import FrameState, release_images
from dimslam.mapper.bundle import (
    FeatureTracks,
    FlowTracks,
    adjust_tracks,
    grey_image,
    prior_at,
    prior_for,
    slide_checked,
    with_flow,
)
from dimslam.mapper.loop import Loop, LoopCloser, map_depth
from dimslam.mapper.mapper import Mapper, MapRound
from dimslam.tracker.frontend import MAX_VELOCITY_STEPS, carry_motion
from dimslam.tracker.tracker import Tracker, keyframe_due

if TYPE_CHECKING:  # imported where a mesh is made: trimesh and scipy take 0.5 s to load
    import trimesh

log = logging.getLogger(__name__)


SCALE_STEPS = 5
"""Keyframe steps over which a keyframe's change of scale is measured (`local_scales`)."""


def local_scales(before: torch.Tensor, after: torch.Tensor) -> torch.Tensor:
    """How much the path about each keyframe grew from `before` to `after` (`(n, 4, 4)`
    poses of the keyframes in path order): the length of the `SCALE_STEPS` steps about the
    keyframe's step to the next one, after against before. A single step between keyframes
    is short enough for its ratio to be noise (0.6-2.1 on room0)."""
    n = len(before)
    if n < 2:
        return torch.ones(n, dtype=after.dtype)
    old = (before[1:, :3, 3] - before[:-1, :3, 3]).norm(dim=1).to(after.dtype)
    new = (after[1:, :3, 3] - after[:-1, :3, 3]).norm(dim=1)
    half = SCALE_STEPS // 2
    scales = []
    for k in range(n):
        a, b = max(0, min(k, n - 2) - half), min(n - 1, min(k, n - 2) + half + 1)
        length = old[a:b].sum()
        scales.append(new[a:b].sum() / length if length > 1e-9 else torch.ones(()))
    return torch.stack(scales).to(after.dtype)


def brought_back(before: torch.Tensor, adjusted: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Keyframe poses `adjusted` (float64, path order) from `before` brought back onto the
    old path by the similarity that fits them best, so that they move only by what the
    adjustment changed in the path's shape (the map was fitted to the old path), and how
    much the path about each keyframe grew (`local_scales`): the scale of the offsets of
    the frames anchored to it."""
    fit = umeyama(adjusted[:, :3, 3].numpy(), before[:, :3, 3].numpy())
    after = torch.from_numpy(fit.apply_poses(adjusted.numpy()))
    return after, local_scales(before, after)


class BackEnd:
    """The frames the mapper holds, the map, and the rounds that refine them."""

    def __init__(
        self, cfg: SlamConfig, camera: Camera, device: torch.device, generator: torch.Generator
    ) -> None:
        self.cfg = cfg
        self.camera = camera
        # The keyframes' refinement draws its pixels from a stream of its own, so that a run
        # where it changes no pose is the run without it (the mapper's draws stay as they were).
        self.refine_generator = torch.Generator(generator.device).manual_seed(
            generator.initial_seed() + 1
        )
        # The initialization's marked frames (`mapper.init_keyframes`, `bundle.init_frames`)
        # too, for the same reason.
        self.init_generator = torch.Generator(generator.device).manual_seed(
            generator.initial_seed() + 2
        )
        self.mapper = Mapper(
            cfg.mapper,
            cfg.map,
            cfg.loss,
            cfg.render,
            cfg.tracker.overlap,
            cfg.tracker.overlap_pixels,
            camera,
            device,
            generator,
        )
        self.frames: list[FrameState] = []
        # Non-keyframe index -> (its keyframe, pose relative to it), for the final trajectory.
        self.anchors: dict[int, tuple[FrameState, torch.Tensor]] = {}
        self.initialized = False
        self.rounds = 0
        self.short_rounds = 0  # rounds on live frames cut to `mapper.live_iters`
        self.round_seconds: list[float] = []
        # Seconds each part of the mapping rounds took, summed over the rounds (`phases`).
        self.phase_seconds: dict[str, float] = {}
        self.closer = (
            LoopCloser(cfg.loop, camera, cfg.render, cfg.tracker, cfg.mapper.gauge_depth, device)
            if cfg.loop.enabled
            else None
        )
        self.closed: list[Loop] = []
        bundle = cfg.bundle
        self.tracks = (
            FeatureTracks(camera.K, bundle.features, bundle.neighbours) if bundle.enabled else None
        )
        self.flow = (
            FlowTracks(bundle.flow, bundle.flow_realign)
            if bundle.enabled and bundle.flow > 0
            else None
        )
        self.adjusted_at = 0  # keyframes with features at the last adjustment
        # Frames the adjustment holds besides the keyframes (`bundle.init_frames`): not the
        # tracker's references nor the mapping rounds' keyframes.
        self.extra: set[int] = set()
        self.taken = 0  # frames (of `frames`, in order) a round or the finish has anchored

    @property
    def field(self):
        return self.mapper.field

    @property
    def keyframes(self) -> list[FrameState]:
        return [f for f in self.frames if f.keyframe]

    def add(self, frames: list[FrameState]) -> None:
        """Frames handed over by the tracker (newest last), at their tracked poses; a frame
        already held is not taken twice (a tracker sends again what a mapper may have lost)."""
        held = {f.index for f in self.frames}
        new = [f for f in frames if f.index not in held]
        if len(new) < len(frames):
            log.info("%d frames received again, already held", len(frames) - len(new))
        self.frames.extend(new)

    def step(self, live: bool = False) -> MapRound:
        """Initialize on the frames held, or run a mapping round on the newest of them; one
        on `live` frames is short (`mapper.live_iters`) and runs no global refinement and
        describes no features.

        Returns:
            What the round did; `window` names the frames it refined.
        """
        started = time.perf_counter()
        short = False
        if not self.initialized:
            result = self.mapper.initialize(self.frames)
            self.initialized = True
            log.info(
                "initialized on %d frames in %.1f s (loss %.4f, warp %.4f)",
                len(self.frames),
                time.perf_counter() - started,
                result.stats.loss,
                result.stats.warp,
            )
            window = self.frames
            if self.cfg.mapper.init_keyframes:
                for f in self._init_marked():
                    f.keyframe = True
            elif self.tracks is not None and self.cfg.bundle.init_frames:
                self.extra = {f.index for f in self._init_marked()}
        else:
            window = self.frames[-self.cfg.mapper.every :]
            with self._timed("refine"):
                self._refine_keyframes(window)
            short = live and self.cfg.mapper.live_iters > 0
            self.short_rounds += short
            with self._timed("map"):
                iters = self.cfg.mapper.live_iters if short else None
                result = self.mapper.map(window, self.keyframes, iters)
        reclaim = self.cfg.map.reclaim_every
        if reclaim > 0 and self.rounds % reclaim == 0:  # round 0: the initialization
            begun = time.perf_counter()
            with self._timed("reclaim"):
                frames = self.keyframes + [f for f in window if not f.keyframe]
                freed = self.mapper.reclaim(frames)
            log.info(
                "the map forgot %.1f MB of cells no ray of %d frames stops near now "
                "(%.1f MB kept, %.1f s)",
                freed / 2**20,
                len(frames),
                self.field.memory_bytes() / 2**20,
                time.perf_counter() - begun,
            )
        fresh = self._fresh(window)
        self._anchor(fresh)
        every = self.cfg.mapper.global_every
        if every > 0 and self.rounds > 0 and self.rounds % every == 0 and not short:
            with self._timed("global"):
                self.refine_global()
        with self._timed("loops"):
            self._close_loops(window)
        if not short:  # the features serve the end-of-run adjustment (`bundle.min_described`)
            with self._timed("features"):
                self._describe(window)
        elif self.cfg.bundle.live:
            with self._timed("flow"):
                self._observe_live(fresh)
        every = self.cfg.bundle.every
        if self.tracks is not None and every > 0:
            if len(self.tracks.keyframes) - self.adjusted_at >= every:
                with self._timed("adjust"):
                    self.adjust_keyframes()
        self.rounds += 1
        self.round_seconds.append(time.perf_counter() - started)
        release_images(self.frames, self.cfg.kept_images)
        return result

    def _init_marked(self) -> list[FrameState]:
        """The initialization's frames after frame 0 that the tracker's rule
        (`keyframe_due`) makes keyframes on the new map, each measured from the last one, as
        if tracked (`mapper.init_keyframes`, `bundle.init_frames`)."""
        last, marked = self.frames[0], []
        for f in self.frames[1:]:
            if keyframe_due(
                self.field,
                f,
                last,
                self.camera,
                self.cfg.tracker,
                self.cfg.render,
                self.init_generator,
            ):
                marked.append(f)
                last = f
        log.info(
            "the initialization's frames the tracker's rule marks: frames %s",
            ", ".join(str(f.index) for f in [self.frames[0], *marked]),
        )
        return marked

    @contextmanager
    def _timed(self, phase: str):
        started = time.perf_counter()
        try:
            yield
        finally:
            seconds = time.perf_counter() - started
            self.phase_seconds[phase] = self.phase_seconds.get(phase, 0.0) + seconds

    def phases(self) -> str:
        """Where the mapping rounds' time went: seconds per round of each part, e.g.
        `map 6.1, global 2.3, loops 0.9` (the initialization's optimization not counted)."""
        rounds = max(1, self.rounds)
        return ", ".join(f"{k} {v / rounds:.1f}" for k, v in self.phase_seconds.items())

    def _fresh(self, window: list[FrameState]) -> list[FrameState]:
        """The round's `window` (the newest frames held) with every frame received since the
        previous round: the frames from the older of the two on. A mapper that fell behind a
        live stream maps only the newest frames of its backlog, but the others still anchor
        to their keyframes, so that they follow later corrections, and (`bundle.live`) the
        flow observes them. They are not described in the round: describing a keyframe
        costs 100-200 ms, a live backlog holds dozens (room0 at 10 FPS, one run: rounds of
        18.3 s against 12.3 s without); the end of the run describes the keyframes."""
        start = min(self.taken, len(self.frames) - len(window))
        self.taken = len(self.frames)
        return self.frames[start:]

    def _refine_keyframes(self, window: list[FrameState]) -> None:
        """`mapper.refine_keyframes` steps of the tracking window objective on each keyframe
        of `window`, against the frames before it that keep their images and the older
        keyframes: once from its tracked pose, once from the motion of the two frames before
        it carried on (as the Adam tracker starts a frame). Where the two ends are different
        minima (`mapper.refine_apart_deg`) and the motion's scores lower, it replaces the
        tracked pose, and the frames after it move with it so that their motion stays as
        tracked; elsewhere the tracked pose stays.

        The direct tracker solves each frame against keyframes only, where a fast turn of a
        narrow view can slide (turn too far and step back) into a minimum of that cost; the
        window objective, with the recent frames as sources and its visibility mask, holds
        the turn when started from the motion guess. Taking its end everywhere cost the
        smooth stretches (docs/results.md, session 21), so it only judges between two minima.
        Keyframes are what the map is fitted to, so theirs are the poses refined."""
        cfg = self.cfg.mapper
        if cfg.refine_keyframes <= 0:
            return
        refiner = Tracker(
            self.cfg.tracker, self.cfg.loss, self.cfg.render, self.camera, self.refine_generator
        )
        position = {id(f): k for k, f in enumerate(self.frames)}
        for kf in [f for f in window if f.keyframe and f.rgb is not None]:
            k = position[id(kf)]
            local = [f for f in self.frames[:k] if f.rgb is not None]
            if len(local) < 2:
                continue
            local = [*local[-(self.cfg.tracker.local_frames - 1) :], kf]
            older = [f for f in self.keyframes if f.index < kf.index]
            tracked = kf.T_wc.clone()
            guess = carry_motion(
                [(f.index, f.T_wc) for f in local[-3:-1]], kf.index, MAX_VELOCITY_STEPS
            )
            ends = refiner.refine(self.field, local, older, cfg.refine_keyframes, [tracked, guess])
            if ends[0] is None or ends[1] is None:
                continue
            apart = math.degrees(pose.angle_between(ends[0][0], ends[1][0]))
            log.debug(
                "keyframe %d: refined ends %.2f deg apart, objective %.5f (tracked) %.5f (guess)",
                kf.index,
                apart,
                ends[0][1],
                ends[1][1],
            )
            if apart <= cfg.refine_apart_deg or ends[1][1] >= ends[0][1]:
                continue
            kf.T_wc = ends[1][0]
            correction = pose.compose(kf.T_wc, pose.invert(tracked))
            for f in self.frames[k + 1 :]:
                f.T_wc = pose.normalize(pose.compose(correction, f.T_wc))

    def _close_loops(self, window: list[FrameState]) -> None:
        """Describe the window's new keyframes and close the first loop one of them finds."""
        if self.closer is None:
            return
        new = [f for f in window if f.keyframe and f.index not in self.closer.codes]
        depth = map_depth(self.field, self.camera, self.cfg.render)
        for f in new:
            self.closer.add(f, depth)
        keyframes = self.keyframes
        for f in new:
            loop = self.closer.detect(f, keyframes)
            if loop is None:
                continue
            if self.closer.agrees(loop):
                log.info(
                    "loop %d -> %d agrees with the poses: nothing to correct", f.index, loop.old
                )
                continue
            result = self.closer.correct(keyframes, loop)
            moved = self._move(keyframes, result.nodes)
            self.closed.append(loop)
            started = time.perf_counter()
            # Refit where the map moved most: windows about the keyframes moved farthest.
            order = sorted(range(len(keyframes)), key=lambda k: -moved[k])
            anchors = [keyframes[k] for k in order[: max(1, self.cfg.loop.refit_iters // 20)]]
            self.mapper.post_optimize(keyframes, self.cfg.loop.refit_iters, anchors=anchors)
            log.info(
                "loop %d -> %d closed; map refitted to the corrected poses in %.1f s",
                loop.new,
                loop.old,
                time.perf_counter() - started,
            )
            return

    def refine_global(self, iters: int | None = None) -> None:
        """A global refinement round (`mapper.global_every`; `iters`, default
        `mapper.global_iters`): keyframes anywhere on the path and the map optimized together,
        in one window about a random keyframe; the frames anchored to keyframes follow."""
        iters = self.cfg.mapper.global_iters if iters is None else iters
        self.mapper.post_optimize(self.keyframes, iters, chunk=iters, poses=True)
        self._follow_anchors()

    def _move(self, keyframes: list[FrameState], nodes: torch.Tensor) -> list[float]:
        """Move keyframes to their corrected Sim(3) nodes (scale dropped from the poses), and
        the frames anchored to them with them: their offsets scale with their keyframe.
        Returns how far each keyframe moved."""
        scales, moved = {}, []
        for kf, node in zip(keyframes, nodes, strict=True):
            T, s = sim3.to_pose(node)
            T = T.to(kf.T_wc)
            moved.append(float((T[:3, 3] - kf.T_wc[:3, 3]).norm()))
            kf.T_wc = T
            scales[id(kf)] = float(s)
        for index, (kf, rel) in self.anchors.items():
            rel = rel.clone()
            rel[:3, 3] *= scales.get(id(kf), 1.0)
            self.anchors[index] = (kf, rel)
        self._follow_anchors()
        return moved

    def _follow_anchors(self) -> None:
        """Every anchored frame takes its final pose (after its keyframe moved)."""
        for f in self.frames:
            if not f.keyframe and f.index in self.anchors:
                f.T_wc = self.final_pose(f)

    def finish(self) -> bool:
        """End of the sequence: the feature bundle adjustment (`bundle.enabled`) and the
        optional post-optimization over all keyframes. Returns whether either ran (poses or
        map changed)."""
        if not self.initialized:
            return False
        self._anchor(self._fresh([]))  # frames kept at a stop without a round
        if self.tracks is not None:
            if self._live_path():
                self._describe_left()
            self.adjust_keyframes()
        if self.cfg.mapper.post_iters > 0:
            self.mapper.post_optimize(self.keyframes)
        return self.tracks is not None or self.cfg.mapper.post_iters > 0

    def _live_path(self) -> bool:
        """Whether the end-of-run adjustment takes the path as live (`bundle.live`): some
        of its rounds were, and described nothing."""
        return self.cfg.bundle.live and self.short_rounds > 0

    def _observe_live(self, frames: list[FrameState]) -> None:
        """A live round's new `frames` (path order) into the flow (`bundle.live`): followed
        through each and observed at each, with corners started at the keyframes; every
        frame it observes is held by the end-of-run adjustment (`extra`). The keyframes'
        ORB features wait for the end (`_describe_left`): they cost 100-200 ms each, the
        flow a few ms a frame."""
        if self.flow is None:
            return
        for f in frames:
            if f.rgb is None:
                continue
            self.flow.add(f.index, grey_image(f.rgb), f.keyframe, observe=True)
            if not f.keyframe and f.index in self.flow:
                self.extra.add(f.index)

    def _describe_left(self) -> None:
        """Describe the keyframes that the live rounds left undescribed (ORB), from the
        images the mapper keeps (the keyframes' and the newest frames')."""
        started = time.perf_counter()
        before = len(self.tracks.keyframes)
        self._describe(self.frames)
        log.info(
            "described %d keyframes the live rounds left (%.1f s)",
            len(self.tracks.keyframes) - before,
            time.perf_counter() - started,
        )

    def _held(self, f: FrameState) -> bool:
        """Whether the adjustment holds `f`: a keyframe, or an `extra` frame."""
        return f.keyframe or f.index in self.extra

    def _describe(self, frames: list[FrameState]) -> None:
        """Add the new keyframes and `extra` frames among `frames` (path order) to the
        feature tracks (`bundle.enabled`), and every new frame to the flow's (`bundle.flow`;
        with `bundle.every_frame` observed there and held as an `extra` frame)."""
        if self.tracks is None:
            return
        newest = max(self.tracks.keyframes, default=-1)
        for f in frames:
            if f.rgb is None:
                continue
            held = self._held(f)
            grey = grey_image(f.rgb) if held or self.flow is not None else None
            if self.flow is not None:
                every = self.cfg.bundle.every_frame and not held
                self.flow.add(f.index, grey, held, observe=every)
                if every and f.index in self.flow:
                    self.extra.add(f.index)  # held, not described (ORB)
            if held and f.index > newest:
                self.tracks.add(f.index, grey)

    def adjust_keyframes(self) -> None:
        """Refine every described keyframe's pose (and `extra` frame's) by the feature bundle
        adjustment (`mapper/bundle.py`); the frames anchored to a keyframe follow it, their offsets
        scaled as the path about it was (`local_scales`), and the map is refitted to the
        new poses where they moved most."""
        assert self.tracks is not None
        cfg = self.cfg.bundle.live_path() if self._live_path() else self.cfg.bundle
        held = [f for f in self.frames if self._held(f)]
        # Described: ORB features, or (a live run's frames) the flow's alone.
        keyframes = [
            kf
            for kf in held
            if kf.index in self.tracks or (self.flow is not None and kf.index in self.flow)
        ]
        if len(keyframes) < 3:
            return
        if len(keyframes) < cfg.min_described * len(held):
            log.info(
                "no feature bundle adjustment: %d of %d keyframes described (under %.0f %%)",
                len(keyframes),
                len(held),
                100 * cfg.min_described,
            )
            return
        self.adjusted_at = len(self.tracks.keyframes)
        started = time.perf_counter()
        indices = [kf.index for kf in keyframes]
        described = self.tracks.observations(indices, cfg.views)
        obs = with_flow(described, self.flow, indices, cfg)
        T_wc = torch.stack([kf.T_wc.detach().cpu().double() for kf in keyframes])
        K = torch.from_numpy(self.camera.K)
        start, free = T_wc, None
        if cfg.slides:
            check = slide_checked(T_wc, K, self.tracks, self.flow, indices, cfg)
            start, free = check.start, check.free
            for first, last in check.stretches:
                log.info(
                    "the features contradict the tracked motion at keyframes of frames %d-%d: "
                    "adjusted from the motion before them",
                    indices[first],
                    indices[last],
                )
        if cfg.every_frame and not self._live_path():  # the prior between described frames
            at = [k for k, kf in enumerate(keyframes) if kf.index in self.tracks]
            prior = prior_at(start, obs, cfg, torch.tensor(at), free)
        else:
            prior = prior_for(start, obs, cfg, free)
        result = adjust_tracks(self.tracks, indices, start, K, cfg, prior, self.flow, free)
        # The adjustment holds only two keyframes, so the path as a whole may come out
        # turned or scaled about them.
        T_new, scales = brought_back(T_wc, result.T_wc)
        everyone, nodes = self._with_undescribed(keyframes, T_new, scales, held)
        if self.extra:  # in this move the frames after an extra one follow it
            self._anchor(self.frames, held)
        moved = self._move(everyone, nodes)
        if self.extra:  # and later corrections move every frame with its keyframe again
            self._anchor(self.frames)
        log.info(
            "feature bundle adjustment of %d keyframes (%d more follow): %d points (of %d "
            "ORB tracks and %d flow tracks), %d observations (%d by guided matching), cost "
            "%.1f; held frames %d and %d; keyframes moved %.3f median, %.3f at most; steps "
            "scaled %.2f-%.2f (%.1f s)",
            len(keyframes),
            len(everyone) - len(keyframes),
            result.points,
            described.points,
            obs.points - described.points,
            result.observations,
            result.guided,
            result.cost,
            indices[result.held],
            indices[result.held + 1],
            float(np.median(moved)),
            max(moved),
            float(scales.min()),
            float(scales.max()),
            time.perf_counter() - started,
        )
        if result.factors:
            log.info(
                "the prior's %s weighed by the residuals: x %.2f (%.2f degrees; the "
                "features reproject within %.2f px)",
                cfg.weighed,
                *result.turns(cfg.turn_deg),
                result.reprojection,
            )
        if cfg.refit_iters > 0:
            mapped = [k for k, f in enumerate(everyone) if f.keyframe]  # not the extra ones
            order = sorted(mapped, key=lambda k: -moved[k])
            anchors = [everyone[k] for k in order[: max(1, cfg.refit_iters // 20)]]
            self.mapper.post_optimize(
                [everyone[k] for k in mapped], cfg.refit_iters, anchors=anchors
            )

    def _with_undescribed(
        self,
        described: list[FrameState],
        T_new: torch.Tensor,
        scales: torch.Tensor,
        held: list[FrameState],
    ) -> tuple[list[FrameState], torch.Tensor]:
        """Every frame of `held` (the keyframes and the `extra` frames, path order) from the
        first `described` one on, with its Sim(3) node after the adjustment moved the
        described ones to `T_new` (path growing by `scales` about each). A mapper behind a
        live camera describes only its rounds' keyframes; a keyframe between two described
        ones takes the similarity that moved them, interpolated by its place between them
        (on the Sim(3) geodesic), and one after the last described takes that one's, so that
        the path stays in one piece. Offline every keyframe is described and this is
        `described` itself."""
        moves = [
            sim3.compose(
                sim3.from_pose(T_new[k], scales[k]),
                sim3.invert(sim3.from_pose(kf.T_wc.detach().cpu().double())),
            )
            for k, kf in enumerate(described)
        ]
        at = {kf.index: k for k, kf in enumerate(described)}
        everyone, nodes = [], []
        for kf in held:
            k = at.get(kf.index)
            if k is not None:
                everyone.append(kf)
                nodes.append(sim3.from_pose(T_new[k], scales[k]))
                continue
            before = [j for j, d in enumerate(described) if d.index < kf.index]
            if not before:
                continue
            a = before[-1]
            move = moves[a]
            if a + 1 < len(described):
                w = (kf.index - described[a].index) / (described[a + 1].index - described[a].index)
                step = sim3.log_sim3(sim3.compose(sim3.invert(move), moves[a + 1]))
                move = sim3.compose(move, sim3.exp_sim3(w * step))
            everyone.append(kf)
            nodes.append(sim3.compose(move, sim3.from_pose(kf.T_wc.detach().cpu().double())))
        return everyone, torch.stack(nodes)

    def reanchor(self) -> None:
        """Anchor every non-keyframe held to the keyframe before it (a resumed map)."""
        self._anchor(self.frames)
        self.taken = len(self.frames)

    def _anchor(self, frames: list[FrameState], held: list[FrameState] | None = None) -> None:
        """Record each non-keyframe's pose relative to the keyframe before it (or to the
        frame of `held`, path order, before it)."""
        keyframes = self.keyframes if held is None else held
        ids = {id(kf) for kf in keyframes}
        for f in frames:
            if id(f) in ids:
                self.anchors.pop(f.index, None)
                continue
            before = [kf for kf in keyframes if kf.index <= f.index]
            if before:
                kf = before[-1]
                self.anchors[f.index] = (kf, pose.compose(pose.invert(kf.T_wc), f.T_wc))

    def final_pose(self, f: FrameState) -> torch.Tensor:
        """A frame's final pose: keyframes as refined, other frames re-anchored."""
        if not f.keyframe and f.index in self.anchors:
            kf, rel = self.anchors[f.index]
            return pose.normalize(pose.compose(kf.T_wc, rel))
        return f.T_wc

    def trajectory(self, keyframes_only: bool = False) -> Trajectory:
        """Final poses of every frame (or of the keyframes); empty before initialization."""
        frames = self.frames if self.initialized else []
        if keyframes_only:
            frames = [f for f in frames if f.keyframe]
        if not frames:
            return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
        return Trajectory(
            np.array([f.timestamp for f in frames], dtype=np.float64),
            np.stack([self.final_pose(f).detach().cpu().double().numpy() for f in frames]),
        )

    def write_loops(self, path: Path) -> None:
        """Write the loops closed (one line each: the keyframes, the check's figures and how
        far the poses were from the loop before its correction)."""
        lines = ["# new_keyframe old_keyframe pnp_inliers scale offset_gauge offset_deg\n"]
        for loop in self.closed:
            offset, angle, _ = loop.error
            scale = float(sim3.scale_of(loop.S_old_new))
            lines.append(
                f"{loop.new} {loop.old} {loop.inliers} {scale:.4f} {offset:.4f} "
                f"{math.degrees(angle):.2f}\n"
            )
        path.write_text("".join(lines))

    def extract_mesh(self) -> trimesh.Trimesh:
        """The map's surface seen from every frame held (see `Mapper.extract_mesh`).

        Raises:
            EmptyMeshError: no map or no surface yet.
        """
        if not self.initialized:
            raise EmptyMeshError("no map yet")
        poses = torch.stack([f.T_wc for f in self.frames])
        return self.mapper.extract_mesh(poses, self.cfg.render.far, self.keyframes)

    def write_mesh(self, out_dir: Path) -> Path | None:
        """Write `out_dir/mesh.ply` and its pictures, `mesh_views.png`; the PLY's path, or
        None (logged) when there is no surface yet."""
        try:
            mesh = self.extract_mesh()
        except EmptyMeshError as e:
            log.warning("no mesh written: %s", e)
            return None
        path = out_dir / "mesh.ply"
        write_mesh(mesh, path)
        log.info("mesh: %d vertices, %d faces -> %s", len(mesh.vertices), len(mesh.faces), path)
        write_mesh_views(mesh, self.camera, self.trajectory().poses, out_dir / "mesh_views.png")
        return path

"""The mapping side: owns the map; initialization, mapping rounds, post-optimization, mesh.

Paper section 3.3 and appendix. Initialization optimizes the map and the poses of the first
`init_frames` frames jointly (frame 0 fixed at identity). The scale of a monocular map is free,
so a gauge pins it (design.md section 5): the map starts as a fronto-parallel plane at
`gauge_depth` in front of frame 0, and during initialization a penalty keeps frame 0's median
rendered depth at `gauge_depth`. No ground truth enters anywhere.

The initialization checks itself: when its warp residual ends above `init_max_warp` (the camera
moved too fast for the frames to join from their motion guess, and map and poses settled on
a wrong depth), it starts again from poses of corners tracked through the frames
(`mapper/bootstrap.py`) and keeps whichever of the two fits the images better.

A mapping round optimizes grids, decoder and the poses of its window (keyframes overlapping the
newest frame plus the frames since the last round; frame 0 stays fixed, `hold_first`) on
random pixels.
"""

from __future__ import annotations

import functools
import logging
import math
from dataclasses import dataclass, replace

import torch

from dimslam.common.geometry.camera import Camera
from dimslam.common.map import mesh as meshing
from dimslam.common.map.field import MapConfig, make_field
from dimslam.common.map.render import (
    RenderConfig,
    camera_rays,
    render_chunked,
    render_pixels,
)
from dimslam.common.map.render import sample_depths as ray_depths
from dimslam.common.optim.objective import LossConfig, WindowLoss, window_objective
from dimslam.common.optim.window import (
    FrameState,
    WindowStats,
    adam,
    constant_velocity,
    optimize_window,
    overlapping_keyframes,
    random_pixels,
)
from dimslam.common.options import option
from dimslam.mapper.bootstrap import bootstrap
from dimslam.mapper.stereo import (
    SweepDepth,
    agreeing_depths,
    consistent_depths,
    plane_sweep,
    sample_depths,
)

log = logging.getLogger(__name__)

INIT_START = 3
"""Frames that start the initialization together (at identity: close enough to their truth)."""
CHECK_PIXELS = 4
"""The initialization's check evaluates the warp on this many times the mapping pixels."""
STEREO_BASELINE = (0.01, 0.15)
"""Baselines (shares of the gauge depth) of the frames a keyframe's plane sweep compares: the
widest within this range are taken (more parallax), among frames at most `STEREO_FRAMES`
before or after it whose optical axes are within `STEREO_ANGLE` degrees of its own."""
STEREO_FRAMES = 15
STEREO_ANGLE = 20.0
STEREO_NEAR = 0.2
"""The plane sweep searches depths from this share of the gauge depth to `RenderConfig.far`."""
MESH_PLANES = 48
"""Inverse depths each mesh view's plane sweep searches (`stereo.PLANES`, 64, for the mapping
rounds' sweeps): a quarter less time, the mesh no worse (fewer cost room3's completion;
docs/benchmarks.md, "Mesh extraction with the keyframes' plane sweeps")."""
MESH_MAP_WEIGHT = 0.3
"""Weight of the map's rendered depth in the mesh's fusion, against a plane sweep's 1: where a
view's sweep saw the surface, the map's depth is not used; where it did not, the map's fills,
and the sweeps of other views that saw that surface win over it."""
MESH_GATE = 0.1
"""The map's depth is left out of the mesh where the sweeps around say it is off by more than
this share (`agreeing_depths`)."""
MESH_GATE_SIGMA = 0.1
"""... over a Gaussian of this share of the mesh's width,"""
MESH_GATE_SUPPORT = 0.1
"""... resting on at least this much of its weight."""
RECLAIM_WIDTH = 40
"""Width of the keyframes' images whose rays say which fine cells the sparse map keeps
(`Mapper.reclaim`): a finest block (8 cells) spans several of their pixels at room depths."""
SCALE_ITERS = 3
"""Map-only iterations (times `init_grow_iters`) that measure the depth of frame 0 a restart
from tracked corners gives, before its poses are scaled to the gauge."""


def _learning(method):
    """The method optimizes the map: its rays may store new cells (`Field.learning`)."""

    @functools.wraps(method)
    def wrapped(self, *args, **kwargs):
        with self.field.learning():
            return method(self, *args, **kwargs)

    return wrapped


@dataclass(frozen=True)
class MapperConfig:
    """Mapping budget (paper: 3000 random px, 100 iterations every 5 frames; init 13 frames)."""

    every: int = option(5, "Frames between mapping rounds.")
    pixels: int = option(3000, "Random pixels per mapping iteration.")
    iters: int = option(100, "Adam iterations per mapping round.")
    grid_lr: float = option(1e-3, "Learning rate of the feature grids.")
    decoder_lr: float = option(
        1e-3, "Learning rate of the decoder in mapping rounds (0: frozen after initialization)."
    )
    pose_lr: float = option(1e-2, "Learning rate of the window's pose increments.")
    keep_adam: bool = option(
        False,
        "Mapping rounds share one Adam state for the map (False: a fresh one each round, "
        "as the paper's code).",
    )
    move_keyframes: bool = option(
        True, "Mapping rounds move the older keyframes' poses too (False: they anchor)."
    )
    hold_first: bool = option(
        True,
        "Mapping and global rounds never move frame 0's pose (False: it moves as any "
        "keyframe, and the map holds the gauge). Where the camera comes back to its start, "
        "those rounds move the keyframes there towards the drifted present, and a held frame "
        "0 is left behind with the frames anchored to it. Held by default: False on the AMD "
        "machine took 7-Scenes from 8.17 to 4.88 cm and room3 from 6.83 to 3.25 (3 seeds "
        "each), but room0 from 3.47 to 3.62 and room5 from 6.62 to 8.84 (docs/results.md, "
        "'Frame 0 left behind').",
    )
    window_keyframes: int = option(10, "Overlapping keyframes in a mapping window.")
    refine_keyframes: int = option(
        0,
        "Adam steps of the paper's tracking window objective (the `tracker` section's window "
        "settings) on each new keyframe's pose before its mapping round, once from the tracked "
        "pose and once from the motion of the two frames before it carried on (as the Adam "
        "tracker starts a frame), against those frames and the keyframes overlapping it; "
        "where the two ends lie apart and the motion's scores lower, it replaces the tracked "
        "pose and the frames after it follow (0: none).",
    )
    refine_apart_deg: float = option(
        0.5,
        "Degrees of rotation between the two refined ends of a keyframe above which they are "
        "different minima of the window objective (below: the tracked pose stays).",
    )
    init_frames: int = option(13, "Frames collected before initialization (paper: 13).")
    init_keyframes: bool = option(
        False,
        "After the initialization, its frames become keyframes by the tracker's rule on the new "
        "map (flow and overlap from the last one), not frame 0 alone: the end-of-run adjustment "
        "then holds the path there at every keyframe, and its frames are carried from a near one. "
        "AMD, 3 seeds, whole runs: room0 0.86 -> 0.53 cm, room3 1.46 -> 1.31, room5 1.55 -> "
        "2.56, 7-Scenes unchanged (docs/results.md, session 65); off: the same frames in the "
        "adjustment only, `bundle.init_frames`, are in the cpu preset.",
    )
    init_grow_iters: int = option(
        40, "Initialization iterations after each frame joins (frames join one at a time)."
    )
    init_iters: int = option(1500, "Joint map and pose iterations once every init frame joined.")
    init_lr_scale: float = option(10.0, "Map learning rates are multiplied by this during init.")
    init_max_warp: float = option(
        0.045,
        "An initialization whose warp residual ends above this starts again from poses of "
        "tracked corners and keeps the better fit (0: never).",
    )
    prior_iters: int = option(200, "Iterations fitting the initial plane at the gauge depth.")
    gauge_depth: float = option(2.0, "Median depth of frame 0 in map units (scale gauge).")
    gauge_weight: float = option(1.0, "Weight of the scale gauge penalty during init.")
    prior_stop: bool = option(
        True,
        "With render.normalize_depth, the initial plane is also fitted to stop every ray "
        "(a normalized depth is met by rays that barely stop).",
    )
    pose_gate: float = option(
        0.0,
        "Mapping and global rounds: rays the map stops less than this (their opacity) move "
        "the map but no pose. A surface newly in view starts where the map's empty space "
        "renders, and with little parallax the poses would follow it there (room0's turns "
        "with render.normalize_depth); 0: every ray moves both. Off: with session 26's "
        "division settings 0.7 takes room0's mean over 3 seeds from 6.82 to 4.50 cm, but "
        "room3's from 9.48 to 13.30 and room5's from 6.14 to 9.03 (docs/results.md, 'The "
        "gate's whole table').",
    )
    stereo_weight: float = option(
        0.0,
        "Weight of the multi-view depth target: in mapping rounds the depth rendered at a "
        "keyframe's pixel is pulled towards the depth a plane sweep against its neighbours "
        "found there (relative L1; 0: no sweeps). Off: over the first 150 frames, 0.3 cost room3 "
        "2.3 cm (3 seeds) and lost 48 frames of room0 seed 1 (docs/results.md, 'Where the "
        "scale goes').",
    )
    stereo_sources: int = option(4, "Neighbouring frames a keyframe's plane sweep compares.")
    post_iters: int = option(0, "Map-only post-optimization iterations over all keyframes.")
    global_every: int = option(
        0,
        "Mapping rounds between global refinement rounds: windows of a keyframe and the "
        "keyframes overlapping it, anywhere on the path, poses and map optimized together "
        "(0: never).",
    )
    global_iters: int = option(20, "Iterations of a global refinement round.")
    live_iters: int = option(
        0,
        "Service only: iterations of a mapping round on frames from a live camera, which "
        "also runs no global refinement and describes no features: short rounds keep the map "
        "up with the camera, where the tracker would run beyond what is mapped and be lost "
        "(0: `iters` always; the cpu preset: 5, rounds of about 0.9 s instead of 12 on room0 "
        "at 10 FPS, docs/results.md, sessions 52-53).",
    )
    idle_chunks: int = option(
        20,
        "Service only: short global refinement chunks (a quarter of global_iters each) a "
        "mapper runs while it waits for a batch, at most this many after each round; each "
        "is published as a snapshot (0: none). When they run depends on timing, so `dimslam "
        "run` in lockstep sets 0: there the service computes what one process does.",
    )
    mesh_voxel: float = option(0.02, "Marching-cubes spacing of the mesh, map units.")
    mesh_views: int = option(60, "Poses whose rendered depth is fused into the mesh.")
    mesh_width: int = option(160, "Width of the depth images rendered for the mesh's fusion.")
    mesh_sweeps: bool = option(
        True,
        "Fuse into the mesh each mesh view's plane sweep (keyframes, at their current poses), "
        "kept where multi-view consistent, with the map's depth where the sweeps agree with it "
        "(false: the map's depth alone).",
    )
    mesh_coarse: bool = option(
        True,
        "Fuse the depth on every other grid point first, at full resolution only near the "
        "surface (5x faster; islands under two voxels are lost).",
    )

    def __post_init__(self) -> None:
        if not 0 <= self.pose_gate <= 1:
            raise ValueError(f"mapper.pose_gate must be in [0, 1], got {self.pose_gate}")
        if self.live_iters < 0:
            raise ValueError(f"mapper.live_iters must be 0 or more, got {self.live_iters}")
        if self.idle_chunks < 0:
            raise ValueError(f"mapper.idle_chunks must be 0 or more, got {self.idle_chunks}")


@dataclass(frozen=True)
class MeshDepths:
    """The depth maps a mesh is fused from (`Mapper.mesh_depths`).

    Attributes:
        depths: `(V, h, w)` z-depth in map units at `camera`'s size, NaN where unknown.
        weights: `(V, h, w)` each pixel's weight in the fusion.
        T_wc: `(V, 4, 4)` the poses they are seen from.
        camera: their camera.
        rendered: `(V, h, w)` the depth the map renders there (NaN where it was not needed).
        index: `(V,)` the frame index of each view.
    """

    depths: torch.Tensor
    weights: torch.Tensor
    T_wc: torch.Tensor
    camera: Camera
    rendered: torch.Tensor
    index: torch.Tensor


@dataclass(frozen=True)
class MapRound:
    """What a mapping round (or the initialization) did."""

    stats: WindowStats
    window: tuple[int, ...]


class Mapper:
    """Builds and refines the implicit map."""

    def __init__(
        self,
        cfg: MapperConfig,
        map_cfg: MapConfig,
        loss_cfg: LossConfig,
        render_cfg: RenderConfig,
        overlap: float,
        overlap_pixels: int,
        camera: Camera,
        device: torch.device,
        generator: torch.Generator,
    ) -> None:
        self.cfg = cfg
        self.loss_cfg = loss_cfg
        self.render_cfg = render_cfg
        self.overlap = overlap
        self.overlap_pixels = overlap_pixels
        self.camera = camera
        self.generator = generator
        self.map_cfg = map_cfg
        self.field = make_field(map_cfg, device=device)
        self.margin = loss_cfg.margin()
        self._map_optimizer: torch.optim.Optimizer | None = None
        self.sweeps: dict[int, SweepDepth] = {}  # keyframe index -> its multi-view depth
        # keyframe index -> (its and its sources' poses, its plane sweep at them) for the mesh
        self._mesh_sweeps: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}

    def _adam(self, groups: list[dict]) -> torch.optim.Optimizer:
        """Adam over `groups`, following the grids when rays store new cells (sparse map)."""
        return self.field.follow(adam(groups))

    def _groups(self, decoder_lr: float, scale: float = 1.0) -> list[dict]:
        groups = [{"params": self.field.grid_parameters(), "lr": self.cfg.grid_lr * scale}]
        if decoder_lr > 0:
            groups.append({"params": self.field.decoder_parameters(), "lr": decoder_lr * scale})
        return groups

    def _round_optimizer(self) -> torch.optim.Optimizer:
        """The map's optimizer for a mapping round: fresh, or the one kept across rounds.

        A kept Adam remembers each parameter's gradient statistics: a voxel whose gradient
        has only been noise moves less, one seen for the first time moves more.
        """
        optimizer = self._map_optimizer or self._adam(self._groups(self.cfg.decoder_lr))
        if self.cfg.keep_adam:
            self._map_optimizer = optimizer
        return optimizer

    def _init_groups(self, scale: float) -> list[dict]:
        """Grids and decoder both learn while the map is built from nothing (a decoder frozen
        in mapping rounds learns at the grids' rate here)."""
        return self._groups(self.cfg.decoder_lr or self.cfg.grid_lr, scale)

    def _sampler(self, n_frames: int):
        device = self.field.bound.device

        def pixels(_: int) -> tuple[torch.Tensor, torch.Tensor]:
            return random_pixels(
                n_frames, self.cfg.pixels, self.camera, self.margin, self.generator, device
            )

        return pixels

    @_learning
    def fit_prior(self, first: FrameState) -> float:
        """Fit the map to a fronto-parallel plane at the gauge depth in front of `first`.

        Returns:
            The final mean absolute depth error, map units.
        """
        device = first.T_wc.device
        error = float("nan")
        # A map that grows where rays look must first hold the plane and the space before it.
        _, uv = random_pixels(1, 1024, self.camera, 0, self.generator, device)
        origins, directions = camera_rays(self.camera, uv, first.T_wc)
        depth = torch.linspace(self.render_cfg.near, 2 * self.cfg.gauge_depth, 64, device=device)
        with torch.no_grad():
            points = origins[:, None] + depth[:, None] * directions[:, None]
            surface = (depth - self.cfg.gauge_depth).abs().expand(points.shape[:2])
            self.field.allocate(points.view(-1, 3), surface.reshape(-1))
        optimizer = self._adam(self._init_groups(10.0))
        # A median depth moves only where the ray crosses half its light, so it cannot pull a
        # fresh map's surface (all near) out to the gauge: the plane is fitted on the mean.
        render_cfg = replace(self.render_cfg, median_depth=False)
        for _ in range(self.cfg.prior_iters):
            _, uv = random_pixels(1, 1024, self.camera, 0, self.generator, device)
            out = render_pixels(self.field, self.camera, uv, first.T_wc, render_cfg, self.generator)
            loss = (out.depth - self.cfg.gauge_depth).abs().mean()
            if self.render_cfg.normalize_depth and self.cfg.prior_stop:
                # A normalized depth is met by rays that barely stop: the plane must stop them.
                loss = loss + (1 - out.opacity).mean()
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            error = loss.item()
        return error

    def initialize(self, frames: list[FrameState]) -> MapRound:
        """Joint optimization of the map and the poses of `frames` (frames[0] fixed).

        First with the frames joining one at a time from their motion guess (`_grow`); when
        that ends with a warp residual above `init_max_warp`, again on a new map from the
        poses of tracked corners (`_from_corners`), and the map and poses that fit the images
        better are kept.
        """
        frames[0].keyframe = True
        first = self._grow(frames)
        limit = self.cfg.init_max_warp
        if limit <= 0:
            return first
        warp = self.check(frames)
        if warp <= limit:
            log.info("initialization's warp residual %.4f (at most %.4f: kept)", warp, limit)
            return first
        log.warning(
            "initialization's warp residual %.4f > %.4f: starting again from tracked corners",
            warp,
            limit,
        )
        kept = self.field, [f.T_wc for f in frames]
        images = [(f.rgb * 255).round().byte().cpu().numpy() for f in frames]
        seed = bootstrap(images, self.camera.K, self.cfg.gauge_depth)
        if seed is None:
            return first  # bootstrap logged why
        log.info(
            "corners: frames %s with %.1f degrees of parallax, %d points, %d-%d per frame",
            seed.pair,
            seed.parallax_deg,
            seed.points,
            min(seed.inliers),
            max(seed.inliers),
        )
        poses = torch.from_numpy(seed.poses).to(frames[0].T_wc)
        second = self._from_corners(frames, poses)
        again = self.check(frames)
        if again < warp:
            log.info("restart kept: warp residual %.4f against %.4f", again, warp)
            return second
        log.warning("restart dropped: warp residual %.4f against %.4f", again, warp)
        self.field = kept[0]
        for f, T in zip(frames, kept[1], strict=True):
            f.T_wc = T
        return first

    def _new_map(self, first: FrameState) -> None:
        """Start the map again, as the plane in front of `first`."""
        self.field = make_field(self.map_cfg, device=self.field.bound.device)
        self.fit_prior(first)

    def _gauge(self, result: WindowLoss, frame: torch.Tensor, _: torch.Tensor) -> torch.Tensor:
        """The scale gauge: a penalty holding frame 0's median rendered depth at
        `gauge_depth`."""
        depth0 = result.depth[frame == 0]
        if depth0.numel() == 0:
            return result.total.new_zeros(())
        return self.cfg.gauge_weight * (depth0.median() / self.cfg.gauge_depth - 1) ** 2

    def _optimize(
        self, frames: list[FrameState], window: list[FrameState], iterations: int, move: bool = True
    ) -> WindowStats:
        """Initialization iterations on `window` (frames[0] fixed; `move`: the others too)."""
        with self.field.learning():
            return optimize_window(
                self.field,
                window,
                [move and f is not frames[0] for f in window],
                self.camera,
                self._sampler(len(window)),
                iterations,
                self.cfg.pose_lr,
                self.loss_cfg,
                self.render_cfg,
                map_optimizer=self._adam(self._init_groups(self.cfg.init_lr_scale)),
                generator=self.generator,
                smooth=True,
                extra_loss=self._gauge if move else None,
                max_loss=float("inf"),
            )

    def _grow(self, frames: list[FrameState]) -> MapRound:
        """The frames join one at a time: the first `INIT_START` together, then each next one
        at the constant-velocity guess from the two before, followed by `init_grow_iters`
        iterations; finally `init_iters` iterations over all of them. Started all at once from
        identity, the far frames of the window lie tens of pixels from their true view, beyond
        the reach of an 11 px patch: on room0 (cpu preset) the 13 poses came out at 3.7 cm ATE
        over a 22 cm path, joined one at a time at 0.6 cm (docs/status.md).
        """
        prior_error = self.fit_prior(frames[0])
        log.info(
            "initial plane at depth %.2f fitted (error %.3f)", self.cfg.gauge_depth, prior_error
        )
        for n in range(min(INIT_START, len(frames)), len(frames) + 1):
            if n > INIT_START:
                frames[n - 1].T_wc = constant_velocity(frames[n - 2].T_wc, frames[n - 3].T_wc)
            stats = self._optimize(frames, frames[:n], self.cfg.init_grow_iters)
        if self.cfg.init_iters > 0:
            stats = self._optimize(frames, frames, self.cfg.init_iters)
        return MapRound(stats, tuple(f.index for f in frames))

    def _from_corners(self, frames: list[FrameState], poses: torch.Tensor) -> MapRound:
        """On a new map, from `poses` (from tracked corners): the map alone for as many
        iterations as `_grow` spends joining frames, then `init_iters` with the poses.

        The corners' scale (their median depth in frame 0) is not the gauge's (the median
        over all of frame 0's pixels; corners gather on near, textured things): a first
        short map at these poses measures frame 0's depth, the poses are scaled so that it
        becomes `gauge_depth`, and the map starts again at that scale, so that the scene
        stays within the map's range whatever the corners were.
        """
        for f, T in zip(frames, poses, strict=True):
            f.T_wc = T.clone()
        grow = self.cfg.init_grow_iters * max(1, len(frames) - INIT_START + 1)
        self._new_map(frames[0])
        self._optimize(frames, frames, SCALE_ITERS * self.cfg.init_grow_iters, move=False)
        scale = self.cfg.gauge_depth / self._median_depth(frames[0])
        for f in frames:
            f.T_wc = f.T_wc.clone()
            f.T_wc[:3, 3] *= scale
        self._new_map(frames[0])
        self._optimize(frames, frames, grow, move=False)
        stats = self._optimize(frames, frames, self.cfg.init_iters)
        return MapRound(stats, tuple(f.index for f in frames))

    def _checking(self) -> torch.Generator:
        """Randomness of the checks, apart from the mapper's: a check that passes leaves the
        run as it would have been without it."""
        return torch.Generator(self.field.bound.device).manual_seed(0)

    def _median_depth(self, frame: FrameState) -> float:
        """Median depth the map renders over `CHECK_PIXELS` x `pixels` random pixels."""
        g = self._checking()
        _, uv = random_pixels(1, CHECK_PIXELS * self.cfg.pixels, self.camera, 0, g, g.device)
        with torch.no_grad():
            out = render_pixels(self.field, self.camera, uv, frame.T_wc, self.render_cfg, g)
        return float(out.depth.median())

    def check(self, frames: list[FrameState]) -> float:
        """The warp residual of `frames` at their poses, on `CHECK_PIXELS` x `pixels`
        random pixels (one iteration's value is too noisy to decide on)."""
        images = torch.stack([f.rgb for f in frames])
        poses = torch.stack([f.T_wc for f in frames])
        g = self._checking()
        count = CHECK_PIXELS * self.cfg.pixels
        frame, uv = random_pixels(len(frames), count, self.camera, self.margin, g, g.device)
        with torch.no_grad():
            result = window_objective(
                self.field,
                images,
                poses,
                self.camera,
                frame,
                uv,
                self.loss_cfg,
                self.render_cfg,
                g,
            )
        return result.warp

    @_learning
    def map(
        self, recent: list[FrameState], keyframes: list[FrameState], iters: int | None = None
    ) -> MapRound:
        """One mapping round on the recent frames plus keyframes overlapping the newest, of
        `iters` iterations (default `iters` of the config)."""
        in_recent = {id(f) for f in recent}
        others = [kf for kf in keyframes if id(kf) not in in_recent]
        chosen = overlapping_keyframes(
            self.field,
            recent[-1],
            others,
            self.camera,
            self.cfg.window_keyframes,
            self.overlap,
            self.overlap_pixels,
            self.render_cfg,
            self.generator,
        )
        window = chosen + recent
        self._sweep_new(recent, keyframes)
        stats = optimize_window(
            self.field,
            window,
            [self._free(f) and (self.cfg.move_keyframes or id(f) in in_recent) for f in window],
            self.camera,
            self._sampler(len(window)),
            self.cfg.iters if iters is None else iters,
            self.cfg.pose_lr,
            self.loss_cfg,
            self.render_cfg,
            map_optimizer=self._round_optimizer(),
            generator=self.generator,
            smooth=True,
            max_loss=float("inf"),
            surface=True,
            extra_loss=self._stereo(window),
            pose_gate=self.cfg.pose_gate,
        )
        return MapRound(stats, tuple(f.index for f in window))

    def reclaim(self, frames: list[FrameState]) -> int:
        """The sparse map forgets the cells of its fine levels that no ray of `frames` (at
        `RECLAIM_WIDTH` px, every pixel) now stops near (`map.fine_band`, `map.reclaim_every`):
        it keeps what those rays would store now.

        Returns:
            Bytes freed.
        """
        reclaim = getattr(self.field, "reclaim", None)
        band = self.map_cfg.fine_band
        if reclaim is None or band <= 0 or not frames:
            return 0
        device = self.field.bound.device
        small = self.camera.resized(min(self.camera.width, RECLAIM_WIDTH))
        uv = small.pixels(device)
        # Steps shorter than the finest voxel: every cell of the band holds a point.
        steps = 2 * math.ceil(band / min(self.map_cfg.voxel_sizes)) + 1
        around = torch.linspace(-band, band, steps, device=device)
        points = []
        with torch.no_grad():
            for f in frames:
                origins, directions = camera_rays(small, uv, f.T_wc.detach().to(device))
                _, reach, stop = ray_depths(self.field, origins, directions, self.render_cfg)
                t = stop[:, None] + around
                kept = (stop[:, None] < self.render_cfg.far) & (t <= reach[:, None])  # as seen
                points.append((origins[:, None] + t[..., None] * directions[:, None])[kept])
        return reclaim(torch.cat(points), self._map_optimizer)

    def _free(self, f: FrameState) -> bool:
        """Whether an optimization may move the frame's pose: not frame 0's (`hold_first`)."""
        return f.index != 0 or not self.cfg.hold_first

    def _sweep_new(self, recent: list[FrameState], keyframes: list[FrameState]) -> None:
        """Plane sweeps of the recent keyframes that have none yet (`stereo_weight`)."""
        if self.cfg.stereo_weight <= 0:
            return
        held = {id(f): f for f in [*keyframes, *recent] if f.rgb is not None}
        for f in recent:
            if not f.keyframe or f.index in self.sweeps or f.rgb is None:
                continue
            sources = self._stereo_sources(f, list(held.values()))
            if not sources:
                log.debug("keyframe %d: no frame with parallax for a plane sweep", f.index)
                continue
            sweep = plane_sweep(
                f.rgb,
                f.T_wc,
                [(s.rgb, s.T_wc) for s in sources],
                self.camera,
                STEREO_NEAR * self.cfg.gauge_depth,
                self.render_cfg.far,
            )
            self.sweeps[f.index] = sweep
            log.debug(
                "keyframe %d: plane sweep against %s kept %.0f %% of its pixels",
                f.index,
                [s.index for s in sources],
                100 * sweep.kept,
            )

    def _stereo_sources(self, f: FrameState, held: list[FrameState]) -> list[FrameState]:
        """The frames `f`'s plane sweep compares: see `STEREO_BASELINE`."""
        low, high = (b * self.cfg.gauge_depth for b in STEREO_BASELINE)
        cos_max = math.cos(math.radians(STEREO_ANGLE))
        found = []
        for g in held:
            if g is f or abs(g.index - f.index) > STEREO_FRAMES:
                continue
            baseline = float((g.T_wc[:3, 3] - f.T_wc[:3, 3]).norm())
            cos = float(g.T_wc[:3, 2] @ f.T_wc[:3, 2])
            if low <= baseline <= high and cos >= cos_max:
                found.append((baseline, g))
        found.sort(key=lambda x: -x[0])
        return [g for _, g in found[: self.cfg.stereo_sources]]

    def _stereo(self, window: list[FrameState]):
        """The multi-view depth target of a window (see `MapperConfig.stereo_weight`), as an
        `extra_loss`; None when no frame of the window has a sweep."""
        sweeps = [self.sweeps.get(f.index) for f in window]
        known = [s for s in sweeps if s is not None]
        if self.cfg.stereo_weight <= 0 or not known:
            return None
        small = known[0].camera
        empty = torch.full_like(known[0].depth, math.nan)
        depths = torch.stack([empty if s is None else s.depth for s in sweeps])

        def term(result: WindowLoss, frame: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
            target = sample_depths(depths, small, frame, uv, self.camera)
            ok = torch.isfinite(target)
            if not ok.any():
                return result.total.new_zeros(())
            error = (result.depth[ok] - target[ok]).abs() / target[ok]
            return self.cfg.stereo_weight * error.mean()

        return term

    @_learning
    def post_optimize(
        self,
        keyframes: list[FrameState],
        iters: int | None = None,
        chunk: int = 20,
        anchors: list[FrameState] | None = None,
        poses: bool = False,
    ) -> WindowStats | None:
        """Refinement over all keyframes (paper appendix): `iters` iterations (default
        `post_iters`) in windows of `chunk` iterations, each of a keyframe and the keyframes
        overlapping it: `anchors` in turn, random keyframes without them. Map only, or with
        the keyframes' poses (`poses`; frame 0 stays with `hold_first`). Also refits the map
        where a loop closure moved keyframes."""
        stats = None
        remaining = self.cfg.post_iters if iters is None else iters
        turn = 0
        while remaining > 0 and len(keyframes) > 1:
            if anchors:
                anchor, turn = anchors[turn % len(anchors)], turn + 1
            else:
                pick = torch.randint(
                    len(keyframes), (1,), generator=self.generator, device=self.generator.device
                )
                anchor = keyframes[int(pick)]
            others = [kf for kf in keyframes if kf is not anchor]
            chosen = overlapping_keyframes(
                self.field,
                anchor,
                others,
                self.camera,
                20,
                self.overlap,
                self.overlap_pixels,
                self.render_cfg,
                self.generator,
            )
            window = [anchor, *chosen]
            if len(window) < 2:
                window = keyframes[-min(len(keyframes), 21) :]
            stats = optimize_window(
                self.field,
                window,
                [poses and self._free(f) for f in window],
                self.camera,
                self._sampler(len(window)),
                min(chunk, remaining),
                self.cfg.pose_lr if poses else 0.0,
                self.loss_cfg,
                self.render_cfg,
                map_optimizer=self._adam(self._groups(0.0)),
                generator=self.generator,
                smooth=True,
                max_loss=float("inf"),
                pose_gate=self.cfg.pose_gate,
            )
            remaining -= chunk
        return stats

    def extract_mesh(
        self,
        poses: torch.Tensor,
        max_depth: float,
        keyframes: list[FrameState] | tuple = (),
        progress=None,
    ):
        """The map's surface, culled to the estimated frustums (see `common/map/mesh.py`).

        The learned occupancy of an RGB-only map stays below 0.5 (docs/status.md: rays end in
        several samples of moderate occupancy), so the surface is the 0.5 level of the
        occupancy fused from depth maps: see `mesh_depths`.
        """
        return self.fuse_mesh(self.mesh_depths(poses, keyframes), poses, max_depth, progress)

    def mesh_depths(
        self, poses: torch.Tensor, keyframes: list[FrameState] | tuple = ()
    ) -> MeshDepths:
        """The depth maps fused into the mesh (`mesh_width` pixels wide).

        With `mesh_sweeps` and two keyframes or more (their images held): at up to
        `mesh_views` of `keyframes` (evenly spread), each one's plane sweep against its
        neighbouring keyframes at their current poses, kept where multi-view consistent;
        elsewhere the depth the map renders there, at `MESH_MAP_WEIGHT` and left out where
        the sweeps around show it off (`agreeing_depths`). The map was fitted to the poses of its
        rounds; the sweeps follow the poses as they are now. Otherwise the map's depth at up
        to `mesh_views` of `poses` (evenly spread)."""
        small = self.camera.resized(min(self.camera.width, self.cfg.mesh_width))
        held = [kf for kf in keyframes if kf.rgb is not None]
        if self.cfg.mesh_sweeps and len(held) >= 2:
            pick = torch.linspace(0, len(held) - 1, min(len(held), self.cfg.mesh_views))
            views = [held[int(i)] for i in pick.round().long().unique()]
            T_wc = torch.stack([f.T_wc.detach().cpu() for f in views])
            swept = [self._mesh_sweep(f, held, small) for f in views]
            sweeps = consistent_depths(torch.stack(swept), T_wc, small)
            # The map's depth where no sweep is, and on every other row and column of the
            # sweeps' pixels for `agreeing_depths` (a fifth of the extraction's time saved,
            # the mesh's figures within 0.3 cm and 0.2 %, docs/results.md).
            found = torch.isfinite(sweeps)
            sparse = torch.zeros_like(found)
            sparse[:, ::2, ::2] = True
            rendered = self.render_depths(T_wc, small, ~found | sparse)
            sigma = MESH_GATE_SIGMA * small.width
            kept = agreeing_depths(rendered, sweeps, MESH_GATE, sigma, MESH_GATE_SUPPORT)
            return MeshDepths(
                torch.where(found, sweeps, kept),
                torch.where(found, 1.0, MESH_MAP_WEIGHT),
                T_wc,
                small,
                rendered,
                torch.tensor([f.index for f in views]),
            )
        pick = torch.linspace(0, len(poses) - 1, min(len(poses), self.cfg.mesh_views))
        pick = pick.round().long()
        T_wc = poses[pick].detach().cpu()
        rendered = self.render_depths(T_wc, small)
        return MeshDepths(rendered, torch.ones_like(rendered), T_wc, small, rendered, pick)

    def render_depths(
        self, T_wc: torch.Tensor, small: Camera, only: torch.Tensor | None = None
    ) -> torch.Tensor:
        """`(V, h, w)` depth the map renders at `small`'s size from poses `T_wc`, only at the
        pixels `only` (`(V, h, w)` bool; NaN elsewhere) if given."""
        device = self.field.bound.device
        uv = small.pixels(device)
        out = torch.full((len(T_wc), small.height, small.width), math.nan)
        everywhere = torch.ones(len(uv), dtype=torch.bool)
        for i, T in enumerate(T_wc):
            wanted = everywhere if only is None else only[i].view(-1)
            at = uv[wanted.to(device)]
            depth, _ = render_chunked(
                self.field, small, at, T.to(device), self.render_cfg, with_color=False
            )
            out[i].view(-1)[wanted] = depth.cpu()
        return out

    def _mesh_sweep(self, f: FrameState, held: list[FrameState], small: Camera) -> torch.Tensor:
        """Keyframe `f`'s plane sweep at `small`'s size against its neighbours among `held`
        at their current poses (NaN where none is kept), computed again only when one of
        those poses has changed since the last mesh."""
        sources = self._stereo_sources(f, held)
        if not sources:
            return torch.full((small.height, small.width), math.nan)
        key = torch.stack([g.T_wc.detach().cpu() for g in [f, *sources]])
        cached = self._mesh_sweeps.get(f.index)
        if cached is not None and torch.equal(cached[0], key):  # False for other sources
            return cached[1]
        sweep = plane_sweep(
            f.rgb,
            f.T_wc.detach(),
            [(g.rgb, g.T_wc.detach()) for g in sources],
            self.camera,
            STEREO_NEAR * self.cfg.gauge_depth,
            self.render_cfg.far,
            planes=MESH_PLANES,
            width=small.width,
        )
        depth = sweep.depth.cpu()
        self._mesh_sweeps[f.index] = (key, depth)
        return depth

    def fuse_mesh(self, depths: MeshDepths, poses: torch.Tensor, max_depth: float, progress=None):
        """The 0.5 level of the occupancy fused from `depths`, culled to the frustums of
        `poses`, coloured by the map."""
        field = self.field
        occupancy = meshing.fused_occupancy(
            depths.depths.nan_to_num(0.0),
            depths.T_wc,
            depths.camera,
            truncation=3 * self.cfg.mesh_voxel,
            weights=depths.weights,
        )

        def color(p: torch.Tensor) -> torch.Tensor:
            return field(p.to(field.bound.device)).rgb.cpu()

        with torch.no_grad():
            return meshing.extract_mesh_in_budget(
                occupancy,
                color,
                field.bound.cpu(),
                self.cfg.mesh_voxel,
                poses.cpu(),
                self.camera,
                max_depth,
                progress=progress,
                unknown_nan=True,
                coarse=self.cfg.mesh_coarse,
            )

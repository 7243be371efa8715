"""Every setting of a run in one frozen config, and the named presets.

`SlamConfig` composes the small configs of each part (map, rendering, objective, tracker,
mapper); defaults live only in those dataclasses. The presets are named instances of it:
`paper` (the paper's numbers, for a GPU), `cpu` (what a 2-core CPU affords) and `tiny`
(tests). Tracker and mapper processes must run the same settings where they exchange maps;
`map_digest` fingerprints those.
"""

from __future__ import annotations

import hashlib
import json
import logging
from dataclasses import dataclass

import torch

from dimslam.common.map.field import MapConfig
from dimslam.common.map.render import RenderConfig
from dimslam.common.optim.objective import LossConfig
from dimslam.common.options import apply_overrides, option, section, to_dict
from dimslam.mapper.bundle import BundleConfig
from dimslam.mapper.loop import LoopConfig
from dimslam.mapper.mapper import MapperConfig
from dimslam.tracker.tracker import TrackerConfig

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SlamConfig:
    """Every setting of a run; `config.json` records it whole."""

    map: MapConfig = section(MapConfig, "the implicit map")
    render: RenderConfig = section(RenderConfig, "ray sampling")
    loss: LossConfig = section(LossConfig, "the window objective")
    tracker: TrackerConfig = section(TrackerConfig, "tracking")
    mapper: MapperConfig = section(MapperConfig, "mapping and initialization")
    loop: LoopConfig = section(LoopConfig, "loop closure")
    bundle: BundleConfig = section(BundleConfig, "feature bundle adjustment of the keyframes")
    width: int = option(0, "Resize input frames to this width, intrinsics following (0: keep).")
    seed: int = option(0, "Random seed of pixel and ray sampling.")

    @property
    def kept_images(self) -> int:
        """How many of the newest frames keep their images (besides keyframes): those a
        tracking window or the next mapping round may still use."""
        return max(self.tracker.local_frames, self.mapper.every)


# Measured on synthetic sequences with benchmarks/diagnose.py (docs/status.md): from identity
# poses, initialization needs a gentler pose step (3e-3) and ~600 iterations to converge at
# 160 px; tracking drifts less when only the newest frame moves, anchored by the others.
_GENTLE = {"tracker.pose_lr": "3e-3", "tracker.optimize_last": "1", "mapper.pose_lr": "3e-3"}

PRESETS: dict[str, SlamConfig] = {
    # The paper's numbers (design.md sections 3-5); meant for a GPU.
    "paper": SlamConfig(),
    # What a 2-core CPU affords: half-size frames, fewer pixels, samples and window frames.
    "cpu": apply_overrides(
        SlamConfig(
            render=RenderConfig(n_stratified=16, n_importance=8, importance_rounds=2),
            loss=LossConfig(smooth_blocks=64),
            # Tracking at the paper's budget (3000 px; 11 local frames + 10 keyframes): room0
            # 4.9 cm against 5.8 with 2000 px over 5 + 4 frames, 7-Scenes the same within its
            # spread, for 10 % more time (docs/results.md, "The cpu preset now").
            # The direct solve on two levels with the paper's visibility mask: means over 3
            # whole runs, room0 5.71 -> 3.59 cm, room3 19.28 -> 19.23, room5 11.08 -> 8.41,
            # 7-Scenes 4.27 -> 4.02 (docs/results.md, "The two flags over the whole table");
            # on four levels the mask lets room5's last turn slide and loses frames there.
            # Live, a frame under 30 % inliers where the map is young is lost to the end of
            # the stream; 20 %: room0 at 10 FPS 91-95 % of frames tracked, none lost
            # (docs/results.md, session 52).
            # A live map renders one keyframe at once, the others as frames use them: fewer
            # frames dropped while the tracker renders (docs/results.md, session 53).
            tracker=TrackerConfig(levels=2, min_views=4, live_min_inliers=0.2, live_map_renders=1),
            mapper=MapperConfig(
                pixels=600,
                iters=50,
                # grid_lr stays at the paper's 1e-3: 2e-3 took room0 from 6.1 to 3.2 cm (3 seeds)
                # but 7-Scenes from 3.3 to 6.4 cm (docs/results.md, "Grid learning rate").
                window_keyframes=6,
                # A global refinement round after every 2nd mapping round: whole runs, means of
                # seeds 0 and 1, room0 9.00 -> 3.76 cm, room3 22.80 -> 21.15, room5 11.04 ->
                # 7.43, 7-Scenes 4.06 -> 3.86 (docs/results.md, "Global refinement rounds
                # over whole runs").
                global_every=2,
                # Live frames: rounds of 5 iterations, no global refinement and no features,
                # about 0.9 s, keep the map up with a camera at 10 FPS (room0: rounds of 12 s
                # before, and the tracker lost beyond the map; docs/results.md, session 52).
                # Room0 at 10 FPS, medians of 3 runs: 3 / 5 / 10 / 15 iterations 12.7 / 9.0
                # / 13.2 / 11.7 cm (`benchmarks/live.py`, docs/results.md, session 53).
                live_iters=5,
                init_grow_iters=40,
                init_iters=200,
                init_lr_scale=3.0,
                prior_iters=60,
                # Fusing rendered depth costs (grid points x views): 5 cm keeps it near a minute.
                mesh_voxel=0.05,
                mesh_views=40,
                # Depth at 80 px meshes room0 as well as at 160 (15.7 cm accuracy, 11.5 % within
                # 5 cm) in a third of the time (docs/benchmarks.md, "Mesh extraction").
                mesh_width=80,
            ),
            # Every keyframe refined at the end by its ORB tracks, the tracked steps' turns
            # and directions as a prior: every frame's ATE, means over session 30's runs,
            # room0 2.41 -> 1.51, room3 17.93 -> 3.70, room5 11.07 -> 9.60, 7-Scenes 4.16 ->
            # 3.84 (docs/results.md, "The bundle adjustment over every frame" and session 34).
            # Corners followed by optical flow join it at every keyframe, each aligned again
            # there with its first keyframe (so that the flow's drift, 7-Scenes', does not
            # add up), and the tracked ratios of consecutive step lengths are held loosely
            # (0.2) where features link the keyframes too: Intel, 3 seeds, room0 2.23 ->
            # 2.08, room3 3.66 -> 2.13, room5 7.20 -> 5.61, 7-Scenes 5.13 -> 4.49 (flow
            # only about the steps ORB does not link before; docs/results.md, session 61).
            # Held at the consecutive keyframes that share the most points rather than the
            # first two, a broken first step is not kept: no sequence's mean worse on either
            # machine (Intel, 3 seeds: room0 2.34 -> 2.23, room3 3.68 -> 3.66, room5 9.53 ->
            # 9.38, 7-Scenes the same; AMD, seeds 1 / 2: 7-Scenes 11.42 / 8.13 ->
            # 9.65 / 7.44; docs/results.md, "The adjustment's gauge over the table").
            # A stretch where the features' essential matrices point against the tracked
            # motion (room5's last turn, where the tracker slides backwards) is started from
            # the motion before it, with no prior on its steps: room5 9.38 -> 7.20, the other
            # sequences have no such stretch (docs/results.md, session 59).
            # The prior's turns weighed again by their residuals against the reprojection
            # errors' (variance component estimation, 3 rounds): Intel, 3 seeds, room0 0.94
            # -> 0.93, room3 1.81 -> 1.79, room5 4.86 -> 4.55, 7-Scenes 4.47 -> 4.33
            # (docs/results.md, session 63).
            # Each step's direction weighed with its turn, one variance component (the
            # tracked step as one measurement): AMD, 3 seeds, room0 1.51 -> 0.86, room3
            # 2.12 -> 1.46, room5 3.97 -> 1.55, 7-Scenes 4.49 -> 4.39 (docs/results.md,
            # session 64).
            # The initialization's frames that the tracker's rule marks join it (frame 0 is
            # the initialization's only keyframe): AMD, 3 seeds, room0 0.86 -> 0.77, room3
            # 1.46 -> 1.03, room5 1.55 -> 1.48, 7-Scenes the same (no frame marked)
            # (docs/results.md, session 66).
            # A live run follows the flow through every frame, describes its keyframes at
            # its end and adjusts every frame with the tracked steps held only where no
            # feature links them: room0 at 10 FPS, seed 0, 3 runs through the service, the
            # final trajectory 0.61 / 0.72 / 0.70 cm (as published 9-19), the offline run
            # 0.67 (`benchmarks/live.py`; docs/results.md, session 67).
            bundle=BundleConfig(
                enabled=True,
                init_frames=True,
                live=True,
                flow=300,
                flow_realign=True,
                length_linked=0.2,
                gauge="linked",
                slides=True,
                weigh=3,
                weigh_steps=True,
            ),
            width=320,
        ),
        _GENTLE,
    ),
    # Tests: seconds on a tiny synthetic sequence.
    "tiny": apply_overrides(
        SlamConfig(
            map=MapConfig(voxel_sizes=(0.64, 0.32, 0.16), bound=(-4.0, -4.0, -4.0, 4.0, 4.0, 4.0)),
            render=RenderConfig(n_stratified=12, n_importance=6, importance_rounds=2, far=6.0),
            loss=LossConfig(patch_sizes=(1, 5), min_views=2, smooth_blocks=16),
            tracker=TrackerConfig(pixels=150, iters=10, local_frames=4, keyframes=2),
            mapper=MapperConfig(
                pixels=256,
                iters=8,
                init_frames=8,
                init_grow_iters=20,
                init_iters=150,
                init_lr_scale=3.0,
                prior_iters=40,
                window_keyframes=3,
                mesh_voxel=0.1,
            ),
            width=80,
        ),
        _GENTLE,
    ),
}


def device_for(name: str) -> torch.device:
    """`cpu` or `cuda:N`; without CUDA, say so once and use the CPU."""
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        log.warning("CUDA is not available: running on the CPU")
        return torch.device("cpu")
    return device


def map_digest(cfg: SlamConfig) -> str:
    """Fingerprint of the settings a tracker and a mapper must share to exchange maps."""
    shared = {"map": to_dict(cfg.map), "render": to_dict(cfg.render), "width": cfg.width}
    return hashlib.sha256(json.dumps(shared, sort_keys=True).encode()).hexdigest()[:16]

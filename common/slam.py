"""The SLAM system in one process: the pipeline's two halves driven in turn.

This is the paper's "one thread" variant and `dimslam run --single-process`. The tracking
half (`tracker/frontend.py`) and the mapping half (`mapper/backend.py`) are the ones the
service processes run; here they share their frames (the same objects), so the mapper's
refinements reach the tracker at once. Frames are fed with `Slam.add`; `Slam.finish` ends the
sequence. `run_dataset` wraps it for a dataset and writes the outputs a user reads.
"""

from __future__ import annotations

import json
import logging
import math
import time
from pathlib import Path

import torch

from dimslam.common.config import SlamConfig
from dimslam.common.errors import DimslamError
from dimslam.common.eval.report import RunSummary, report_run
from dimslam.common.geometry.camera import Camera
from dimslam.common.io.datasets import ReaderOptions, open_dataset
from dimslam.common.io.datasets.base import Frame
from dimslam.common.io.trajectory import Trajectory, write_tum
from dimslam.common.optim.window import FrameState, image_tensor
from dimslam.common.options import to_dict
from dimslam.common.progress import Progress
from dimslam.mapper.backend import BackEnd
from dimslam.mapper.mapper import MapRound
from dimslam.tracker.frontend import FrontEnd

log = logging.getLogger(__name__)


class Slam:
    """Tracking and mapping over a stream of frames, in turn."""

    def __init__(self, cfg: SlamConfig, camera: Camera, device: torch.device) -> None:
        self.cfg = cfg
        self.camera = camera
        self.device = device
        # Each half draws from a generator of its own, seeded as in its service process, so
        # that a lockstep run through the service (`dimslam run`) computes this one.
        self.generator = torch.Generator(device).manual_seed(cfg.seed)
        torch.manual_seed(cfg.seed)  # the grids' initialization
        self.back = BackEnd(cfg, camera, device, self.generator)
        self.front = FrontEnd(cfg, camera, torch.Generator(device).manual_seed(cfg.seed))
        self.last_loss = math.nan
        self.fed = 0

    @property
    def initialized(self) -> bool:
        return self.back.initialized

    @property
    def frames(self) -> list[FrameState]:
        """Every frame so far (the tracker's list; the mapper holds the same objects)."""
        return self.front.frames

    @property
    def keyframes(self) -> list[FrameState]:
        return self.front.keyframes

    def add(self, frame: Frame) -> list[FrameState]:
        """Process one frame; returns the frames whose poses became known (for publishing):
        none while initializing or when the frame is lost (`lost_frames`)."""
        rgb = image_tensor(frame.rgb, self.device)
        if rgb.shape[:2] != (self.camera.height, self.camera.width):
            raise DimslamError(f"frame {frame.index}: size {rgb.shape[1]}x{rgb.shape[0]} != camera")
        index, self.fed = self.fed, self.fed + 1  # position in the stream, after the stride
        if not self.initialized:
            if not self.front.collect(index, frame.timestamp, rgb):
                return []
            self.last_loss = self._map_batch().stats.loss
            return list(self.frames)
        state = self.front.track(self.back.field, index, frame.timestamp, rgb)
        if self.front.batch_due():  # a complete batch, or what was tracked up to a loss
            self._map_batch()
        if state is None:
            return []
        self.last_loss = self.front.last_result.stats.loss
        return [state]

    def _map_batch(self) -> MapRound:
        """Hand the frames tracked since the last round to the mapper and map them."""
        self.back.add(self.front.take_batch())
        result = self.back.step()
        self.front.map_changed(self.back.field, self.back.rounds)
        return result

    @property
    def lost_frames(self) -> list[tuple[int, float]]:
        """`(index, timestamp)` of every frame the tracker could not place."""
        return self.front.lost

    def finish(self) -> None:
        """End of the sequence: initialize a short one, map the last frames, post-optimize."""
        if not self.initialized:
            if not self.front.collect_rest():
                raise DimslamError(
                    f"sequence too short: {len(self.frames)} frames, need at least 3"
                )
            log.info(
                "sequence shorter than %d frames: initializing on all %d",
                self.cfg.mapper.init_frames,
                len(self.frames),
            )
        if self.front.pending:
            self._map_batch()
        self.back.finish()

    def trajectory(self) -> Trajectory:
        """Final poses of every frame so far (none before initialization)."""
        return self.back.trajectory()

    def keyframe_trajectory(self) -> Trajectory:
        """Final poses of the keyframes."""
        return self.back.trajectory(keyframes_only=True)


def run_dataset(
    source: str,
    out_dir: Path,
    cfg: SlamConfig,
    device: torch.device,
    max_frames: int | None = None,
    layout: str | None = None,
    mesh: bool = True,
    stride: int = 1,
) -> RunSummary:
    """Run SLAM on a dataset and write trajectory, keyframes, loops closed, mesh, config, log
    and metrics.

    `stride`: every stride-th frame of the dataset (stride times the motion per frame);
    `max_frames` counts the frames used.

    Raises:
        DimslamError: bad input. Lost frames do not raise: they have no pose in the outputs
            and are counted in `RunSummary.frames_lost` and `metrics.json`.
    """
    out_dir.mkdir(parents=True, exist_ok=True)
    handler = logging.FileHandler(out_dir / "log.txt", mode="w")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname).1s %(name)s: %(message)s"))
    logging.getLogger().addHandler(handler)
    try:
        end = None if max_frames is None else max_frames * stride
        options = ReaderOptions(end=end, stride=stride, width=cfg.width or None)
        reader = open_dataset(source, layout=layout, options=options)
        (out_dir / "config.json").write_text(
            json.dumps(
                {"source": str(source), "stride": stride, "device": str(device), **to_dict(cfg)},
                indent=2,
            )
            + "\n"
        )
        camera = reader.camera
        log.info(
            "%s: %s layout, %d frames, %dx%d",
            source,
            reader.layout,
            len(reader),
            camera.width,
            camera.height,
        )
        slam = Slam(cfg, camera, device)
        bar = Progress(len(reader), "slam")
        started = time.perf_counter()
        for n, frame in enumerate(reader, 1):
            slam.add(frame)
            bar.update(n, loss=slam.last_loss, kf=len(slam.keyframes), lost=len(slam.lost_frames))
        slam.finish()
        seconds = bar.close(kf=len(slam.keyframes))
        traj = slam.trajectory()
        write_tum(out_dir / "trajectory.txt", traj, header=f"dimslam estimate of {source}")
        write_tum(out_dir / "keyframes.txt", slam.keyframe_trajectory(), header="keyframes")
        slam.back.write_loops(out_dir / "loops.txt")
        mesh_path = None
        if mesh and slam.initialized:
            mesh_path = slam.back.write_mesh(out_dir)
        lost = len(slam.lost_frames)
        if lost:
            log.warning("%d frames lost (no pose): %s", lost, [i for i, _ in slam.lost_frames])
        extra = {
            "frames_lost": lost,
            "map_mb": slam.back.field.memory_bytes() / 2**20,
            "loops_closed": len(slam.back.closed),
        }
        metrics = report_run(source, out_dir, layout, mesh_path, seconds, len(traj), extra)
        return RunSummary(
            len(slam.frames) + lost,
            len(slam.keyframes),
            time.perf_counter() - started,
            lost,
            metrics,
        )
    finally:
        logging.getLogger().removeHandler(handler)
        handler.close()

"""The mapping process's loop: batches in, map snapshots and refined poses out, queries answered.

The steps are the single-process ones (`Mapper.initialize`, `Mapper.map`,
`Mapper.post_optimize`, `Mapper.extract_mesh`); this module adds the exchange:

- Batch 0 holds the first frames: the mapper initializes on them and publishes snapshot 1.
- Every later batch brings the frames since the previous one, with their tracked poses and
  keyframe flags. All batches pending when a round starts are taken together (the
  backpressure policy of a mapper that falls behind); the round runs on the newest `every`
  frames plus overlapping keyframes, exactly as in one process, so the frames in between keep
  their tracked poses. Offline runs avoid this with `dimslam-tracker --map-lag`.
- After each round: a versioned snapshot (map tensors, refined poses of every keyframe and of
  the round's frames) on the map topic, and the refined keyframe poses on the keyframes topic.
- A tracker whose mapper was restarted sends its own snapshot on the mapping topic, then its
  newest keyframes: a mapper without a map (only) takes them as its starting point.
- Queries: `query/map` (the newest snapshot), `query/keyframes` (the newest keyframes with
  their images, for a tracker that takes over a running map), `query/trajectory` (TUM text of
  the final poses: keyframes as refined, every other frame re-anchored to the keyframe before
  it), `query/mesh` (PLY bytes, extracted between rounds).
"""

from __future__ import annotations

import logging
import queue
import time
from pathlib import Path

import numpy as np
import torch
import zenoh

from dimslam.common import pose
from dimslam.common.camera import Camera
from dimslam.common.mesh import EmptyMeshError
from dimslam.common.messages import (
    MAX_BATCH_FRAMES,
    EndOfStream,
    MappingBatch,
    MappingFrame,
    MapSnapshot,
    MessageError,
    PoseMessage,
    message_type,
)
from dimslam.common.slam import SlamConfig, map_digest, release_images
from dimslam.common.trajectory import Trajectory, format_tum, write_tum
from dimslam.common.transport import BATCH_QUEUE, Inbox, Keys, Presence, Rejects, Stop, publisher
from dimslam.common.window import FrameState
from dimslam.mapper.mapper import Mapper

log = logging.getLogger(__name__)

WAIT_S = 0.5
STOP_GRACE_S = 2.0
"""At a stop, how long the mapper waits for the tracker's last batch and end of stream."""


class MapperService:
    """One mapping process on one zenoh session."""

    def __init__(
        self,
        cfg: SlamConfig,
        device: torch.device,
        session: zenoh.Session,
        keys: Keys,
        stop: Stop,
        exit_at_end: bool = False,
    ) -> None:
        self.cfg = cfg
        self.exit_at_end = exit_at_end
        self.device = device
        self.stop = stop
        self.digest = map_digest(cfg)
        self.generator = torch.Generator(device).manual_seed(cfg.seed)
        torch.manual_seed(cfg.seed)  # the grids' initialization, as in one process
        self.mapper: Mapper | None = None
        self.camera: Camera | None = None
        self.frames: list[FrameState] = []
        # Non-keyframe seq -> (anchor keyframe, pose relative to it), for the final trajectory.
        self.anchors: dict[int, tuple[FrameState, torch.Tensor]] = {}
        self.version = 0
        self.rounds = 0
        self.ended = False
        self.snapshot_bytes: bytes | None = None
        self.seed: MapSnapshot | None = None
        self.rejects = Rejects()
        self.round_seconds: list[float] = []
        self.batches_in = Inbox(BATCH_QUEUE, "mapping batches")
        self.mesh_queries: queue.SimpleQueue[zenoh.Query] = queue.SimpleQueue()
        stop.watch(self.batches_in)
        self.map_pub = publisher(session, keys.map, lossless=True)
        self.keyframe_pub = publisher(session, keys.keyframes, lossless=True, urgent=True)
        # Keep references to everything declared (zenoh.md trap 4).
        self.declared = [
            session.declare_subscriber(keys.mapping, self.batches_in.callback),
            session.declare_queryable(keys.query("map"), self._answer_map),
            session.declare_queryable(keys.query("trajectory"), self._answer_trajectory),
            session.declare_queryable(keys.query("keyframes"), self._answer_keyframes),
            session.declare_queryable(keys.query("mesh"), self.mesh_queries.put),
        ]
        self.presence = Presence(session, keys, "mapper", self._peer_changed)

    def _peer_changed(self, role: str, alive: bool) -> None:
        if role == "tracker" and not alive:
            log.warning("the tracker is gone: the map is kept and queries are still answered")

    # -- queries (zenoh's thread: cheap answers only; the mesh waits for the main loop) ------

    def _answer_map(self, query: zenoh.Query) -> None:
        with query:  # dropping the query ends it for the asker (zenoh.md trap 3)
            if self.snapshot_bytes is None:
                query.reply_err(b"no map yet")
            else:
                query.reply(query.key_expr, self.snapshot_bytes)

    def _answer_keyframes(self, query: zenoh.Query) -> None:
        with query:
            keyframes = [f for f in self.keyframes if f.rgb is not None][-MAX_BATCH_FRAMES:]
            if self.camera is None or not keyframes:
                query.reply_err(b"no keyframes yet")
                return
            items = tuple(
                MappingFrame(
                    f.index,
                    f.timestamp,
                    (f.rgb * 255.0).round().byte().cpu().numpy(),
                    f.T_wc.detach().cpu().double().numpy(),
                    True,
                )
                for f in keyframes
            )
            query.reply(query.key_expr, MappingBatch(self.rounds, items, self.camera).to_bytes())

    def _answer_trajectory(self, query: zenoh.Query) -> None:
        with query:
            text = format_tum(self.trajectory(), header="dimslam final poses")
            query.reply(query.key_expr, text.encode())

    def _answer_meshes(self) -> None:
        while True:
            try:
                query = self.mesh_queries.get_nowait()
            except queue.Empty:
                return
            with query:
                try:
                    query.reply(query.key_expr, self.mesh_ply())
                except EmptyMeshError as e:
                    query.reply_err(str(e).encode())

    # -- main loop --------------------------------------------------------------------------

    def run(self) -> int:
        """Map until a stop signal (or the end of the stream with `exit_at_end`)."""
        while not self.stop:
            self._answer_meshes()
            payload = self.batches_in.get(WAIT_S)
            if payload is None:
                continue
            batches = self._parse([payload, *self.batches_in.drain()])
            if batches and self._receive(batches):
                self._step(batches)
            if self.ended:
                self._finish()
                if self.exit_at_end:
                    break
                self.ended = False
        if self.stop:
            self._keep_pending()
        self._answer_meshes()
        log.info(
            "%d rounds (median %.1f s), map version %d, %d keyframes, %d rejected messages",
            self.rounds,
            float(np.median(self.round_seconds)) if self.round_seconds else 0.0,
            self.version,
            len(self.keyframes),
            self.rejects.count,
        )
        return 0

    @property
    def keyframes(self) -> list[FrameState]:
        return [f for f in self.frames if f.keyframe]

    def _parse(self, payloads: list[bytes]) -> list[MappingBatch]:
        """The mapping batches among `payloads`; an end of stream or a seed map is noted."""
        batches = []
        for p in payloads:
            try:
                kind = message_type(p)
                if kind == EndOfStream.TYPE:
                    self.ended = True
                elif kind == MapSnapshot.TYPE:
                    self._seed(MapSnapshot.from_bytes(p))
                else:
                    batches.append(MappingBatch.from_bytes(p))
            except MessageError as e:
                self.rejects("mapping", e)
        return batches

    def _keep_pending(self) -> None:
        """At a stop: the frames still in flight (a tracker stopped at the same time flushes its
        last batch) join the trajectory at their tracked poses, without a mapping round. Waits
        for the tracker's end of stream at most `STOP_GRACE_S`."""
        deadline = time.monotonic() + STOP_GRACE_S
        kept = 0
        while not self.ended and (left := deadline - time.monotonic()) > 0:
            payload = self.batches_in.get(min(left, WAIT_S))
            if payload is None:
                continue
            batches = self._parse([payload, *self.batches_in.drain()])
            batches = [b for b in batches if b.round > 0]  # never a new stream at a stop
            if batches and self.version > 0 and self._receive(batches):
                kept += sum(len(b.frames) for b in batches)
        if kept:
            log.info("stopped: %d unmapped frames kept at their tracked poses", kept)

    def _receive(self, batches: list[MappingBatch]) -> bool:
        """Add the batches' frames; True if there is a map (or a first batch) to run a round on."""
        for batch in batches:
            if batch.round == 0:
                self._reset(batch.camera)
            elif self.mapper is None and self.seed is not None:
                self._reset(batch.camera)
                self._take_seed()
            elif self.mapper is None:
                self.rejects("mapping", MessageError(f"batch {batch.round} before initialization"))
                continue
            elif batch.camera != self.camera:
                self.rejects("mapping", MessageError(f"batch {batch.round}: another camera"))
                continue
            for f in batch.frames:
                rgb = torch.from_numpy(f.rgb).to(self.device).float() / 255.0
                T = torch.from_numpy(f.T_wc).float().to(self.device)
                self.frames.append(FrameState(f.seq, f.timestamp, rgb, T, f.keyframe))
        return self.mapper is not None and bool(self.frames)

    def _step(self, batches: list[MappingBatch]) -> None:
        """One round on the frames just received: initialization first, then mapping."""
        assert self.mapper is not None
        started = time.perf_counter()
        if self.version == 0:
            result = self.mapper.initialize(self.frames)
            log.info("initialized on %d frames (loss %.4f)", len(self.frames), result.stats.loss)
            window = self.frames
        else:
            recent = self.frames[-self.cfg.mapper.every :]
            self.mapper.map(recent, self.keyframes)
            window = recent
        self.rounds += 1
        self.round_seconds.append(time.perf_counter() - started)
        self._anchor(window)
        release_images(self.frames, self.cfg)
        self._publish(batches[-1].round, window)

    def _seed(self, snap: MapSnapshot) -> None:
        """A tracker's map, sent because this mapper had none: kept for its next batch."""
        if snap.config != self.digest:
            self.rejects("mapping", MessageError("a seed map with other settings"))
        elif self.mapper is None:
            self.seed = snap
        else:
            log.info("a tracker offered map version %d; this mapper keeps its own", snap.version)

    def _take_seed(self) -> None:
        assert self.mapper is not None and self.seed is not None
        state = {k: torch.from_numpy(v) for k, v in self.seed.state.items()}
        self.mapper.field.load_state_dict(state)
        self.version = self.seed.version
        log.info("continuing the tracker's map version %d", self.version)
        self.seed = None

    def _reset(self, camera: Camera) -> None:
        if self.mapper is not None:
            log.info("a new stream starts: the previous map is dropped")
        self.camera = camera
        self.mapper = Mapper(
            self.cfg.mapper,
            self.cfg.map,
            self.cfg.loss,
            self.cfg.render,
            self.cfg.tracker.overlap,
            self.cfg.tracker.overlap_pixels,
            camera,
            self.device,
            self.generator,
        )
        self.frames = []
        self.anchors = {}
        self.version = 0

    def _anchor(self, frames: list[FrameState]) -> None:
        """Record each non-keyframe's pose relative to the keyframe before it."""
        keyframes = self.keyframes
        for f in frames:
            if f.keyframe:
                self.anchors.pop(f.index, None)
                continue
            before = [kf for kf in keyframes if kf.index <= f.index]
            if before:
                kf = before[-1]
                self.anchors[f.index] = (kf, pose.compose(pose.invert(kf.T_wc), f.T_wc))

    def _publish(self, round_: int, window: list[FrameState]) -> None:
        assert self.mapper is not None
        self.version += 1
        refined = {f.index: f for f in [*self.keyframes, *window]}
        snap = MapSnapshot(
            self.version,
            round_,
            self.digest,
            {k: v.detach().cpu().numpy() for k, v in self.mapper.field.state_dict().items()},
            {s: f.T_wc.detach().cpu().double().numpy() for s, f in refined.items()},
            tuple(kf.index for kf in self.keyframes),
        )
        self.snapshot_bytes = snap.to_bytes()
        self.map_pub.put(self.snapshot_bytes)
        for kf in self.keyframes:
            T = kf.T_wc.detach().cpu().double().numpy()
            msg = PoseMessage(kf.index, kf.timestamp, T, True, self.version)
            self.keyframe_pub.put(msg.to_bytes())

    def _finish(self) -> None:
        if self.mapper is None:
            log.warning("end of stream before any map was built")
            return
        if self.cfg.mapper.post_iters > 0:
            self.mapper.post_optimize(self.keyframes)
            self._publish(self.rounds, [])
        log.info("end of stream: map version %d, %d frames", self.version, len(self.frames))

    # -- outputs ----------------------------------------------------------------------------

    def trajectory(self) -> Trajectory:
        """Final poses: keyframes as refined, other frames re-anchored to their keyframe."""
        poses, stamps = [], []
        for f in self.frames if self.version > 0 else []:
            T = f.T_wc
            if not f.keyframe and f.index in self.anchors:
                kf, rel = self.anchors[f.index]
                T = pose.normalize(pose.compose(kf.T_wc, rel))
            poses.append(T.detach().cpu().double().numpy())
            stamps.append(f.timestamp)
        if not poses:
            return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
        return Trajectory(np.array(stamps), np.stack(poses))

    def mesh_ply(self) -> bytes:
        """The current mesh as PLY bytes; raises EmptyMeshError without a surface."""
        if self.mapper is None or self.version == 0:
            raise EmptyMeshError("no map yet")
        poses = torch.stack([f.T_wc for f in self.frames])
        mesh = self.mapper.extract_mesh(poses, self.cfg.render.far)
        return mesh.export(file_type="ply", encoding="binary")

    def write(self, out: Path, mesh: bool) -> None:
        """Flush the outputs: final trajectory, keyframes, map checkpoint and the mesh if asked."""
        out.mkdir(parents=True, exist_ok=True)
        traj = self.trajectory()
        write_tum(out / "trajectory.txt", traj, header="dimslam final poses")
        kf = [i for i, f in enumerate(self.frames) if f.keyframe]
        write_tum(
            out / "keyframes.txt",
            Trajectory(traj.timestamps[kf], traj.poses[kf]) if len(traj) else traj,
            header="keyframes",
        )
        if self.snapshot_bytes is not None:
            (out / "map.msgpack").write_bytes(self.snapshot_bytes)
        if mesh and self.mapper is not None and self.version > 0:
            try:
                (out / "mesh.ply").write_bytes(self.mesh_ply())
            except EmptyMeshError as e:
                log.warning("no mesh written: %s", e)
        log.info("outputs written to %s", out)

    def close(self) -> None:
        self.presence.close()

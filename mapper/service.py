"""The mapping process's loop: batches in, map snapshots and refined poses out, queries answered.

The steps are the single-process ones (`mapper/backend.py`: initialize, map rounds, re-anchor
the final trajectory, post-optimize, mesh); this module adds the exchange:

- Batch 0 holds the first frames: the mapper initializes on them and publishes snapshot 1.
- Every later batch brings the frames since the previous one, with their tracked poses and
  keyframe flags. Each batch gets its own round while at most `MAX_BACKLOG` wait; a mapper
  with more waiting has fallen behind (a live stream) and takes them all into one round (its
  backpressure policy): the round runs on the newest `every` frames plus overlapping
  keyframes, exactly as in one process, so the frames in between keep their tracked poses.
- A batch of live frames (a live camera) gets a short round: `mapper.live_iters` iterations,
  no global refinement and no features described, so that the map keeps up with the camera.
  Offline runs never fall that far behind (`dimslam-tracker --map-lag`).
- After each round: a versioned snapshot (map tensors, the poses of every frame received) on
  the map topic, and the refined keyframe poses on the keyframes topic.
- With `mapper.global_every` set, a mapper that waits for a batch spends the wait on short
  chunks of global refinement (keyframes anywhere on the path and the map), each published
  as a snapshot, up to `mapper.idle_chunks` per batch; then it waits without work (a stream
  that paused or ended costs no CPU for long).
- A tracker whose mapper was restarted sends its own snapshot on the mapping topic, then its
  newest keyframes: a mapper without a map (only) takes them as its starting point.
- Queries: `query/map` (the newest snapshot), `query/keyframes` (the newest keyframes with
  their images, for a tracker that takes over a running map), `query/trajectory` (TUM text of
  the final poses: keyframes as refined, every other frame re-anchored to the keyframe before
  it), `query/mesh` (PLY bytes, extracted between rounds).
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

import numpy as np
import torch
import zenoh

from dimslam.common.config import SlamConfig, map_digest
from dimslam.common.errors import DimslamError
from dimslam.common.geometry.camera import Camera
from dimslam.common.io.trajectory import Trajectory, format_tum, write_tum
from dimslam.common.map.mesh import EmptyMeshError
from dimslam.common.net.exchange import (
    from_batch,
    load_map,
    pose_array,
    pose_tensor,
    to_batch,
    to_snapshot,
)
from dimslam.common.net.messages import (
    MAX_BATCH_FRAMES,
    EndOfStream,
    MapperCheckpoint,
    MappingBatch,
    MapSnapshot,
    MessageError,
    PoseMessage,
    decode_or_end,
    message_type,
)
from dimslam.common.net.transport import (
    BATCH_QUEUE,
    MESH_QUERIES,
    Inbox,
    Keys,
    Presence,
    Queries,
    Rejects,
    Stop,
    publisher,
)
from dimslam.common.optim.window import FrameState
from dimslam.mapper.backend import BackEnd

log = logging.getLogger(__name__)

WAIT_S = 0.5
MAX_BACKLOG = 2
"""Batches that may wait and still be mapped one round each. A tracker at `--map-lag 1` can
have two waiting at the end of a round (it tracks fast, the mapper reads its inbox a moment
later); more means the mapper has fallen behind a live stream."""
CHECKPOINT_FILE = "checkpoint.msgpack"
STOP_GRACE_S = 10.0
"""At a stop, how long the mapper waits for the tracker's last batch and end of stream (it
stops waiting as soon as the end arrives; on a loaded 2-core machine the tracker's flush took
more than 2 s)."""


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
        checkpoint: Path | None = None,
        checkpoint_every: int = 0,
        resume: Path | None = None,
    ) -> None:
        self.cfg = cfg
        self.exit_at_end = exit_at_end
        self.checkpoint_dir = checkpoint
        self.checkpoint_every = checkpoint_every
        self.device = device
        self.stop = stop
        self.digest = map_digest(cfg)
        self.generator = torch.Generator(device).manual_seed(cfg.seed)
        torch.manual_seed(cfg.seed)  # the grids' initialization, as in one process
        self.back: BackEnd | None = None  # once the first batch gives the camera
        self.camera: Camera | None = None
        self.version = 0
        self.ended = False
        self.snapshot_bytes: bytes | None = None
        self.last_round = 0  # the newest mapping batch mapped (the snapshots' `round`)
        self.seed: MapSnapshot | None = None
        self.rejects = Rejects()
        self.backlog: list[MappingBatch] = []  # received, not yet mapped
        self.idle_chunks = 0  # global refinement chunks run idle since the last round
        self.idle_total = 0
        # Frames of the stream admitted so far: a batch of none but these is a duplicate.
        self.received: set[int] = set()
        self.ended_ns = -1  # the send stamp of the last end of stream
        self.stream_open = False  # a batch came after the last end of stream (or none)
        self.batches_in = Inbox(BATCH_QUEUE, "mapping batches", self._admit)
        self.mesh_queries = Queries(MESH_QUERIES, "mesh queries")
        stop.watch(self.batches_in)
        self.map_pub = publisher(session, keys.map, lossless=True)
        self.keyframe_pub = publisher(session, keys.keyframes, lossless=True, urgent=True)
        # Keep references to everything declared (zenoh.md trap 4).
        self.declared = [
            session.declare_subscriber(keys.mapping, self.batches_in.callback),
            session.declare_queryable(keys.query("map"), self._answer_map),
            session.declare_queryable(keys.query("trajectory"), self._answer_trajectory),
            session.declare_queryable(keys.query("keyframes"), self._answer_keyframes),
            session.declare_queryable(keys.query("mesh"), self.mesh_queries.callback),
        ]
        if resume is not None:  # before the token: a tracker that sees us must find the map
            self.resume(resume)
        self.presence = Presence(session, keys, "mapper", self._peer_changed)

    @property
    def frames(self) -> list[FrameState]:
        return self.back.frames if self.back is not None else []

    @property
    def rounds(self) -> int:
        return self.back.rounds if self.back is not None else 0

    def _peer_changed(self, role: str, alive: bool) -> None:
        if role != "tracker" or alive:
            return
        if not self.stream_open and self.ended_ns >= 0:  # it ended its stream, then exited
            log.info("the tracker has left after its end of stream")
        else:
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
            batch = to_batch(keyframes, self.rounds, self.camera, keyframes=True)
            query.reply(query.key_expr, batch.to_bytes())

    def _answer_trajectory(self, query: zenoh.Query) -> None:
        with query:
            text = format_tum(self.trajectory(), header="dimslam final poses")
            query.reply(query.key_expr, text.encode())

    # -- main loop --------------------------------------------------------------------------

    def run(self) -> int:
        """Map until a stop signal (or the end of the stream with `exit_at_end`)."""
        while not self.stop:
            self.mesh_queries.answer_all(self.mesh_ply)
            if self.backlog:
                self.backlog += self._parse(self.batches_in.drain())
            else:
                item = self.batches_in.get(WAIT_S)
                if item is None:
                    self._idle()
                    continue
                self.backlog = self._parse([item, *self.batches_in.drain()])
            n = 1 if len(self.backlog) <= MAX_BACKLOG else len(self.backlog)
            take, self.backlog = self.backlog[:n], self.backlog[n:]
            if take and self._receive(take):
                self._step(take, live=any(b.live for b in take))
            if self.ended and not self.backlog:
                self._finish()
                if self.exit_at_end:
                    break
                self.ended = False
        if self.stop:
            self._keep_pending()
        self.mesh_queries.answer_all(self.mesh_ply)
        seconds = self.back.round_seconds if self.back is not None else []
        log.info(
            "%d rounds (%d short on live frames; median %.1f s; seconds a round: %s), "
            "%d idle refinement chunks, map version %d, %d keyframes, %d rejected messages",
            self.rounds,
            self.back.short_rounds if self.back is not None else 0,
            float(np.median(seconds)) if seconds else 0.0,
            self.back.phases() if self.back is not None else "none",
            self.idle_total,
            self.version,
            len(self.keyframes),
            self.rejects.count,
        )
        return 0

    @property
    def keyframes(self) -> list[FrameState]:
        return [f for f in self.frames if f.keyframe]

    def _admit(self, payload: bytes) -> MappingBatch | MapSnapshot | EndOfStream | None:
        """A mapping-topic message decoded on zenoh's thread; None (counted) if it is not one,
        or is a batch of frames all received before (sent again, or a replay): it would map
        them again, and a batch 0 would even drop the map. After an end of stream a new
        stream may number its frames from 0 again; a batch sent before that end (its stamp,
        on the tracker's clock as the end's) belongs to the old stream."""
        try:
            if message_type(payload) == MapSnapshot.TYPE:
                snap = MapSnapshot.from_bytes(payload)
                if snap.config != self.digest:
                    raise MessageError("a seed map with other settings")
                return snap
            msg = decode_or_end(payload, MappingBatch)
            if isinstance(msg, EndOfStream):
                self.received.clear()
                self.ended_ns = max(self.ended_ns, msg.stamp_ns)
                self.stream_open = False
                return msg
            if msg.stamp_ns <= self.ended_ns:
                raise MessageError(f"batch {msg.round}: sent before the end of its stream")
            seqs = {f.seq for f in msg.frames}
            if seqs <= self.received:
                raise MessageError(f"batch {msg.round}: every frame received before")
            self.received |= seqs
            self.stream_open = True
            return msg
        except MessageError as e:
            self.rejects("mapping", e)
            return None

    def _parse(self, items: list) -> list[MappingBatch]:
        """The mapping batches among `items` (admitted messages); an end of stream or a seed
        map is noted."""
        batches = []
        for item in items:
            if isinstance(item, EndOfStream):
                self.ended = True
            elif isinstance(item, MapSnapshot):
                self._seed(item)
            else:
                batches.append(item)
        return batches

    def _keep_pending(self) -> None:
        """At a stop: the frames still in flight (a tracker stopped at the same time flushes its
        last batch) join the trajectory at their tracked poses, without a mapping round. Waits
        for the tracker's end of stream at most `STOP_GRACE_S`."""
        deadline = time.monotonic() + STOP_GRACE_S
        kept = 0
        waiting, self.backlog = self.backlog, []
        while waiting or (not self.ended and (left := deadline - time.monotonic()) > 0):
            batches = waiting
            waiting = []
            if not batches:
                item = self.batches_in.get(min(left, WAIT_S))
                if item is None:
                    continue
                batches = self._parse([item, *self.batches_in.drain()])
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
            elif self.back is None and self.seed is not None:
                self._reset(batch.camera)
                self._take_seed()
            elif self.back is None:
                self.rejects("mapping", MessageError(f"batch {batch.round} before initialization"))
                continue
            elif batch.camera != self.camera:
                self.rejects("mapping", MessageError(f"batch {batch.round}: another camera"))
                continue
            assert self.back is not None
            self.back.add(from_batch(batch, self.device))
        return self.back is not None and bool(self.frames)

    def _step(self, batches: list[MappingBatch], live: bool = False) -> None:
        """One round on the frames just received: initialization first, then mapping (a
        short one on `live` frames)."""
        assert self.back is not None
        self.back.step(live)
        self.idle_chunks = 0
        self._publish(batches[-1].round)
        every = self.checkpoint_every
        if self.checkpoint_dir is not None and every > 0 and self.rounds % every == 0:
            self.write_checkpoint(self.checkpoint_dir)

    def _idle(self) -> None:
        """No batch waiting: a short chunk of global refinement, published as a snapshot
        (`mapper.global_every` > 0; at most `mapper.idle_chunks` after each batch)."""
        back = self.back
        if (
            back is None
            or not back.initialized
            or self.cfg.mapper.global_every <= 0
            or self.idle_chunks >= self.cfg.mapper.idle_chunks
            or len(back.keyframes) < 2
        ):
            return
        self.idle_chunks += 1
        self.idle_total += 1
        back.refine_global(max(1, self.cfg.mapper.global_iters // 4))
        self._publish(self.last_round)

    def _seed(self, snap: MapSnapshot) -> None:
        """A tracker's map, sent because this mapper had none: kept for its next batch."""
        if self.back is None:
            self.seed = snap
        else:
            log.info("a tracker offered map version %d; this mapper keeps its own", snap.version)

    def _take_seed(self) -> None:
        assert self.back is not None and self.seed is not None
        load_map(self.back.field, self.seed)
        self.back.initialized = True
        self.version = self.seed.version
        log.info("continuing the tracker's map version %d", self.version)
        self.seed = None

    def _reset(self, camera: Camera) -> None:
        if self.back is not None:
            log.info("a new stream starts: the previous map is dropped")
        self.camera = camera
        self.back = BackEnd(self.cfg, camera, self.device, self.generator)
        self.version = 0

    def _publish(self, round_: int) -> None:
        assert self.back is not None
        self.version += 1
        self.last_round = round_
        # Every frame's pose, not only the round's and the keyframes': global refinement and
        # loop closure move frames of earlier rounds, and the tracker's views of its recent
        # frames must see that as one process's shared frames do (16 doubles a frame).
        keyframes = self.keyframes
        snap = to_snapshot(
            self.version, round_, self.digest, self.back.field, self.frames, keyframes
        )
        self.snapshot_bytes = snap.to_bytes()
        self.map_pub.put(self.snapshot_bytes)
        for kf in keyframes:
            msg = PoseMessage(kf.index, kf.timestamp, pose_array(kf.T_wc), True, self.version)
            self.keyframe_pub.put(msg.to_bytes())

    def _finish(self) -> None:
        if self.back is None:
            log.warning("end of stream before any map was built")
            return
        if self.back.finish():
            self._publish(self.rounds)
        log.info("end of stream: map version %d, %d frames", self.version, len(self.frames))

    # -- checkpoints ------------------------------------------------------------------------

    def write_checkpoint(self, folder: Path) -> None:
        """Write the map, every frame's pose and the images still held to
        `folder/checkpoint.msgpack`, atomically: a crash mid-write leaves the previous one."""
        if self.back is None or not self.back.initialized or self.camera is None:
            return
        back = self.back
        snap = to_snapshot(
            self.version,
            self.last_round,
            self.digest,
            back.field,
            back.frames,
            back.keyframes,
            pose=back.final_pose,
        )
        held = [f for f in back.frames if f.rgb is not None]
        images = tuple(
            to_batch(held[i : i + MAX_BATCH_FRAMES], self.rounds, self.camera)
            for i in range(0, len(held), MAX_BATCH_FRAMES)
        )
        frames = tuple((f.index, f.timestamp) for f in back.frames)
        payload = MapperCheckpoint(snap, frames, images, self.rounds).to_bytes()
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / CHECKPOINT_FILE
        tmp = path.with_suffix(".tmp")
        with open(tmp, "wb") as f:
            f.write(payload)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        log.info(
            "checkpoint: map version %d, %d frames, %d rounds -> %s",
            self.version, len(frames), self.rounds, path,
        )  # fmt: skip

    def resume(self, folder: Path) -> None:
        """Start from `folder/checkpoint.msgpack` instead of from nothing.

        Raises:
            DimslamError: no readable checkpoint there, or one of other map settings.
        """
        path = folder / CHECKPOINT_FILE
        try:
            ckpt = MapperCheckpoint.from_bytes(path.read_bytes())
        except OSError as e:
            raise DimslamError(
                f"--resume {folder}: cannot read {path.name} ({e.strerror})"
            ) from None
        except MessageError as e:
            raise DimslamError(f"--resume {folder}: {path.name} is not a checkpoint: {e}") from None
        snap = ckpt.snapshot
        if snap.config != self.digest:
            raise DimslamError(
                f"--resume {folder}: the checkpoint's map has other settings; give the mapper "
                "the --preset and overrides it was written with"
            )
        if not ckpt.images:
            raise DimslamError(f"--resume {folder}: the checkpoint holds no keyframe images")
        self._reset(ckpt.images[0].camera)
        back = self.back
        assert back is not None
        load_map(back.field, snap)
        with_images = {f.index: f for b in ckpt.images for f in from_batch(b, self.device)}
        keyframes = set(snap.keyframes)
        for seq, timestamp in ckpt.frames:
            frame = with_images.get(seq) or FrameState(
                seq, timestamp, None, pose_tensor(snap.poses[seq], self.device)
            )
            frame.keyframe = seq in keyframes
            back.frames.append(frame)
        back.initialized = True
        back.rounds = ckpt.rounds
        back.reanchor()
        self.version = snap.version
        self.last_round = snap.round
        self.snapshot_bytes = snap.to_bytes()
        log.info(
            "resumed from %s: map version %d, %d frames (%d keyframes), %d rounds",
            path, self.version, len(back.frames), len(keyframes), back.rounds,
        )  # fmt: skip

    # -- outputs ----------------------------------------------------------------------------

    def trajectory(self, keyframes_only: bool = False) -> Trajectory:
        """Final poses (of every frame, or of the keyframes): keyframes as refined, other
        frames re-anchored to their keyframe."""
        if self.back is None:
            return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
        return self.back.trajectory(keyframes_only)

    def mesh_ply(self) -> bytes:
        """The current mesh as PLY bytes; raises EmptyMeshError without a surface."""
        if self.back is None:
            raise EmptyMeshError("no map yet")
        return self.back.extract_mesh().export(file_type="ply", encoding="binary")

    def write(self, out: Path, mesh: bool) -> None:
        """Flush the outputs: final trajectory, keyframes, loops closed, map checkpoint and the
        mesh if asked."""
        out.mkdir(parents=True, exist_ok=True)
        write_tum(out / "trajectory.txt", self.trajectory(), header="dimslam final poses")
        write_tum(out / "keyframes.txt", self.trajectory(keyframes_only=True), header="keyframes")
        if self.snapshot_bytes is not None:
            (out / "map.msgpack").write_bytes(self.snapshot_bytes)
        if self.back is not None:
            self.back.write_loops(out / "loops.txt")
        if mesh and self.back is not None and self.version > 0:
            self.back.write_mesh(out)
        log.info("outputs written to %s", out)

    def close(self) -> None:
        self.presence.close()

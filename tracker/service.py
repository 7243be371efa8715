"""The tracking process's loop: frames in, poses out, mapping batches to the mapper.

The steps are the single-process ones (`tracker/frontend.py`: collect, track, decide
keyframes, hand batches over); what this module adds is the exchange:

- Until the map exists, frames are collected; the first `init_frames` go to the mapper as
  batch 0, and the tracker waits for snapshot 1 (frames keep queueing meanwhile).
- Then every frame is tracked against the newest snapshot held, and its pose published at once.
  Every `every` frames, the frames since the last batch (images, poses, keyframe flags) go to
  the mapper. The tracker never waits for a mapping round.
- Snapshots are swapped in between frames. The refined poses they carry replace the tracker's
  estimates; frames tracked after the snapshot's newest frame move with it (the correction of
  that frame is applied to them), so the motion model does not see a jump.
- The mapper's liveliness token is watched: if it dies, the tracker says so once and keeps
  tracking on the last map. When a mapper appears while the tracker has a map, the tracker asks
  it for its map; a mapper without one (restarted) gets the tracker's: a snapshot and the newest
  keyframes with their images, on the mapping topic, before any held batch.
- A tracker that starts while a mapper holds a map continues that map (a late or restarted
  tracker): it fetches the snapshot and the newest keyframes by query, and numbers its frames
  after the map's so that frame numbers never collide.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch
import zenoh

from dimslam.common.config import SlamConfig, map_digest
from dimslam.common.geometry.camera import Camera
from dimslam.common.io.trajectory import Trajectory, write_tum
from dimslam.common.map.field import make_field
from dimslam.common.net.exchange import (
    from_batch,
    load_map,
    pose_array,
    pose_tensor,
    snapshot_poses,
    to_batch,
    to_snapshot,
)
from dimslam.common.net.messages import (
    MAX_BATCH_FRAMES,
    EndOfStream,
    FrameMessage,
    MappingBatch,
    MapSnapshot,
    MessageError,
    PoseMessage,
    decode_or_end,
    now_ns,
)
from dimslam.common.net.transport import (
    FRAME_QUEUE,
    Inbox,
    Keys,
    Presence,
    Rejects,
    Stop,
    pose_publisher,
    publisher,
)
from dimslam.common.optim.window import FrameState, image_tensor
from dimslam.common.progress import Progress
from dimslam.tracker.frontend import FrontEnd

log = logging.getLogger(__name__)

WAIT_S = 0.5
"""How long a loop waits on its inbox before checking the stop event again."""
MAPPER_GRACE_S = 30.0
"""Default `--mapper-grace`: how long a tracker with `--map-lag` waits for a mapper that left."""


@dataclass
class TrackerStats:
    """Counters a user reads at exit (and the benchmark).

    Attributes:
        received: frames that arrived (dropped ones included).
        frames: frames processed (collected for the initialization or tracked).
        tracked: frames given a pose by the solver.
        lost: frames the solver could not place (published as lost, no pose).
        skipped_live: live frames dropped because a newer one was already waiting.
        repeated: frames not newer than one taken before, ignored: sent again by the camera
            after a link cut (it sends those without a pose again), or out of order.
        snapshots: map snapshots swapped in.
        track_seconds: per tracked or lost frame, the tracking step's time.
        refresh_seconds: per snapshot, the time the solver took to refresh what it caches.
        latency_seconds: per tracked frame, from the camera's send stamp to the published pose.
        mapper_busy: per tracked frame, whether a mapping round was running.
    """

    received: int = 0
    frames: int = 0
    tracked: int = 0
    lost: int = 0
    skipped_live: int = 0
    repeated: int = 0
    snapshots: int = 0
    track_seconds: list[float] = field(default_factory=list)
    refresh_seconds: list[float] = field(default_factory=list)
    latency_seconds: list[float] = field(default_factory=list)
    mapper_busy: list[bool] = field(default_factory=list)

    def summary(self, dropped_in_queue: int = 0) -> dict:
        """Counts, tracking time per frame (median with the mapper busy and idle; p50 and
        p95 over all), latency p50 / p95, in milliseconds."""
        t = np.array(self.track_seconds)
        busy = np.array(self.mapper_busy, dtype=bool)
        out = {
            "frames_received": self.received,
            "frames": self.frames,
            "tracked": self.tracked,
            "frames_lost": self.lost,
            "frames_dropped": self.skipped_live + dropped_in_queue,
            "frames_repeated": self.repeated,
            "snapshots": self.snapshots,
        }
        for name, sel in (("busy", busy), ("idle", ~busy)):
            out[f"frames_mapper_{name}"] = int(sel.sum())
            out[f"median_track_ms_mapper_{name}"] = _ms(t[sel], 50)
        out["track_ms_p50"], out["track_ms_p95"] = _ms(t, 50), _ms(t, 95)
        out["refresh_ms_p50"] = _ms(np.array(self.refresh_seconds), 50)
        latency = np.array(self.latency_seconds)
        out["latency_ms_p50"], out["latency_ms_p95"] = _ms(latency, 50), _ms(latency, 95)
        return out


def _ms(seconds: np.ndarray, percentile: float) -> float | None:
    return float(np.percentile(seconds, percentile) * 1000) if len(seconds) else None


class TrackerService:
    """One tracking process on one zenoh session."""

    def __init__(
        self,
        cfg: SlamConfig,
        device: torch.device,
        session: zenoh.Session,
        keys: Keys,
        stop: Stop,
        map_lag: int | None = None,
        mapper_grace: float = MAPPER_GRACE_S,
    ) -> None:
        self.cfg = cfg
        self.device = device
        self.keys = keys
        self.stop = stop
        # Bounded staleness (offline runs): at most this many sent batches unmapped before the
        # next frame is tracked; None: never wait (live cameras).
        self.map_lag = map_lag
        # With map_lag, a mapper that left is waited for this long (it may come back with
        # --resume) before tracking goes on without it.
        self.mapper_grace = mapper_grace
        self.mapper_left: float | None = None  # monotonic time the mapper's token vanished
        self.digest = map_digest(cfg)
        self.generator = torch.Generator(device).manual_seed(cfg.seed)
        self.field = make_field(cfg.map, device=device).requires_grad_(False)
        self.camera: Camera | None = None
        self.source_camera: Camera | None = None
        self.front: FrontEnd | None = None  # once the first frame gives the camera
        self.online: dict[int, tuple[float, np.ndarray]] = {}
        self.outbox: list[bytes] = []
        # Batches sent that no snapshot covers yet, by round: a resumed mapper gets them again.
        self.uncovered: dict[int, bytes] = {}
        self.map_version = 0
        self.map_round = -1
        self.round = 0
        self.init_sent = False
        self.live = False  # the newest frame came from a live camera (its batches say so)
        self.offset = 0  # internal frame index = camera seq + offset (see `fetch_map`)
        self.handover: tuple[MapSnapshot, MappingBatch] | None = None
        self.mapper_appeared = threading.Event()
        self.stats = TrackerStats()
        self.rejects = Rejects()
        # Checked on arrival (`_admit_frame`, `_admit_map`): a flood of bad messages never
        # pushes a real one out of these queues.
        self.newest_seq = -1  # the newest frame admitted, in the camera's numbering
        self.map_floor = 0  # snapshots of this version or older are refused
        self.frames_in = Inbox(FRAME_QUEUE, "frames", self._admit_frame)
        self.maps_in = Inbox(1, "map snapshots", self._admit_map)  # newest wins
        stop.watch(self.frames_in, self.maps_in)
        # Keep references to everything declared (zenoh.md trap 4).
        self.subscribers = [
            session.declare_subscriber(keys.frames, self.frames_in.callback),
            session.declare_subscriber(keys.map, self.maps_in.callback),
        ]
        self.pose_pub = pose_publisher(session, keys.poses)
        self.mapping_pub = publisher(session, keys.mapping, lossless=True)
        self.presence = Presence(session, keys, "tracker", self._peer_changed)
        self.session = session

    @property
    def frames(self) -> list[FrameState]:
        return self.front.frames if self.front is not None else []

    # -- liveliness -------------------------------------------------------------------------

    def _peer_changed(self, role: str, alive: bool) -> None:
        if role != "mapper":
            return
        if not alive:
            self.mapper_left = time.monotonic()
            if self.map_lag is not None:
                log.warning(
                    "the mapper is gone (map version %d): waiting up to %g s for it to come "
                    "back (--mapper-grace) once more than %d batches are unmapped",
                    self.map_version,
                    self.mapper_grace,
                    self.map_lag,
                )
            else:
                log.warning(
                    "the mapper is gone: tracking goes on with map version %d", self.map_version
                )
        else:
            log.info("a mapper is present")
            self.mapper_left = None
            self.mapper_appeared.set()

    def _query(self, what: str, timeout: float) -> bytes | None:
        for reply in self.session.get(self.keys.query(what), timeout=timeout):
            if reply.ok is not None:
                return reply.ok.payload.to_bytes()
        return None

    def fetch_map(self, timeout: float = 5.0) -> None:
        """A late tracker: take over the map a running mapper holds, if any."""
        if not self.presence.wait_for("mapper", 2.0):
            return
        try:
            snap_bytes = self._query("map", timeout)
            kf_bytes = self._query("keyframes", timeout) if snap_bytes else None
            if snap_bytes is None or kf_bytes is None:
                return
            snap, batch = MapSnapshot.from_bytes(snap_bytes), MappingBatch.from_bytes(kf_bytes)
        except MessageError as e:
            self.rejects("query/map", e)
            return
        if snap.config != self.digest:
            log.warning("the running mapper's map has other settings: starting a new one")
            return
        self.handover = (snap, batch)
        log.info("a mapper holds map version %d: this tracker continues it", snap.version)

    def _adopt(self) -> None:
        """Continue the fetched map: its keyframes become this tracker's."""
        assert self.handover is not None and self.front is not None
        snap, batch = self.handover
        self.handover = None
        if batch.camera != self.camera:
            log.warning("the running map was made with another camera: starting a new one")
            return
        load_map(self.field, snap)
        self.front.frames.extend(from_batch(batch, self.device))
        newest = max(snap.poses, default=0)
        if newest in snap.poses:  # the last tracked pose is the best guess for the next frame
            self.front.next_guess = pose_tensor(snap.poses[newest], self.device)
        self.offset = max([newest, *(f.index for f in self.frames)]) + 1
        self.map_version = snap.version
        self.map_round = snap.round
        self.round = snap.round + 1
        self.init_sent = True

    def _reseed_mapper(self) -> None:
        """A mapper appeared: if it has no map (restarted), give it ours before any batch."""
        self.mapper_appeared.clear()
        if not self.initialized:
            return
        held = self._query("map", 5.0)
        if held is not None:
            self._follow_resumed(held)
            return
        assert self.camera is not None
        keyframes = [f for f in self.frames if f.keyframe and f.rgb is not None]
        keyframes = keyframes[-MAX_BATCH_FRAMES:]
        if not keyframes:
            return
        snap = to_snapshot(
            self.map_version, self.map_round, self.digest, self.field, keyframes, keyframes
        )
        batch = to_batch(keyframes, self.round, self.camera)
        self.outbox[:0] = [snap.to_bytes(), batch.to_bytes()]
        self.round += 1
        log.info("the new mapper has no map: sending map version %d", self.map_version)

    def _follow_resumed(self, payload: bytes) -> None:
        """The new mapper has a map of its own (resumed from a checkpoint): its versions count
        from there, and may be behind this tracker's; take its next snapshots all the same,
        and send it again every batch its checkpoint does not cover."""
        try:
            snap = MapSnapshot.from_bytes(payload)
        except MessageError as e:
            self.rejects("query/map", e)
            return
        self.map_floor = min(self.map_floor, snap.version)
        if snap.version < self.map_version:
            log.info(
                "the mapper resumed map version %d (this tracker had %d): its maps are taken "
                "from there",
                snap.version,
                self.map_version,
            )
            self.map_version = snap.version
        self.map_round = min(self.map_round, snap.round)
        again = [p for r, p in sorted(self.uncovered.items()) if r > snap.round]
        if again:
            log.info("sending the resumed mapper %d batches its checkpoint lacks", len(again))
        self.outbox = again  # what the outbox held is among them

    # -- main loop --------------------------------------------------------------------------

    @property
    def initialized(self) -> bool:
        return self.map_version > 0

    def run(self) -> int:
        """Track until the stream ends or a stop signal; returns the exit code (0)."""
        self.fetch_map()
        bar = Progress(None, "tracker")
        try:
            while not self.stop:
                if self.mapper_appeared.is_set():
                    self._reseed_mapper()
                self._apply_snapshots()
                self._flush_outbox()
                if (self.init_sent and not self.initialized) or self._map_too_old():
                    self.maps_in_wait()
                    continue
                msg = self.frames_in.get(WAIT_S)
                if msg is None:
                    continue
                if self._handle(msg):
                    break
                bar.update(
                    self.stats.frames,
                    kf=sum(f.keyframe for f in self.frames),
                    lost=self.stats.lost,
                    dropped=self.stats.skipped_live,
                )
        finally:
            bar.close()
            self._end_of_stream()
        return 0

    def maps_in_wait(self) -> None:
        snap = self.maps_in.get(WAIT_S)
        if snap is not None:
            self.maps_in.put(snap)  # applied at the top of the loop, between frames

    def _admit_frame(self, payload: bytes) -> FrameMessage | EndOfStream | None:
        """A frames-topic message decoded on zenoh's thread; None (counted) if it is not a
        frame or an end, or is a frame not newer than the newest one admitted (`repeated`):
        the camera sends again the frames without a pose when a tracker comes back, and this
        one may have had them; the motion model cannot take one out of order anyway."""
        try:
            msg = decode_or_end(payload, FrameMessage)
            if isinstance(msg, FrameMessage):
                if msg.seq <= self.newest_seq:
                    self.stats.repeated += 1
                    return None
                self.newest_seq = msg.seq
        except MessageError as e:
            self.rejects("frames", e)
            return None
        return msg

    def _admit_map(self, payload: bytes) -> MapSnapshot | None:
        """A snapshot decoded on zenoh's thread; None (counted) if it is not one, has other
        settings, or is not newer than one already taken: it would push the newest out of
        its queue of one."""
        try:
            snap = MapSnapshot.from_bytes(payload)
            if snap.config != self.digest:
                raise MessageError(f"snapshot {snap.version} has other map settings")
            if snap.version <= max(self.map_floor, self.map_version):
                raise MessageError(
                    f"snapshot {snap.version}: not newer than version "
                    f"{max(self.map_floor, self.map_version)} (a duplicate or out of order)"
                )
            self.map_floor = snap.version
        except MessageError as e:
            self.rejects("map", e)
            return None
        return snap

    def _handle(self, msg: FrameMessage | EndOfStream) -> bool:
        """Process one frames-topic message; True at the end of the stream."""
        try:
            if isinstance(msg, EndOfStream):
                log.info("end of stream after %d frames", msg.frames)
                return True
            self.stats.received += 1
            self.live = msg.live
            if msg.live and len(self.frames_in) > 0:
                self.stats.skipped_live += 1  # a newer live frame is waiting: this one is stale
                return False
            rgb = self._prepare(msg)
        except MessageError as e:
            self.rejects("frames", e)
            return False
        if msg.live and self.front is not None and not self.front.live:
            self.front.go_live()
        if self.handover is not None:
            self._adopt()
        self.stats.frames += 1
        self._process(msg.seq + self.offset, msg.timestamp, rgb, msg.stamp_ns)
        return False

    def _prepare(self, msg: FrameMessage) -> torch.Tensor:
        """The frame on the device at the configured width; the first frame fixes the camera."""
        if self.source_camera is None:
            self.source_camera = msg.camera
            cam = msg.camera
            if self.cfg.width and self.cfg.width != cam.width:
                cam = cam.resized(self.cfg.width)
            self.camera = cam
            self.front = FrontEnd(self.cfg, cam, self.generator)
            log.info("camera %dx%d, tracking at %dx%d", *msg.camera.size, *cam.size)
        elif msg.camera != self.source_camera:
            raise MessageError(f"frame {msg.seq}: camera {msg.camera} differs from the stream's")
        rgb = msg.rgb
        assert self.camera is not None
        if rgb.shape[1] != self.camera.width:
            rgb = cv2.resize(rgb, self.camera.size, interpolation=cv2.INTER_AREA)
        return image_tensor(rgb, self.device)

    def _process(self, seq: int, timestamp: float, rgb: torch.Tensor, sent_ns: int) -> None:
        assert self.front is not None
        if not self.initialized:
            if self.front.collect(seq, timestamp, rgb):
                self._send_batch(self.front.take_batch())
                self.init_sent = True
            return
        started = time.perf_counter()
        state = self.front.track(self.field, seq, timestamp, rgb)
        self.stats.track_seconds.append(time.perf_counter() - started)
        self.stats.mapper_busy.append(self._mapper_busy())
        if state is None:
            self.stats.lost += 1
            lost = PoseMessage(
                seq - self.offset, timestamp, None, map_version=self.map_version, lost=True
            )
            self.pose_pub.put(lost.to_bytes())
        else:
            self.stats.tracked += 1
            self._publish_pose(state)
            self.stats.latency_seconds.append((now_ns() - sent_ns) / 1e9)
        if self.front.batch_due():  # a complete batch, or what was tracked up to a loss
            self._send_batch(self.front.take_batch())

    def _unmapped(self) -> int:
        """Batches sent to a mapper that no snapshot covers yet (0 without a mapper)."""
        if not self._mapper_expected():
            return 0
        return max(0, self.round - 1 - self.map_round)

    def _mapper_expected(self) -> bool:
        """A mapper is alive, or left less than `mapper_grace` seconds ago (a restart with
        `--resume` takes seconds)."""
        if self.presence.alive("mapper"):
            return True
        if self.mapper_left is None:
            return False
        if time.monotonic() - self.mapper_left <= self.mapper_grace:
            return True
        log.warning(
            "the mapper did not come back within %g s: tracking goes on with map version %d",
            self.mapper_grace,
            self.map_version,
        )
        self.mapper_left = None
        return False

    def _map_too_old(self) -> bool:
        """With `map_lag`: more batches sent to a mapper are unmapped than it allows."""
        return self.map_lag is not None and self.initialized and self._unmapped() > self.map_lag

    def _mapper_busy(self) -> bool:
        """Whether a batch sent to a live mapper has no snapshot yet (a round is running)."""
        return self._unmapped() > 0

    def _publish_pose(self, state: FrameState) -> None:
        T = pose_array(state.T_wc)
        self.online.setdefault(state.index, (state.timestamp, T))
        seq = state.index - self.offset  # the camera's own numbering
        msg = PoseMessage(seq, state.timestamp, T, state.keyframe, self.map_version)
        self.pose_pub.put(msg.to_bytes())

    def _send_batch(self, frames: list[FrameState]) -> None:
        assert self.camera is not None
        payload = to_batch(frames, self.round, self.camera, live=self.live).to_bytes()
        self.outbox.append(payload)
        self.uncovered[self.round] = payload
        self.round += 1
        self._flush_outbox()

    def _flush_outbox(self) -> None:
        """Send held batches once a mapper listens: a put with no subscriber is lost."""
        if self.outbox and self.mapping_pub.matching_status.matching:
            for payload in self.outbox:
                self.mapping_pub.put(payload)
            self.outbox.clear()

    # -- snapshots --------------------------------------------------------------------------

    def _apply_snapshots(self) -> None:
        snap = self.maps_in.get(0.0)  # decoded and checked by `_admit_map`
        if snap is None:
            return
        if snap.version <= self.map_version:
            return
        try:
            load_map(self.field, snap)
        except MessageError as e:
            self.rejects("map", e)
            return
        first = not self.initialized
        if self.front is not None:
            self.front.apply_poses(snapshot_poses(snap, self.device), snap.keyframes)
            started = time.perf_counter()
            self.front.map_changed(self.field, snap.version)
            self.stats.refresh_seconds.append(time.perf_counter() - started)
        self.map_version = snap.version
        self.map_round = snap.round
        for covered in [r for r in self.uncovered if r <= snap.round]:
            del self.uncovered[covered]
        self.stats.snapshots += 1
        log.debug("map version %d (round %d) swapped in", snap.version, snap.round)
        if first:
            for f in self.frames:
                if f.index >= self.offset:
                    self._publish_pose(f)

    # -- end --------------------------------------------------------------------------------

    def _end_of_stream(self) -> None:
        """Flush the last batch, tell the mapper and the pose subscribers the stream ended."""
        if self.front is not None and self.initialized and self.front.pending:
            self._send_batch(self.front.take_batch())
        elif self.front is not None and not self.init_sent and self.front.collect_rest():
            log.info("stream shorter than %d frames: initializing on all", len(self.frames))
            self._send_batch(self.front.take_batch())
            self.init_sent = True
        if self.init_sent and not self.initialized and not self.stop:
            log.info("waiting for the mapper's initialization to publish the first poses")
            while not self.stop and not self.initialized:
                self._flush_outbox()
                self.maps_in_wait()
                self._apply_snapshots()
        end = EndOfStream(len(self.online)).to_bytes()
        self.outbox.append(end)
        self._flush_outbox()
        if self.outbox:
            log.warning("no mapper listening: %d mapping messages not delivered", len(self.outbox))
        self.pose_pub.put(end)
        log.info(
            "%d frames, %d tracked, %d lost, %d poses published, %d snapshots, %d rejected, "
            "%d live frames skipped, %d dropped, %d repeated",
            self.stats.frames,
            self.stats.tracked,
            self.stats.lost,
            len(self.online),
            self.stats.snapshots,
            self.rejects.count,
            self.stats.skipped_live,
            self.frames_in.dropped,
            self.stats.repeated,
        )

    def online_trajectory(self) -> Trajectory:
        """Every pose as it was first published."""
        seqs = sorted(self.online)
        if not seqs:
            return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
        return Trajectory(
            np.array([self.online[s][0] for s in seqs]),
            np.stack([self.online[s][1] for s in seqs]),
        )

    def write(self, out: Path) -> None:
        out.mkdir(parents=True, exist_ok=True)
        write_tum(out / "trajectory_online.txt", self.online_trajectory(), header="as published")
        summary = self.stats.summary(self.frames_in.dropped)
        summary["frames_refined"] = len(self.front.refined) if self.front is not None else 0
        (out / "tracker_stats.json").write_text(json.dumps(summary, indent=2) + "\n")
        log.info("wrote trajectory_online.txt and tracker_stats.json to %s", out)

    def close(self) -> None:
        self.presence.close()

"""Fuzzing, measured: every key the service's processes subscribe to fed hostile messages.

    python benchmarks/fuzz.py [--messages 2000] [--frames 60] [--rate 2] [--out out/fuzz]
        [--json out/fuzz.json]
    python benchmarks/fuzz.py --messages 100000 --rate 0.1    # the issue's count, per key

The service runs on the built-in scene as in benchmarks/faults.py (its `Harness`: tiny preset,
lockstep camera at `--rate` frames per second and at most 10 frames ahead of the poses,
router, mapper, tracker and camera as zenoh clients of the router on loopback). Once the
first pose is out (the stream exists: its first frame fixed the camera), a second harness
session publishes `--messages` hostile messages on each subscribed key, paced by the poses
so that they are all sent `HOLD_MARGIN` poses before the camera may publish its last frame
(at 60 frames: by pose 46), round robin over the generators. A fuzzer still behind by then
holds the camera (SIGSTOP, `HOLD_MAX_S` at most) and sends the rest at once, so that a busy
machine does not end the stream with messages unsent (the time held is reported):

- random: random bytes (sometimes behind a msgpack map header);
- truncated: a prefix of a message captured on the key;
- bitflip: a captured message with 1-8 bits flipped, most in its header and tail;
- version: a captured message with another schema version or type tag;
- shape: absurd array shapes, byte counts, cameras, frame counts;
- nonfinite: NaN and infinite numbers, non-rigid and reflected poses, NaN map tensors;
- types: one field of a captured message replaced by a value of another type;
- sequence: duplicate and out-of-order sequence numbers (frame seq, batch round, map
  version, pose seq): real messages sent again, or with an old (or, for poses, a never sent)
  number.

The blind mutations (random, truncated, bitflip, types) that still decode are not sent (they
are valid messages, for a receiver indistinguishable from the sender's: what TLS and
authentication are for, deploy/README.md) and counted as `still_valid`; the built ones
(version, shape, nonfinite) are all sent, and those the decoder accepts are counted as
`decoded`: each is a finding. Sequence messages decode by design: the receiver's stream
checks must refuse them (or, for old poses, ignore them).

Subscribed keys (transport.py's table; each is checked to have a subscriber before the run):
the tracker's `frames` and `map`, the mapper's `mapping`, the camera's `poses`. Not fuzzed:
liveliness tokens (no payload) and the mapper's queryables, which read no query payload.

Reported per process: exit code and whether it crashed (non-zero exit, a traceback, or still
running), rejections it counted, the log lines about rejections per key, RSS at the start and
end of fuzzing (VmRSS) and its peak, the growth of its private part (RssAnon; the rest is
mostly the zenoh shared-memory pages of the processes it receives from), and RSS again
`SETTLE_S` after the flood (where the stream lasts that long: `--rate` 0.1 or lower), once
the process has trimmed its heap, which is what it keeps; per key the
messages sent per generator; and the final trajectory's ATE against a clean run with the
same seed (`--messages 0`), unless `--no-clean`. The clean run's RSS is taken at the same
points (first pose, the pose by which every message is sent, settled): a tracker's grows
with the map and keyframes it receives, so its settled RSS beyond the clean run's is what
the hostile messages cost it.
"""

from __future__ import annotations

import json
import re
import shutil
import signal
import subprocess
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import msgpack
import numpy as np
import zenoh
from faults import WAIT_S, Harness, benchmark_parser, builtin_scene, report

from dimslam.common.config import PRESETS
from dimslam.common.io.trajectory import read_tum
from dimslam.common.net.messages import (
    EndOfStream,
    FrameMessage,
    MappingBatch,
    MapSnapshot,
    MessageError,
    PoseMessage,
    decode_or_end,
    message_type,
)
from dimslam.common.net.service import HEAP_TRIM_S
from dimslam.common.net.transport import Keys

TARGETS = {"frames": "tracker", "map": "tracker", "mapping": "mapper", "poses": "camera"}
"""Every key a process of the service subscribes to, and which process."""
GENERATORS = (
    "random", "truncated", "bitflip", "version", "shape", "nonfinite", "types", "sequence",
)  # fmt: skip
BLIND = {"random", "truncated", "bitflip", "types"}
"""Generators whose output may happen to be valid: redrawn (up to `TRIES`) until it is not."""
TRIES = 20
ROLES = ("router", "mapper", "tracker", "camera")
END_WAIT_S = 120.0
"""How long the processes have to finish (mapper: final round and outputs) after the end."""
MATCH_WAIT_S = 30.0
"""How long the fuzzer waits for its publishers to see a subscriber (a routed declaration)."""
HOLD_MARGIN = 3
"""Poses between the one by which every message is sent and the first that lets the
camera publish its last frame (and so end the stream)."""
HOLD_MAX_S = 4.0
"""The longest the camera is held: well inside zenoh's 10 s lease (the router would drop
its session, and the frames it sends meanwhile would go unanswered)."""
SETTLE_S = 2 * HEAP_TRIM_S + 5
"""How long after the flood RSS is taken again: what the process keeps, not what it holds."""
_REJECT_LINE = re.compile(r"rejected (?:a message|\d+ more messages?) on (\S+?)[ :(]")


def _mapping(payload: bytes) -> object:
    if message_type(payload) == MapSnapshot.TYPE:
        return MapSnapshot.from_bytes(payload)
    return decode_or_end(payload, MappingBatch)


DECODERS: dict[str, Callable[[bytes], object]] = {
    "frames": lambda p: decode_or_end(p, FrameMessage),
    "poses": lambda p: decode_or_end(p, PoseMessage),
    "mapping": _mapping,
    "map": MapSnapshot.from_bytes,
}
"""What a receiver of each key decodes (the same decoders the processes use)."""


def _decodes(key: str, payload: bytes) -> bool:
    try:
        DECODERS[key](payload)
    except MessageError:
        return False
    return True


# -- generators ------------------------------------------------------------------------------

WRONG_VALUES = (None, True, "x", 1.5, -3, 2**64 - 1, [], {}, b"\x00", [1, 2, 3], {"a": 1})


def _children(obj: object):
    """(key or index, value) of a map's or a list's items; none for anything else."""
    if isinstance(obj, dict):
        return obj.items()
    return enumerate(obj) if isinstance(obj, list) else ()


def _paths(obj: object, path: tuple = ()) -> list[tuple]:
    """Every field below `obj` (maps and lists walked; the array maps' own fields included)."""
    found = []
    for k, v in _children(obj):
        found.append((*path, k))
        found += _paths(v, (*path, k))
    return found


def _arrays(obj: object, path: tuple = ()) -> list[tuple]:
    """Paths of the array maps (`{"dtype", "shape", "data"}`) below `obj`."""
    if isinstance(obj, dict) and set(obj) == {"dtype", "shape", "data"}:
        return [path]
    return [p for k, v in _children(obj) for p in _arrays(v, (*path, k))]


def _get(body: object, path: tuple) -> object:
    for k in path:
        body = body[k]
    return body


def _set(body: object, path: tuple, value: object) -> None:
    _get(body, path[:-1])[path[-1]] = value


def _pack(body: object) -> bytes:
    return msgpack.packb(body, use_bin_type=True)


def _pose_arrays(body: dict) -> list[tuple]:
    return [p for p in _arrays(body) if _get(body, p)["shape"] == [4, 4]]


def _bad_pose(rng: np.random.Generator) -> np.ndarray:
    T = np.eye(4)
    match int(rng.integers(6)):
        case 0:
            T[int(rng.integers(4)), int(rng.integers(4))] = np.nan
        case 1:
            T[:3, 3] = np.inf
        case 2:
            T[:3, :3] *= 1.5  # scaled
        case 3:
            T[0, 1] = 0.3  # sheared
        case 4:
            T[0, 0] = -1.0  # reflected
        case _:
            T[3] = [0.0, 0.0, 1.0, 1.0]  # projective
    return T


@dataclass
class Bases:
    """Real messages captured on every key (mutated into hostile ones), and the stream's
    progress as the harness sees it."""

    payloads: dict[str, list[bytes]] = field(default_factory=lambda: {k: [] for k in TARGETS})
    highest_pose: int = -1
    versions: list[int] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)
    KEEP = 8

    def add(self, key: str, payload: bytes) -> None:
        try:
            msg = DECODERS[key](payload)
        except MessageError:
            return  # a hostile message of our own, seen by our own subscriber
        if isinstance(msg, EndOfStream):
            return
        with self.lock:
            kept = self.payloads[key]
            kept.append(payload)
            del kept[: -self.KEEP]
            if isinstance(msg, MapSnapshot):
                self.versions.append(msg.version)

    def pick(self, key: str, rng: np.random.Generator) -> bytes:
        with self.lock:
            kept = self.payloads[key]
            return kept[int(rng.integers(len(kept)))]


class Generator:
    """Hostile messages for one key."""

    def __init__(self, key: str, bases: Bases, frames: int, seed: int) -> None:
        self.key, self.bases, self.frames = key, bases, frames
        self.rng = np.random.default_rng(seed)

    def make(self, kind: str) -> bytes:
        base = self.bases.pick(self.key, self.rng)
        if kind in ("random", "truncated", "bitflip"):
            return getattr(self, kind)(base)
        body = msgpack.unpackb(base, raw=False)
        return _pack(getattr(self, kind)(body))

    def random(self, _base: bytes) -> bytes:
        rng = self.rng
        data = rng.bytes(int(rng.integers(0, 4096)))
        if rng.random() < 0.5:  # looks like a message map for its first byte or two
            data = bytes([0x80 | int(rng.integers(16))]) + data
        return data

    def truncated(self, base: bytes) -> bytes:
        return base[: int(self.rng.integers(0, len(base)))]

    def bitflip(self, base: bytes) -> bytes:
        rng = self.rng
        data = bytearray(base)
        for _ in range(int(rng.integers(1, 9))):
            # The header and the tail hold the structure; the middle is mostly pixels, whose
            # flips make valid messages (redrawn).
            region = int(rng.integers(3))
            n = len(data)
            pos = (
                int(rng.integers(min(n, 256)))
                if region == 0
                else n - 1 - int(rng.integers(min(n, 256)))
                if region == 1
                else int(rng.integers(n))
            )
            data[pos] ^= 1 << int(rng.integers(8))
        return bytes(data)

    def version(self, body: dict) -> dict:
        rng = self.rng
        choice = int(rng.integers(3))
        if choice == 0:
            body["v"] = [0, 2, 255, -1, 2**40, "1", 1.0, None, True, [1]][int(rng.integers(10))]
        elif choice == 1:
            del body["v"]
        else:
            body["type"] = ["frame", "pose", "mapping", "map", "end", "checkpoint", "?", 7, None][
                int(rng.integers(9))
            ]
            if body["type"] == self._own_type(body):
                body["type"] = "nonsense"
        return body

    def _own_type(self, body: dict) -> str:
        return {"frames": "frame", "poses": "pose", "mapping": "mapping", "map": "map"}[self.key]

    def shape(self, body: dict) -> dict:
        rng = self.rng
        arrays = _arrays(body)
        choice = int(rng.integers(4))
        if choice == 0 and "camera" in body:
            body["camera"] = [
                [100_000, 100_000, 500.0, 500.0, 1.0, 1.0],
                [-160, 120, 100.0, 100.0, 80.0, 60.0],
                [0, 0, 100.0, 100.0, 80.0, 60.0],
                [160, 120, 0.0, -1.0, 80.0, 60.0],
                [160, 120],
            ][int(rng.integers(5))]
        elif choice == 1 and isinstance(body.get("frames"), list):
            frames = body["frames"]
            body["frames"] = [] if rng.random() < 0.3 else frames * (65 // len(frames) + 1)
        elif choice == 2 and arrays:
            arr = _get(body, arrays[int(rng.integers(len(arrays)))])
            arr["data"] = arr["data"] + rng.bytes(int(rng.integers(1, 4 << 20)))  # oversized
        elif arrays:
            arr = _get(body, arrays[int(rng.integers(len(arrays)))])
            arr["shape"] = [
                [2**31, 2**31, 3],
                [10**12],
                [-1, 3],
                [4] * 9,
                [0, 2**62, 2**62],
                ["4", 4],
                [4.0, 4.0],
                [],
                [1, 1, 1],
            ][int(rng.integers(9))]
        else:
            body["seq"] = 2**64 - 1  # no array in the message: an absurd number
        return body

    def nonfinite(self, body: dict) -> dict:
        rng = self.rng
        poses = _pose_arrays(body)
        tensors = [p for p in _arrays(body) if p[:1] == ("state",)]
        stamps = [p for p in _paths(body) if p[-1] == "timestamp"]
        choice = int(rng.integers(3))
        if choice == 0 and poses:
            arr = _get(body, poses[int(rng.integers(len(poses)))])
            arr["data"] = _bad_pose(rng).tobytes()
        elif choice == 1 and tensors:
            arr = _get(body, tensors[int(rng.integers(len(tensors)))])
            values = np.frombuffer(arr["data"], arr["dtype"]).copy()
            values[int(rng.integers(values.size))] = [np.nan, np.inf, -np.inf][int(rng.integers(3))]
            arr["data"] = values.tobytes()
        elif stamps:
            _set(body, stamps[int(rng.integers(len(stamps)))], float(rng.choice([np.nan, np.inf])))
        elif "camera" in body:
            body["camera"][2] = float("nan")
        elif poses:
            _get(body, poses[0])["data"] = _bad_pose(rng).tobytes()
        return body

    def types(self, body: dict) -> dict:
        rng = self.rng
        paths = [p for p in _paths(body) if p[0] not in ("v", "type")]
        path = paths[int(rng.integers(len(paths)))]
        current = _get(body, path)
        wrong = [w for w in WRONG_VALUES if type(w) is not type(current)]
        _set(body, path, wrong[int(rng.integers(len(wrong)))])
        return body

    def sequence(self, body: dict) -> dict:
        """An old (duplicate or out-of-order) number; for poses half are of unsent frames."""
        rng = self.rng
        with self.bases.lock:
            highest = self.bases.highest_pose
            versions = list(self.bases.versions)
        if self.key == "frames":
            body["seq"] = int(rng.integers(0, max(highest, 0) + 1))
        elif self.key == "poses":
            late = rng.random() < 0.5
            body["seq"] = int(
                rng.integers(0, max(highest, 0) + 1) if late else self.frames + rng.integers(1000)
            )
        elif self.key == "mapping" and rng.random() < 0.5:
            body["round"] = int(rng.integers(0, body["round"] + 1))
        elif self.key == "map" and rng.random() < 0.5:
            body["version"] = int(rng.integers(0, max(versions[:-1], default=1) + 1))
        return body  # else: sent again as it was


# -- the run ---------------------------------------------------------------------------------


def rss_mb(pid: int, field: str = "VmRSS") -> float | None:
    """A process's resident set (VmRSS), or one part of it (RssAnon: its private memory;
    RssShmem: shared memory it touched, such as zenoh's shared-memory pools of the processes
    it receives from), MiB; None once it is gone."""
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return None
    found = re.search(rf"{field}:\s+(\d+) kB", text)
    return int(found.group(1)) / 1024 if found else None


def memory_mb(procs: dict[str, subprocess.Popen], field: str = "VmRSS") -> dict:
    """`rss_mb` of each process, by role."""
    return {role: rss_mb(p.pid, field) for role, p in procs.items()}


def _growth(start: float | None, end: float | None) -> float | None:
    return None if start is None or end is None else end - start


class Fuzzer:
    """Sends the hostile messages from a session of its own, paced by the poses seen."""

    def __init__(
        self, h: Harness, keys: Keys, bases: Bases, messages: int, frames: int, done_at: int
    ) -> None:
        self.h, self.keys, self.bases = h, keys, bases
        self.messages, self.frames, self.done_at = messages, frames, done_at
        self.lock = threading.Lock()
        self.done = messages == 0  # a clean run holds nothing
        self.hurry = False  # past `done_at`: the rest goes out at once
        self.held_since: float | None = None
        self.held_s = 0.0
        self._unhold_timer: threading.Timer | None = None
        self.sent = {k: Counter() for k in TARGETS}
        self.still_valid = {k: Counter() for k in TARGETS}
        self.decoded = {k: Counter() for k in TARGETS}
        self.peak_rss: dict[str, float] = {}
        self.seconds = 0.0
        self.error: str | None = None

    def _allowed(self, start: int) -> int:
        """Messages (over all keys) that may be out by now."""
        total = self.messages * len(TARGETS)
        if self.hurry:
            return total
        span = max(1.0, self.done_at - start)
        return int(total * min(1.0, (self.h.count - start + 1) / span))

    def hold_if_behind(self, highest_pose: int) -> None:
        """Called on every pose: from `done_at` on, a fuzzer not done stops the camera for at
        most `HOLD_MAX_S` and sends the rest at once."""
        with self.lock:
            if self.done or self.hurry or highest_pose < self.done_at:
                return
            self.hurry = True
            self.h.procs["camera"].send_signal(signal.SIGSTOP)
            self.held_since = time.monotonic()
            self._unhold_timer = threading.Timer(HOLD_MAX_S, self._unhold)
            self._unhold_timer.start()
        with self.h.changed:
            self.h.changed.notify_all()

    def _unhold(self) -> None:
        with self.lock:
            if self.held_since is not None:
                self.h.procs["camera"].send_signal(signal.SIGCONT)
                self.held_s = time.monotonic() - self.held_since
                self.held_since = None

    def _release(self) -> None:
        with self.lock:
            self.done = True
            if self._unhold_timer is not None:
                self._unhold_timer.cancel()
        self._unhold()

    def _sample_rss(self) -> None:
        for role, mb in memory_mb(self.h.procs).items():
            if mb is not None:
                self.peak_rss[role] = max(self.peak_rss.get(role, 0.0), mb)

    def run(self, session: zenoh.Session) -> None:
        try:
            self._flood(session)
        finally:
            self._release()

    def _flood(self, session: zenoh.Session) -> None:
        started = time.monotonic()
        pubs = {
            k: session.declare_publisher(
                getattr(self.keys, k), congestion_control=zenoh.CongestionControl.BLOCK
            )
            for k in TARGETS
        }
        for k, pub in pubs.items():
            matched = threading.Event()
            listener = pub.declare_matching_listener(lambda s, m=matched: s.matching and m.set())
            if not (pub.matching_status.matching or matched.wait(MATCH_WAIT_S)):
                self.error = f"nobody subscribes to {k}: the table of keys is out of date"
                raise RuntimeError(self.error)
            listener.undeclare()
        gens = {k: Generator(k, self.bases, self.frames, seed=i) for i, k in enumerate(TARGETS)}
        start = self.h.count
        order = [(k, g) for g in GENERATORS for k in TARGETS]
        total = self.messages * len(TARGETS)
        sent = 0
        last_sample = 0.0
        while sent < total and not self.h.ended.is_set():
            allowed = self._allowed(start)
            if sent >= allowed:
                with self.h.changed:
                    self.h.changed.wait(0.5)
                continue
            for _ in range(allowed - sent):
                key, kind = order[sent % len(order)]
                pubs[key].put(self._one(gens[key], key, kind))
                self.sent[key][kind] += 1
                sent += 1
            if time.monotonic() - last_sample > 0.5:
                self._sample_rss()
                last_sample = time.monotonic()
        self._sample_rss()
        self.seconds = time.monotonic() - started
        for pub in pubs.values():
            pub.undeclare()

    def _one(self, gen: Generator, key: str, kind: str) -> bytes:
        for _ in range(TRIES):
            payload = gen.make(kind)
            valid = _decodes(key, payload)
            if kind in BLIND and valid:
                self.still_valid[key][kind] += 1
                continue
            if valid and kind != "sequence":
                self.decoded[key][kind] += 1
            return payload
        return payload


def _log_figures(log: str) -> dict:
    per_key = Counter(_REJECT_LINE.findall(log))
    return {
        "reject_lines": dict(per_key),
        "queue_full_lines": log.count("queue full"),
        "log_lines": log.count("\n"),
        "traceback": "Traceback" in log,
    }


def _rejected(role: str, log: str) -> int | None:
    """Messages the process's closing line says it refused (the tracker's frames not newer
    than one it took count too: it ignores them without a log line, as a camera sends them
    again after a link cut)."""
    patterns = {
        "tracker": [r"(\d+) rejected,", r"(\d+) repeated"],
        "mapper": [r"(\d+) rejected messages"],
        "camera": [r"(\d+) poses rejected"],
    }.get(role, [])
    counts = [re.findall(p, log) for p in patterns]
    if not counts or not all(counts):
        return None
    return sum(int(found[-1]) for found in counts)


def run_fuzz(scene: Path, out: Path, messages: int, frames: int, rate: float) -> dict:
    """One run of the service with `messages` hostile messages per key (0: a clean run)."""
    name = "fuzz" if messages else "clean"
    folder = out / name
    shutil.rmtree(folder, ignore_errors=True)  # the harness appends to the logs it finds
    # Never more frames ahead of the poses than the initialization needs: the frames after it
    # come at `rate`, not in one burst when the map exists, and the fuzzing spans them.
    ahead = PRESETS["tiny"].mapper.init_frames + 2
    camera = ["--lockstep", "--rate", str(rate), "--ahead", str(ahead)]
    # The camera publishes its last frame once it has the pose `frames - 1 - ahead`.
    done_at = max(1, frames - 1 - ahead - HOLD_MARGIN)
    # Bounded staleness, as `dimslam run` (common/net/launch.py): the ATE then does not
    # depend on when the mapper's rounds end, which a machine busy with the fuzzing changes.
    h = Harness(name, scene, folder, {"camera": camera, "tracker": ["--map-lag", "1"]})
    stream_s = frames / rate if rate > 0 else 0.0  # how long the camera takes, at least
    bases = Bases()
    fuzzer = Fuzzer(h, Keys(h.session_name), bases, messages, frames, done_at)
    seen: set[int] = set()
    rss_start: dict[str, float | None] = {}
    rss_end: dict[str, float | None] = {}
    rss_settled: dict[str, float | None] = {}
    anon_start: dict[str, float | None] = {}
    anon_end: dict[str, float | None] = {}

    def on_pose(sample: zenoh.Sample) -> None:
        payload = sample.payload.to_bytes()
        bases.add("poses", payload)
        try:
            msg = decode_or_end(payload, PoseMessage)
        except MessageError:
            return  # one of ours
        if isinstance(msg, EndOfStream):
            h.ended.set()
        elif msg.seq < frames:  # a pose of a never sent frame is one of ours too
            seen.add(msg.seq)
            with bases.lock:
                bases.highest_pose = max(bases.highest_pose, msg.seq)
            fuzzer.hold_if_behind(msg.seq)
        with h.changed:
            h.count = len(seen)
            h.changed.notify_all()

    started = time.monotonic()
    codes: dict[str, object] = {}
    try:
        h.start("router")
        with h.session() as zs, h.session() as fz:
            keys = Keys(h.session_name)
            captures = [
                zs.declare_subscriber(
                    getattr(keys, k), lambda s, k=k: bases.add(k, s.payload.to_bytes())
                )
                for k in ("frames", "mapping", "map")
            ]
            subs = [zs.declare_subscriber(keys.poses, on_pose)]
            for role in ("mapper", "tracker", "camera"):
                h.start(role)
            h.wait_for_poses(1)
            rss_start, anon_start = memory_mb(h.procs), memory_mb(h.procs, "RssAnon")
            thread = threading.Thread(target=fuzzer.run, args=(fz,), daemon=True)
            for sub in captures:  # enough bases: decoding our own messages would slow us
                sub.undeclare()
            if messages:
                thread.start()
                thread.join(stream_s + WAIT_S)
                if fuzzer.error:
                    raise RuntimeError(fuzzer.error)
            else:  # the clean run's end figures at the point where the fuzzing would end
                h.wait_for_poses(done_at, stream_s + WAIT_S)
            rss_end, anon_end = memory_mb(h.procs), memory_mb(h.procs, "RssAnon")
            # What stays: the heaps are trimmed every HEAP_TRIM_S (service.trim_heap), and
            # the messages of the flood's last seconds are still in them at its end. Only
            # where the stream outlasts the wait (a short run's processes would be gone).
            if (1 - done_at / frames) * stream_s > 2 * SETTLE_S:
                time.sleep(SETTLE_S)
                rss_settled = memory_mb(h.procs)
            if not h.ended.wait(stream_s + WAIT_S):
                raise RuntimeError(f"{name}: no end of stream after {stream_s + WAIT_S:g} s")
            for role in ("camera", "tracker", "mapper"):
                try:
                    codes[role] = h.procs[role].wait(END_WAIT_S)
                except subprocess.TimeoutExpired:
                    codes[role] = "still running"
            h.procs["router"].send_signal(signal.SIGTERM)
            try:
                codes["router"] = h.procs["router"].wait(30)
            except subprocess.TimeoutExpired:
                codes["router"] = "still running"
            for sub in subs:
                sub.undeclare()
    finally:
        h.stop_all()
    processes = {}
    for role in ROLES:
        log = (folder / f"{role}.log").read_text()
        figures = _log_figures(log)
        start_mb, end_mb = rss_start.get(role), rss_end.get(role)
        processes[role] = {
            "exit": codes.get(role),
            "crashed": codes.get(role) != 0 or figures["traceback"],
            "rejected": _rejected(role, log),
            **figures,
            "rss_start_mb": start_mb,
            "rss_end_mb": end_mb,
            "rss_settled_mb": rss_settled.get(role),
            "settled_growth_mb": _growth(start_mb, rss_settled.get(role)),
            "rss_peak_mb": fuzzer.peak_rss.get(role),
            "rss_growth_mb": _growth(start_mb, end_mb),
            "private_growth_mb": _growth(anon_start.get(role), anon_end.get(role)),
        }
    result = {
        "run": name,
        "messages_per_key": messages,
        "frames": frames,
        "posed": len(seen),
        "seconds": time.monotonic() - started,
        "fuzz_seconds": fuzzer.seconds,
        "camera_held_s": fuzzer.held_s,
        "sent": {k: dict(v) for k, v in fuzzer.sent.items()},
        "sent_total": sum(sum(v.values()) for v in fuzzer.sent.values()),
        "still_valid": {k: dict(v) for k, v in fuzzer.still_valid.items() if v},
        "decoded": {k: dict(v) for k, v in fuzzer.decoded.items() if v},
        "processes": processes,
    }
    result.update(h.final_figures())
    online = folder / "tracker" / "trajectory_online.txt"
    result["online_frames"] = len(read_tum(online)) if online.is_file() else 0
    return result


def beyond_clean(process: dict, clean: dict | None, role: str) -> float | None:
    """A fuzzed process's settled RSS less the clean run's at the same point of the stream:
    what the hostile messages left it with, apart from the map and keyframes every run
    accumulates (growths would not do: a mapper's start figure is taken mid-initialization)."""
    if clean is None:
        return None
    return _growth(clean["processes"][role]["rss_settled_mb"], process["rss_settled_mb"])


def table(results: list[dict]) -> str:
    """Per run and process: exit, rejections, log lines per key, RSS; then the ATE."""
    rows = [
        "| run | process | exit | crashed | rejected | rejection log lines per key "
        "| RSS start -> end (peak) | growth | of which private | settled (growth) "
        "| settled beyond the clean run's |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    clean_run = next((r for r in results if r["run"] == "clean"), None)
    for r in results:
        for role, p in r["processes"].items():
            lines = ", ".join(f"{k.rsplit('/', 1)[-1]} {n}" for k, n in p["reject_lines"].items())

            def mb(v):
                return "-" if v is None else f"{v:.0f}"

            rows.append(
                f"| {r['run']} | {role} | {p['exit']} | {'yes' if p['crashed'] else 'no'} "
                f"| {'-' if p['rejected'] is None else p['rejected']} | {lines or '-'} "
                f"| {mb(p['rss_start_mb'])} -> {mb(p['rss_end_mb'])} ({mb(p['rss_peak_mb'])}) MiB "
                f"| {mb(p['rss_growth_mb'])} MiB | {mb(p.get('private_growth_mb'))} MiB "
                f"| {mb(p['rss_settled_mb'])} ({mb(p['settled_growth_mb'])}) MiB "
                f"| {mb(beyond_clean(p, clean_run, role)) if r is not clean_run else '-'} MiB |"
            )
    rows.append("")
    clean = clean_run.get("ate_m") if clean_run else None
    for r in results:
        ate = r.get("ate_m")
        ratio = f", {ate / clean:.2f}x clean" if ate and clean else ""
        rows.append(
            f"{r['run']}: {r['sent_total']} messages sent in {r['fuzz_seconds']:.0f} s "
            f"(camera held {r['camera_held_s']:.1f} s), "
            f"posed {r['posed']} / {r['frames']}, final frames {r.get('final_frames')}, "
            f"ATE {'-' if ate is None else f'{100 * ate:.2f} cm'}{ratio}"
        )
    return "\n".join(rows)


def main() -> int:
    parser = benchmark_parser(__doc__, "fuzz")
    parser.add_argument(
        "--messages", type=int, default=2000, help="hostile messages per subscribed key"
    )
    parser.add_argument(
        "--rate",
        type=float,
        default=2.0,
        help="camera frames per second (lower it for more messages: the run must outlast them)",
    )
    parser.add_argument("--no-clean", action="store_true", help="skip the clean reference run")
    args = parser.parse_args()
    scene = builtin_scene(args.out / f"scene{args.frames}", args.frames)
    runs = ([] if args.no_clean else [0]) + [args.messages]
    results = []
    for messages in runs:
        print(f"{messages} messages per key ...", flush=True)
        results.append(run_fuzz(scene, args.out, messages, args.frames, args.rate))
        print(json.dumps(results[-1]), flush=True)
    report(results, table(results), args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Every message that crosses a process boundary: versioned, msgpack, arrays as raw bytes.

A message is a frozen dataclass with `to_bytes()` and a `from_bytes()` class method. On the
wire it is one msgpack map: `{"v": SCHEMA, "type": <name>, ...fields}`; an array field is a map
`{"dtype", "shape", "data"}` whose dtype comes from an allow-list and whose byte count is
checked against its shape before anything is allocated. Nothing is ever unpickled.

A payload that is too large, truncated, of another schema version or of the wrong type raises
`MessageError`; the receiving process logs the reason, counts it and keeps running.

Frames carry uint8 images and the intrinsics of the (undistorted) image, so the stream is
self-describing. Poses are `T_wc` float64 (4, 4) (design.md section 2). Timestamps are the
dataset's seconds; `stamp_ns` is the sender's wall clock when it sent the message.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, TypeVar

import msgpack
import numpy as np

from dimslam.common.errors import DimslamError
from dimslam.common.geometry.camera import Camera

SCHEMA = 1
"""Major version of every message; it is also the `@v1` chunk of every key (transport.py)."""

MAX_MESSAGE_BYTES = 1 << 30
"""Largest payload any decoder accepts (a map snapshot of the paper preset is ~100 MB)."""

MAX_FRAME_PIXELS = 4096 * 4096
MAX_BATCH_FRAMES = 64
"""Most frames in one mapping batch (initialization sends `init_frames`, rounds `every`)."""

_DTYPES = {"uint8", "int64", "float32", "float64"}


class MessageError(DimslamError):
    """A payload that is not a valid message of the expected type and schema version."""


def now_ns() -> int:
    return time.time_ns()


def pack_array(a: np.ndarray) -> dict:
    """An array as a msgpack map; the dtype must be in the allow-list."""
    a = np.asarray(a)  # not ascontiguousarray: it turns a 0-d array into shape (1,)
    if a.dtype.name not in _DTYPES:
        raise ValueError(f"dtype {a.dtype} cannot be sent (allowed: {sorted(_DTYPES)})")
    return {"dtype": a.dtype.name, "shape": list(a.shape), "data": a.tobytes()}


def unpack_array(
    name: str, obj: Any, dtype: str | None = None, shape: tuple[int | None, ...] | None = None
) -> np.ndarray:
    """Decode an array map, checking dtype, shape and byte count before allocating.

    Args:
        name: field name, for the error message.
        obj: the decoded msgpack value.
        dtype: required dtype name (None: any allowed one).
        shape: required shape; None entries match any size.

    Returns:
        A writable array (a copy of the payload bytes).
    """
    if not isinstance(obj, Mapping) or set(obj) != {"dtype", "shape", "data"}:
        raise MessageError(f"{name}: not an array")
    kind, dims, data = obj["dtype"], obj["shape"], obj["data"]
    if not isinstance(kind, str) or kind not in _DTYPES or (dtype is not None and kind != dtype):
        raise MessageError(f"{name}: dtype {kind!r} not accepted (want {dtype or sorted(_DTYPES)})")
    if (
        not isinstance(dims, list)
        or len(dims) > 8
        or not all(isinstance(d, int) and not isinstance(d, bool) and 0 <= d for d in dims)
    ):
        raise MessageError(f"{name}: bad shape {dims!r}")
    if shape is not None and (
        len(dims) != len(shape)
        or any(w is not None and w != d for w, d in zip(shape, dims, strict=True))
    ):
        raise MessageError(f"{name}: shape {tuple(dims)} does not match {shape}")
    if not isinstance(data, bytes):
        raise MessageError(f"{name}: data is not bytes")
    count, extent = 1, 1
    for d in dims:
        count *= d
        extent *= max(d, 1)  # an empty array with absurd other dims must not reach numpy either
        if extent > MAX_MESSAGE_BYTES:
            raise MessageError(f"{name}: shape {tuple(dims)} too large")
    if count * np.dtype(kind).itemsize != len(data):
        raise MessageError(f"{name}: {len(data)} bytes for shape {tuple(dims)} {kind}")
    return np.frombuffer(data, dtype=kind).reshape(dims).copy()


RIGID_TOLERANCE = 1e-3
"""Largest entry of `R^T R - I` a pose's rotation may have: poses solved in float32 are
orthonormal to ~1e-6; a scaled or sheared matrix is not a camera pose, and a map fitted to
one is poisoned."""


def _pose(name: str, obj: Any) -> np.ndarray:
    T = unpack_array(name, obj, "float64", (4, 4))
    R = T[:3, :3]
    with np.errstate(over="ignore", invalid="ignore"):  # huge entries: inf, then refused
        rigid = (
            np.isfinite(T).all()
            and np.allclose(T[3], [0, 0, 0, 1])
            and np.abs(R.T @ R - np.eye(3)).max() <= RIGID_TOLERANCE
            and np.linalg.det(R) > 0
        )
    if not rigid:
        raise MessageError(f"{name}: not a finite rigid transform")
    return T


def _get(body: Mapping, key: str, kind: type | tuple[type, ...]) -> Any:
    if key not in body:
        raise MessageError(f"missing field {key!r}")
    value = body[key]
    if isinstance(value, bool) and bool not in (kind if isinstance(kind, tuple) else (kind,)):
        raise MessageError(f"field {key!r}: expected {kind}, got bool")
    if kind is float and isinstance(value, int):
        value = float(value)
    if not isinstance(value, kind):
        raise MessageError(f"field {key!r}: expected {kind}, got {type(value).__name__}")
    return value


def _count(body: Mapping, key: str) -> int:
    value = _get(body, key, int)
    if value < 0:
        raise MessageError(f"field {key!r}: negative")
    return value


def _finite(body: Mapping, key: str) -> float:
    value = _get(body, key, float)
    if not np.isfinite(value):
        raise MessageError(f"field {key!r}: not finite")
    return value


def _encode(type_name: str, body: dict) -> bytes:
    return msgpack.packb({"v": SCHEMA, "type": type_name, **body}, use_bin_type=True)


def _decode(payload: bytes | bytearray | memoryview) -> dict:
    """Check size, unpack, and check the schema version; returns the body."""
    max_bytes = MAX_MESSAGE_BYTES  # read at call time, like unpack_array does
    if len(payload) > max_bytes:
        raise MessageError(f"payload of {len(payload)} bytes exceeds the limit of {max_bytes}")
    try:
        body = msgpack.unpackb(
            bytes(payload),
            raw=False,
            strict_map_key=True,
            max_array_len=1 << 20,
            max_map_len=1 << 16,
            max_str_len=1 << 20,
        )
    except Exception as e:  # msgpack raises several unrelated types on corrupt input
        raise MessageError(f"not a msgpack message: {type(e).__name__}: {e}") from None
    if not isinstance(body, dict):
        raise MessageError("not a message map")
    version = body.get("v")
    if type(version) is not int or version != SCHEMA:
        raise MessageError(f"schema version {version!r}, this build speaks {SCHEMA}")
    if not isinstance(body.get("type"), str):
        raise MessageError("message without a type")
    return body


def message_type(payload: bytes) -> str:
    """The `type` of a payload (validated header only), to dispatch on a shared topic."""
    return _decode(payload)["type"]


def decode_or_end(payload: bytes, kind: type[M]) -> M | EndOfStream:
    """A `kind` message or the end of the stream; `MessageError` for anything else."""
    if message_type(payload) == EndOfStream.TYPE:
        return EndOfStream.from_bytes(payload)
    return kind.from_bytes(payload)


M = TypeVar("M", bound="Message")


class Message:
    """Base of every message: `to_bytes()` / `from_bytes()` around `_body` / `_parse`."""

    TYPE: ClassVar[str]

    def _body(self) -> dict:
        raise NotImplementedError

    @classmethod
    def _parse(cls: type[M], body: dict) -> M:
        raise NotImplementedError

    def to_bytes(self) -> bytes:
        return _encode(self.TYPE, self._body())

    @classmethod
    def from_bytes(cls: type[M], payload: bytes | bytearray | memoryview) -> M:
        """Decode and validate; raises `MessageError` on anything but a valid `cls`."""
        body = _decode(payload)
        if body["type"] != cls.TYPE:
            raise MessageError(f"expected a {cls.TYPE!r} message, got {body['type']!r}")
        try:
            return cls._parse(body)
        except MessageError:
            raise
        except (ValueError, TypeError, KeyError) as e:
            raise MessageError(f"{cls.TYPE}: {e}") from None


def _camera_body(camera: Camera) -> list:
    return [camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy]


def _camera(obj: Any) -> Camera:
    if not isinstance(obj, list) or len(obj) != 6:
        raise MessageError("camera: expected [width, height, fx, fy, cx, cy]")
    w, h, fx, fy, cx, cy = obj
    if not all(isinstance(v, int) and not isinstance(v, bool) for v in (w, h)):
        raise MessageError("camera: width and height must be integers")
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (fx, fy, cx, cy)):
        raise MessageError("camera: intrinsics must be numbers")
    if w * h > MAX_FRAME_PIXELS:
        raise MessageError(f"camera: {w}x{h} exceeds the frame size limit")
    try:
        return Camera(w, h, float(fx), float(fy), float(cx), float(cy))
    except ValueError as e:
        raise MessageError(f"camera: {e}") from None


def _image(name: str, obj: Any, camera: Camera) -> np.ndarray:
    return unpack_array(name, obj, "uint8", (camera.height, camera.width, 3))


@dataclass(frozen=True, eq=False)
class FrameMessage(Message):
    """One camera frame (camera -> tracker).

    Attributes:
        seq: position in the stream, from 0, consecutive.
        timestamp: the frame's own time, seconds.
        rgb: `(H, W, 3)` uint8, undistorted, matching `camera`.
        camera: intrinsics of this image.
        live: from a live source: a tracker that falls behind skips to the newest frame
            instead of working through stale ones.
        stamp_ns: sender wall clock.
    """

    TYPE: ClassVar[str] = "frame"
    seq: int
    timestamp: float
    rgb: np.ndarray
    camera: Camera
    live: bool = False
    stamp_ns: int = field(default_factory=now_ns)

    def _body(self) -> dict:
        return {
            "seq": self.seq,
            "timestamp": self.timestamp,
            "rgb": pack_array(self.rgb.astype(np.uint8, copy=False)),
            "camera": _camera_body(self.camera),
            "live": self.live,
            "stamp_ns": self.stamp_ns,
        }

    @classmethod
    def _parse(cls, body: dict) -> FrameMessage:
        camera = _camera(body.get("camera"))
        return cls(
            _count(body, "seq"),
            _finite(body, "timestamp"),
            _image("rgb", body.get("rgb"), camera),
            camera,
            _get(body, "live", bool),
            _count(body, "stamp_ns"),
        )


@dataclass(frozen=True)
class EndOfStream(Message):
    """The source has no more frames (camera -> tracker, tracker -> mapper).

    Attributes:
        frames: how many frames were sent in all (seq 0 .. frames-1).
    """

    TYPE: ClassVar[str] = "end"
    frames: int
    stamp_ns: int = field(default_factory=now_ns)

    def _body(self) -> dict:
        return {"frames": self.frames, "stamp_ns": self.stamp_ns}

    @classmethod
    def _parse(cls, body: dict) -> EndOfStream:
        return cls(_count(body, "frames"), _count(body, "stamp_ns"))


@dataclass(frozen=True, eq=False)
class PoseMessage(Message):
    """A solved camera pose (tracker -> anyone; mapper refinements are PoseMessages too), or
    the news that a frame is lost.

    Attributes:
        seq: the frame's position in the stream.
        timestamp: the frame's own time, seconds.
        T_wc: `(4, 4)` float64 camera-to-world; None when the frame is lost (no pose is
            invented for it).
        keyframe: whether the frame is a keyframe.
        map_version: version of the map snapshot it was tracked against (0: initialization).
        lost: the tracker could not place the frame (status "lost"); it is relocalizing.
    """

    TYPE: ClassVar[str] = "pose"
    seq: int
    timestamp: float
    T_wc: np.ndarray | None
    keyframe: bool = False
    map_version: int = 0
    stamp_ns: int = field(default_factory=now_ns)
    lost: bool = False

    def __post_init__(self) -> None:
        if self.lost != (self.T_wc is None):
            raise ValueError("a pose message has a pose exactly when the frame is not lost")

    @property
    def status(self) -> str:
        """ "lost" or "tracked"."""
        return "lost" if self.lost else "tracked"

    def supersedes(self, kept: PoseMessage | None) -> bool:
        """Whether this pose replaces `kept`, the one held for the same frame: refinements and
        tracked poses race on two topics, so the newer map decides, not the order of arrival;
        for one map the last received wins. A lost frame replaces nothing."""
        return not self.lost and (kept is None or self.map_version >= kept.map_version)

    def _body(self) -> dict:
        return {
            "seq": self.seq,
            "timestamp": self.timestamp,
            "T_wc": None if self.T_wc is None else pack_array(np.asarray(self.T_wc, np.float64)),
            "keyframe": self.keyframe,
            "map_version": self.map_version,
            "stamp_ns": self.stamp_ns,
            "lost": self.lost,
        }

    @classmethod
    def _parse(cls, body: dict) -> PoseMessage:
        lost = _get(body, "lost", bool)
        if lost and body.get("T_wc") is not None:
            raise MessageError("T_wc: a lost frame carries no pose")
        return cls(
            _count(body, "seq"),
            _finite(body, "timestamp"),
            None if lost else _pose("T_wc", body.get("T_wc")),
            _get(body, "keyframe", bool),
            _count(body, "map_version"),
            _count(body, "stamp_ns"),
            lost,
        )


@dataclass(frozen=True, eq=False)
class MappingFrame:
    """One frame as the mapper receives it: image, tracked pose, keyframe flag."""

    seq: int
    timestamp: float
    rgb: np.ndarray
    T_wc: np.ndarray
    keyframe: bool


@dataclass(frozen=True, eq=False)
class MappingBatch(Message):
    """The frames of one mapping round, or of the initialization (tracker -> mapper).

    Attributes:
        round: 0 for the initialization batch, then 1, 2, ... consecutively.
        frames: the frames since the previous batch, oldest first.
        camera: intrinsics of every image in the batch.
        live: the frames came from a live camera (the mapper keeps pace with it:
            `mapper.live_iters`).
    """

    TYPE: ClassVar[str] = "mapping"
    round: int
    frames: tuple[MappingFrame, ...]
    camera: Camera
    live: bool = False
    stamp_ns: int = field(default_factory=now_ns)

    def _body(self) -> dict:
        return {
            "round": self.round,
            "camera": _camera_body(self.camera),
            "frames": [
                {
                    "seq": f.seq,
                    "timestamp": f.timestamp,
                    "rgb": pack_array(f.rgb.astype(np.uint8, copy=False)),
                    "T_wc": pack_array(np.asarray(f.T_wc, dtype=np.float64)),
                    "keyframe": f.keyframe,
                }
                for f in self.frames
            ],
            "live": self.live,
            "stamp_ns": self.stamp_ns,
        }

    @classmethod
    def _parse(cls, body: dict) -> MappingBatch:
        camera = _camera(body.get("camera"))
        items = _get(body, "frames", list)
        if not 0 < len(items) <= MAX_BATCH_FRAMES:
            raise MessageError(f"frames: {len(items)} frames (1..{MAX_BATCH_FRAMES} allowed)")
        frames = []
        for i, item in enumerate(items):
            if not isinstance(item, dict):
                raise MessageError(f"frames[{i}]: not a map")
            frames.append(
                MappingFrame(
                    _count(item, "seq"),
                    _finite(item, "timestamp"),
                    _image(f"frames[{i}].rgb", item.get("rgb"), camera),
                    _pose(f"frames[{i}].T_wc", item.get("T_wc")),
                    _get(item, "keyframe", bool),
                )
            )
        return cls(
            _count(body, "round"),
            tuple(frames),
            camera,
            _get(body, "live", bool),
            _count(body, "stamp_ns"),
        )


@dataclass(frozen=True, eq=False)
class MapSnapshot(Message):
    """The map after a mapping round, with the poses that round refined (mapper -> tracker).

    Attributes:
        version: 1 after the initialization, +1 per round; newer replaces older.
        round: the mapping batch this snapshot answers.
        config: digest of the map and render settings; a tracker with other settings rejects it.
        state: the field's tensors by name (`Field.state_dict()` as numpy arrays): float32,
            and int64 for a sparse map's block coordinates.
        poses: `T_wc` by frame seq: every frame the mapper holds (the mapper service sends
            them all); a tracker takes them as they are.
        keyframes: seqs of every keyframe so far.
    """

    TYPE: ClassVar[str] = "map"
    version: int
    round: int
    config: str
    state: dict[str, np.ndarray]
    poses: dict[int, np.ndarray]
    keyframes: tuple[int, ...] = ()
    stamp_ns: int = field(default_factory=now_ns)

    def _body(self) -> dict:
        return {
            "version": self.version,
            "round": self.round,
            "config": self.config,
            "state": {k: pack_array(v) for k, v in self.state.items()},
            "poses": [[s, pack_array(np.asarray(T, np.float64))] for s, T in self.poses.items()],
            "keyframes": list(self.keyframes),
            "stamp_ns": self.stamp_ns,
        }

    @classmethod
    def _parse(cls, body: dict) -> MapSnapshot:
        state_obj = _get(body, "state", dict)
        state = {}
        for k, v in state_obj.items():
            if not isinstance(k, str):
                raise MessageError("state: non-string tensor name")
            state[k] = unpack_array(f"state[{k}]", v)
            if state[k].dtype not in (np.float32, np.int64):
                raise MessageError(
                    f"state[{k}]: dtype {state[k].dtype} not accepted (float32, or int64 for "
                    "the indices of a sparse map)"
                )
            if not np.isfinite(state[k]).all():  # one NaN spreads through every render
                raise MessageError(f"state[{k}]: not finite")
        poses = {}
        for i, item in enumerate(_get(body, "poses", list)):
            if (
                not isinstance(item, list)
                or len(item) != 2
                or type(item[0]) is not int
                or item[0] < 0
            ):
                raise MessageError(f"poses[{i}]: expected [seq, T_wc]")
            poses[item[0]] = _pose(f"poses[{i}]", item[1])
        keyframes = _get(body, "keyframes", list)
        if not all(isinstance(k, int) and not isinstance(k, bool) and k >= 0 for k in keyframes):
            raise MessageError("keyframes: expected frame numbers")
        return cls(
            _count(body, "version"),
            _count(body, "round"),
            _get(body, "config", str),
            state,
            poses,
            tuple(keyframes),
            _count(body, "stamp_ns"),
        )


@dataclass(frozen=True, eq=False)
class MapperCheckpoint(Message):
    """A mapper's state on disk, to resume from (`dimslam-mapper --checkpoint/--resume`).

    Attributes:
        snapshot: the map, the final pose of every frame held (keyframes as refined, others
            re-anchored to their keyframe), and the keyframe numbers.
        frames: `(seq, timestamp)` of every frame held, oldest first.
        images: the frames that still hold their image, in batches of at most
            `MAX_BATCH_FRAMES` (their poses and keyframe flags as the mapper holds them).
        rounds: mapping rounds run so far.
    """

    TYPE: ClassVar[str] = "checkpoint"
    snapshot: MapSnapshot
    frames: tuple[tuple[int, float], ...]
    images: tuple[MappingBatch, ...]
    rounds: int
    stamp_ns: int = field(default_factory=now_ns)

    def _body(self) -> dict:
        return {
            "snapshot": self.snapshot.to_bytes(),
            "frames": [[seq, ts] for seq, ts in self.frames],
            "images": [b.to_bytes() for b in self.images],
            "rounds": self.rounds,
            "stamp_ns": self.stamp_ns,
        }

    @classmethod
    def _parse(cls, body: dict) -> MapperCheckpoint:
        snapshot = MapSnapshot.from_bytes(_get(body, "snapshot", bytes))
        frames = []
        for i, item in enumerate(_get(body, "frames", list)):
            if not (isinstance(item, list) and len(item) == 2):
                raise MessageError(f"frames[{i}]: expected [seq, timestamp]")
            seq, ts = item
            if type(seq) is not int or seq < 0 or type(ts) is not float or not np.isfinite(ts):
                raise MessageError(f"frames[{i}]: expected [seq, timestamp]")
            if seq not in snapshot.poses:
                raise MessageError(f"frames[{i}]: frame {seq} has no pose in the snapshot")
            frames.append((seq, ts))
        images = tuple(MappingBatch.from_bytes(b) for b in _get(body, "images", list))
        cameras = {b.camera for b in images}
        if len(cameras) > 1:
            raise MessageError("images: batches of different cameras")
        return cls(
            snapshot, tuple(frames), images, _count(body, "rounds"), _count(body, "stamp_ns")
        )

"""Messages: round trips, schema version and type checks, the array codec, and fuzzed input.

The property tests feed random bytes, every prefix of valid encodings and valid messages with
one field replaced by an arbitrary msgpack value to every decoder: a receiver must only ever see
`MessageError`, whatever arrives on the wire.

About 520 lines: one test module per message module; its length is the list of hostile inputs.
"""

import dataclasses
import pickle

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dimslam.common.errors import DimslamError
from dimslam.common.geometry.camera import Camera
from dimslam.common.net import messages
from dimslam.common.net.messages import (
    EndOfStream,
    FrameMessage,
    MapperCheckpoint,
    MappingBatch,
    MappingFrame,
    MapSnapshot,
    MessageError,
    PoseMessage,
    message_type,
    pack_array,
    unpack_array,
)

CAM = Camera(6, 4, 5.0, 5.5, 2.5, 1.5)
FUZZ = settings(
    max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow], database=None
)
DECODERS = {
    "frame": FrameMessage.from_bytes,
    "end": EndOfStream.from_bytes,
    "pose": PoseMessage.from_bytes,
    "mapping": MappingBatch.from_bytes,
    "map": MapSnapshot.from_bytes,
    "checkpoint": MapperCheckpoint.from_bytes,
    "message_type": message_type,
}


def _rgb(seed: int, camera: Camera = CAM) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.integers(0, 256, (camera.height, camera.width, 3), dtype=np.uint8)


def _T(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    T = np.eye(4)
    T[:3, :3] = q
    T[:3, 3] = rng.normal(size=3)
    return T


def _examples() -> list[messages.Message]:
    """One small valid message of every type (small so that every prefix can be tried)."""
    rng = np.random.default_rng(1)
    batch = MappingBatch(
        1,
        tuple(MappingFrame(s, 0.1 * s, _rgb(s), _T(s), s % 2 == 0) for s in (5, 6)),
        CAM,
        stamp_ns=1,
    )
    snapshot = MapSnapshot(
        2,
        1,
        "abc123",
        {
            "grid.0": rng.normal(size=(2, 3, 4)).astype(np.float32),
            "decoder.weight": rng.normal(size=(5,)).astype(np.float32),
        },
        {0: _T(0), 5: _T(5)},
        (0, 5),
        stamp_ns=2,
    )
    return [
        FrameMessage(3, 12.5, _rgb(0), CAM, live=True, stamp_ns=123),
        EndOfStream(17, stamp_ns=456),
        PoseMessage(4, 1.25, _T(0), keyframe=True, map_version=2, stamp_ns=789),
        batch,
        snapshot,
        PoseMessage(5, 1.5, None, map_version=2, stamp_ns=790, lost=True),
        MapperCheckpoint(snapshot, ((0, 0.0), (5, 0.5)), (batch,), 3, stamp_ns=3),
    ]


def _assert_same(a, b, where: str = "message") -> None:
    """Field-by-field equality; arrays must match in dtype, shape and values."""
    if isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray), where
        assert a.dtype == b.dtype and a.shape == b.shape, where
        np.testing.assert_array_equal(a, b, err_msg=where)
    elif dataclasses.is_dataclass(a) and not isinstance(a, Camera):
        assert type(a) is type(b), where
        for f in dataclasses.fields(a):
            _assert_same(getattr(a, f.name), getattr(b, f.name), f"{where}.{f.name}")
    elif isinstance(a, dict):
        assert isinstance(b, dict) and list(a) == list(b), where
        for k in a:
            _assert_same(a[k], b[k], f"{where}[{k!r}]")
    elif isinstance(a, tuple):
        assert isinstance(b, tuple) and len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _assert_same(x, y, f"{where}[{i}]")
    else:
        assert type(a) is type(b) and a == b, where


def _decode_everywhere(payload: bytes) -> None:
    """Every decoder either accepts `payload` or raises MessageError; nothing else escapes."""
    for name, decode in DECODERS.items():
        try:
            result = decode(payload)
        except MessageError:
            continue
        if name == "message_type":
            assert isinstance(result, str)
        else:
            assert result.TYPE == name


def _body(msg: messages.Message) -> dict:
    return msgpack.unpackb(msg.to_bytes(), raw=False)


def _pack(body: dict) -> bytes:
    return msgpack.packb(body, use_bin_type=True)


# -- round trips -----------------------------------------------------------------------------


@pytest.mark.parametrize("msg", _examples(), ids=lambda m: m.TYPE)
def test_round_trip_keeps_every_field(msg):
    payload = msg.to_bytes()
    assert isinstance(payload, bytes)
    assert message_type(payload) == msg.TYPE
    back = type(msg).from_bytes(payload)
    _assert_same(msg, back)
    # What zenoh hands over may be a bytearray or a memoryview.
    _assert_same(msg, type(msg).from_bytes(memoryview(bytearray(payload))))


def test_decoded_arrays_are_writable_copies():
    msg = _examples()[0]
    back = FrameMessage.from_bytes(msg.to_bytes())
    # unpack_array promises a writable copy, not a read-only view of the payload.
    back.rgb[0, 0, 0] ^= 1
    assert back.rgb[0, 0, 0] != msg.rgb[0, 0, 0]


def test_map_snapshot_round_trip_with_several_tensors_and_poses():
    rng = np.random.default_rng(7)
    state = {f"planes.{i}": rng.normal(size=(3, 8, 8 + i)).astype(np.float32) for i in range(3)} | {
        "mlp.bias": np.array([], dtype=np.float32),
        "scale": np.array(2.0, np.float32),
    }
    poses = {s: _T(s) for s in (0, 10, 20, 25)}
    snap = MapSnapshot(9, 8, "cfg-digest", state, poses, (0, 10, 20), stamp_ns=5)
    back = MapSnapshot.from_bytes(snap.to_bytes())
    _assert_same(snap, back)
    assert list(back.poses) == [0, 10, 20, 25] and back.keyframes == (0, 10, 20)


def test_mapping_batch_round_trip_with_several_frames():
    frames = tuple(MappingFrame(s, s / 30, _rgb(s), _T(s), s in (10, 13)) for s in range(10, 15))
    batch = MappingBatch(4, frames, CAM, stamp_ns=99)
    back = MappingBatch.from_bytes(batch.to_bytes())
    _assert_same(batch, back)
    assert [f.seq for f in back.frames] == list(range(10, 15))
    assert back.camera == CAM


def test_defaults_stamp_the_send_time():
    assert EndOfStream(3).stamp_ns > 0 and PoseMessage(0, 0.0, np.eye(4)).stamp_ns > 0


# -- version and type ------------------------------------------------------------------------


@pytest.mark.parametrize("msg", _examples(), ids=lambda m: m.TYPE)
def test_other_schema_version_is_rejected_naming_it(msg):
    body = _body(msg) | {"v": 2}
    payload = _pack(body)
    with pytest.raises(MessageError, match=r"schema version 2\b"):
        type(msg).from_bytes(payload)
    with pytest.raises(MessageError, match=r"schema version 2\b"):
        message_type(payload)


def test_missing_version_or_type_is_rejected():
    body = _body(EndOfStream(1))
    with pytest.raises(MessageError, match="schema version None"):
        EndOfStream.from_bytes(_pack({k: v for k, v in body.items() if k != "v"}))
    with pytest.raises(MessageError, match="without a type"):
        message_type(_pack({k: v for k, v in body.items() if k != "type"}))


def test_message_of_another_type_is_rejected():
    frame = _examples()[0].to_bytes()
    with pytest.raises(MessageError, match="expected a 'pose' message, got 'frame'"):
        PoseMessage.from_bytes(frame)
    for name, decode in DECODERS.items():
        if name not in ("frame", "message_type"):
            with pytest.raises(MessageError):
                decode(frame)


def test_message_error_is_a_dimslam_error():
    # Entry points catch DimslamError and report it without a traceback.
    assert issubclass(MessageError, DimslamError)


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("seq", -1, "negative"),
        ("seq", True, "got bool"),
        ("seq", "3", "expected"),
        ("timestamp", float("nan"), "not finite"),
        ("live", 1, "expected"),
        ("camera", [6, 4, 5.0], "camera"),
        ("camera", [6, 4, -5.0, 5.0, 2.5, 1.5], "camera"),
        ("camera", [4097, 4096, 5.0, 5.0, 2.5, 1.5], "frame size limit"),
    ],
)
def test_frame_field_checks(field, value, match):
    body = _body(_examples()[0]) | {field: value}
    with pytest.raises(MessageError, match=match):
        FrameMessage.from_bytes(_pack(body))


def test_missing_field_is_rejected():
    body = _body(_examples()[2])
    del body["map_version"]
    with pytest.raises(MessageError, match="missing field 'map_version'"):
        PoseMessage.from_bytes(_pack(body))


def test_mapping_batch_frame_count_is_bounded():
    body = _body(_examples()[3])
    with pytest.raises(MessageError, match="0 frames"):
        MappingBatch.from_bytes(_pack(body | {"frames": []}))
    many = body["frames"][:1] * (messages.MAX_BATCH_FRAMES + 1)
    with pytest.raises(MessageError, match=f"{messages.MAX_BATCH_FRAMES + 1} frames"):
        MappingBatch.from_bytes(_pack(body | {"frames": many}))


# -- array codec -----------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", ["object", "<U5", "float16", "int32", "O", "V8"])
def test_dtype_outside_the_allow_list_is_rejected(dtype):
    obj = {"dtype": dtype, "shape": [1], "data": b"\0" * 8}
    with pytest.raises(MessageError, match="not accepted"):
        unpack_array("x", obj)


@pytest.mark.parametrize("dtype", [["float32"], {"a": 1}, None, 4])
def test_dtype_of_the_wrong_kind_is_rejected(dtype):
    with pytest.raises(MessageError):
        unpack_array("x", {"dtype": dtype, "shape": [1], "data": b"\0" * 4})


def test_sender_refuses_dtypes_outside_the_allow_list():
    with pytest.raises(ValueError, match="cannot be sent"):
        pack_array(np.array(["abcde"]))
    with pytest.raises(ValueError, match="cannot be sent"):
        pack_array(np.array([object()], dtype=object))


def test_required_dtype_and_shape_are_enforced():
    a = pack_array(np.zeros((3, 3), np.float64))
    with pytest.raises(MessageError, match="not accepted"):
        unpack_array("T", a, "float32")
    with pytest.raises(MessageError, match="does not match"):
        unpack_array("T", a, "float64", (4, 4))
    with pytest.raises(MessageError, match="does not match"):
        unpack_array("T", a, "float64", (3, 3, 1))
    assert unpack_array("T", a, "float64", (None, 3)).shape == (3, 3)


def test_byte_count_must_match_the_shape():
    a = pack_array(np.zeros((2, 3), np.float32))
    for data in (a["data"][:-1], a["data"] + b"\0", b""):
        with pytest.raises(MessageError, match="bytes for shape"):
            unpack_array("x", a | {"data": data})
    with pytest.raises(MessageError, match="bytes for shape"):
        unpack_array("x", a | {"shape": [3, 3]})


def test_huge_declared_shape_is_rejected_before_allocating():
    # 2**80 elements: any attempt to allocate (or even to reshape) would fail differently.
    for dims in ([2**40, 2**40], [2**31, 2**31, 1], [2**64 - 1]):
        with pytest.raises(MessageError, match="too large"):
            unpack_array("x", {"dtype": "uint8", "shape": dims, "data": b""})
    # An empty array whose other dimensions are absurd must not reach numpy either.
    for dims in ([0, 2**63], [0, 2**64 - 1], [0, 2**31, 2**31]):
        with pytest.raises(MessageError):
            unpack_array("x", {"dtype": "float32", "shape": dims, "data": b""})


@pytest.mark.parametrize(
    "dims", [[-1, 4], [2, -2], [1.0, 4], [True, 4], "4", [[4]], list(range(9))]
)
def test_bad_shape_is_rejected(dims):
    with pytest.raises(MessageError, match="bad shape"):
        unpack_array("x", {"dtype": "uint8", "shape": dims, "data": b"\0" * 4})


@pytest.mark.parametrize(
    "obj",
    [
        None,
        [1, 2],
        b"raw",
        {"dtype": "uint8", "shape": [1]},
        {"dtype": "uint8", "shape": [1], "data": b"\0", "x": 1},
    ],
)
def test_not_an_array_is_rejected(obj):
    with pytest.raises(MessageError, match="not an array"):
        unpack_array("x", obj)


def test_array_data_must_be_bytes():
    with pytest.raises(MessageError, match="not bytes"):
        unpack_array("x", {"dtype": "uint8", "shape": [1], "data": "a"})


@pytest.mark.parametrize("bad", ["nan", "inf", "row", "scaled", "sheared", "reflected"])
def test_pose_must_be_a_finite_rigid_transform(bad):
    T = _T(3)
    if bad == "nan":
        T[0, 3] = np.nan
    elif bad == "inf":
        T[1, 1] = np.inf
    elif bad == "row":
        T[3] = [0, 0, 1, 1]
    elif bad == "scaled":  # a map fitted to it would be poisoned (benchmarks/fuzz.py)
        T[:3, :3] *= 1.01
    elif bad == "sheared":
        T[:3, :3] = T[:3, :3] @ np.array([[1, 0.01, 0], [0, 1, 0], [0, 0, 1]])
    else:
        T[:3, :3] = T[:3, :3] @ np.diag([1.0, 1.0, -1.0]) * np.sign(np.linalg.det(T[:3, :3]))
    with pytest.raises(MessageError, match="not a finite rigid transform"):
        PoseMessage.from_bytes(PoseMessage(0, 0.0, T).to_bytes())
    frames = (MappingFrame(0, 0.0, _rgb(0), T, True),)
    with pytest.raises(MessageError, match=r"frames\[0\]\.T_wc"):
        MappingBatch.from_bytes(MappingBatch(0, frames, CAM).to_bytes())
    with pytest.raises(MessageError, match=r"poses\[0\]"):
        MapSnapshot.from_bytes(MapSnapshot(1, 0, "c", {}, {0: T}).to_bytes())


def test_a_lost_frame_carries_a_status_and_no_pose():
    lost = PoseMessage.from_bytes(PoseMessage(7, 2.0, None, lost=True).to_bytes())
    assert lost.status == "lost" and lost.T_wc is None and lost.seq == 7
    assert PoseMessage(7, 2.0, np.eye(4)).status == "tracked"
    body = _body(_examples()[2])
    with pytest.raises(MessageError, match="a lost frame carries no pose"):
        PoseMessage.from_bytes(_pack(body | {"lost": True}))
    with pytest.raises(MessageError, match="T_wc"):  # tracked, so the pose must be there
        PoseMessage.from_bytes(_pack(body | {"T_wc": None}))
    with pytest.raises(ValueError, match="exactly when"):
        PoseMessage(7, 2.0, np.eye(4), lost=True)


def test_pose_must_be_4x4_float64():
    body = _body(_examples()[2])
    for T in (np.eye(4, dtype=np.float32), np.eye(3)):
        with pytest.raises(MessageError, match="T_wc"):
            PoseMessage.from_bytes(_pack(body | {"T_wc": pack_array(T)}))


def test_image_must_match_the_camera():
    other = Camera(5, 4, 5.0, 5.0, 2.0, 1.5)
    with pytest.raises(MessageError, match="rgb"):
        FrameMessage.from_bytes(FrameMessage(0, 0.0, _rgb(0), other).to_bytes())
    gray = _rgb(0)[..., :1]
    with pytest.raises(MessageError, match="rgb"):
        FrameMessage.from_bytes(FrameMessage(0, 0.0, gray, CAM).to_bytes())
    frames = (MappingFrame(0, 0.0, _rgb(0, other), _T(0), True),)
    with pytest.raises(MessageError, match=r"frames\[0\]\.rgb"):
        MappingBatch.from_bytes(MappingBatch(0, frames, CAM).to_bytes())
    body = _body(_examples()[0])
    body["rgb"] = pack_array(_rgb(0).astype(np.float32))
    with pytest.raises(MessageError, match="not accepted"):
        FrameMessage.from_bytes(_pack(body))


def test_snapshot_tensors_must_be_float32():
    snap = MapSnapshot(1, 0, "c", {"w": np.zeros(3, np.float64)}, {})
    with pytest.raises(MessageError, match=r"state\[w\]"):
        MapSnapshot.from_bytes(snap.to_bytes())


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
def test_snapshot_tensors_must_be_finite(value):
    w = np.zeros(3, np.float32)
    w[1] = value
    with pytest.raises(MessageError, match=r"state\[w\]: not finite"):
        MapSnapshot.from_bytes(MapSnapshot(1, 0, "c", {"w": w}, {}).to_bytes())


def test_poses_solved_in_float32_are_rigid_enough():
    T = _T(4).astype(np.float32).astype(np.float64)
    assert np.array_equal(PoseMessage.from_bytes(PoseMessage(0, 0.0, T).to_bytes()).T_wc, T)


def test_oversized_payload_is_rejected(monkeypatch):
    payload = _examples()[0].to_bytes()
    monkeypatch.setattr(messages, "MAX_MESSAGE_BYTES", len(payload) - 1)
    for decode in DECODERS.values():
        with pytest.raises(MessageError, match="exceeds the limit"):
            decode(payload)
    monkeypatch.setattr(messages, "MAX_MESSAGE_BYTES", len(payload))
    FrameMessage.from_bytes(payload)


# -- no pickle, ever -------------------------------------------------------------------------

_UNPICKLED: list[str] = []


def _record(what: str) -> str:
    _UNPICKLED.append(what)
    return what


class _Payload:
    """Runs `_record` when unpickled: proof that a decoder called pickle."""

    def __reduce__(self):
        return _record, ("pickle ran",)


def test_decoding_never_unpickles(monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("pickle used while decoding a message")

    evil = pickle.dumps(_Payload())
    monkeypatch.setattr(pickle, "loads", refuse)
    monkeypatch.setattr(pickle, "load", refuse)
    body = _body(_examples()[0])
    # An ext type anywhere, a numpy object array, a msgpack-numpy style map, bare pickle bytes.
    ext = msgpack.ExtType(42, evil)
    candidates = [
        _pack(body | {"rgb": ext}),
        _pack(body | {"seq": ext}),
        _pack(body | {"camera": [ext] * 6}),
        _pack(ext),
        _pack(body | {"rgb": {"dtype": "object", "shape": [1], "data": evil}}),
        _pack(body | {"rgb": {"nd": True, "type": "|O", "kind": "O", "shape": [1], "data": evil}}),
        evil,
    ]
    for payload in candidates:
        _decode_everywhere(payload)  # message_type reads the header only and may accept it
        with pytest.raises(MessageError):
            FrameMessage.from_bytes(payload)
    assert _UNPICKLED == []


# -- property tests --------------------------------------------------------------------------

_scalars = (
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**64 - 1)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=8)
    | st.binary(max_size=40)
)
_values = st.recursive(
    _scalars,
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4)
    ),
    max_leaves=12,
)
_array_like = st.fixed_dictionaries(
    {
        "dtype": st.sampled_from(["uint8", "int64", "float32", "float64", "object", "<U5"])
        | _values,
        "shape": st.lists(st.integers(-2, 2**64 - 1) | st.sampled_from([0, 1, 3, 4, 6]), max_size=4)
        | _values,
        "data": st.binary(max_size=300) | _values,
    }
)


@FUZZ
@given(st.binary(max_size=400))
def test_random_bytes_only_raise_message_error(payload):
    _decode_everywhere(payload)


@FUZZ
@given(st.sampled_from(_examples()), st.data())
def test_truncated_encodings_only_raise_message_error(msg, data):
    payload = msg.to_bytes()
    cut = data.draw(st.integers(0, len(payload) - 1))
    _decode_everywhere(payload[:cut])
    with pytest.raises(MessageError):
        type(msg).from_bytes(payload[:cut])


@pytest.mark.parametrize("msg", _examples(), ids=lambda m: m.TYPE)
def test_every_prefix_of_a_valid_encoding_is_rejected(msg):
    payload = msg.to_bytes()
    for cut in range(len(payload)):
        for decode in DECODERS.values():
            with pytest.raises(MessageError):
                decode(payload[:cut])


@FUZZ
@given(st.sampled_from(_examples()), st.data())
def test_one_corrupted_field_only_raises_message_error(msg, data):
    """A well-formed msgpack map of the right type and version with one field replaced."""
    body = _body(msg)
    key = data.draw(st.sampled_from(sorted(body)), label="field")
    action = data.draw(st.sampled_from(["value", "array", "delete"]), label="action")
    if action == "delete":
        del body[key]
    else:
        body[key] = data.draw(_array_like if action == "array" else _values, label="value")
    _decode_everywhere(_pack(body))


@FUZZ
@given(st.data())
def test_corrupted_nested_arrays_only_raise_message_error(data):
    """Corrupt the array maps deep inside frames, batches and snapshots."""
    msg = data.draw(
        st.sampled_from([m for m in _examples() if m.TYPE in ("frame", "mapping", "map")])
    )
    body = _body(msg)
    if msg.TYPE == "frame":
        target = body["rgb"]
    elif msg.TYPE == "mapping":
        frame = data.draw(st.sampled_from(body["frames"]))
        target = frame[data.draw(st.sampled_from(["rgb", "T_wc"]))]
    else:
        target = data.draw(
            st.sampled_from([*body["state"].values(), *(p[1] for p in body["poses"])])
        )
    part = data.draw(st.sampled_from(["dtype", "shape", "data"]))
    target[part] = data.draw(_array_like)[part]
    _decode_everywhere(_pack(body))


def test_a_checkpoint_names_only_frames_its_snapshot_has_a_pose_for():
    example = _examples()[-1]
    orphan = MapperCheckpoint(example.snapshot, ((0, 0.0), (7, 0.7)), example.images, 3)
    with pytest.raises(MessageError, match="frame 7 has no pose"):
        MapperCheckpoint.from_bytes(orphan.to_bytes())

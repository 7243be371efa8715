"""Transport: key names, zenoh configs, inboxes, liveliness and shutdown.

Sessions are real zenoh peers on `tcp/127.0.0.1:<free port>` with scouting off. Tests wait on
a matching listener, a liveliness token or an event set from a callback, always with a bounded
timeout, never on sleep; every session is closed in a `with` block so nothing hangs at exit.
"""

import json
import os
import signal
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path

import numpy as np
import pytest
import zenoh
from hypothesis import given, settings
from hypothesis import strategies as st

from dimslam.common.errors import DimslamError
from dimslam.common.geometry.camera import Camera
from dimslam.common.map.mesh import EmptyMeshError
from dimslam.common.net import transport
from dimslam.common.net.launch import _listen_ports, loopback_endpoints
from dimslam.common.net.messages import SCHEMA, FrameMessage, MessageError
from dimslam.common.net.transport import (
    MAPPER_PORT,
    TRACKER_PORT,
    Inbox,
    Keys,
    Presence,
    Queries,
    Rejects,
    Stop,
    TransportConfig,
    open_session,
    publisher,
    zenoh_config,
)

pytestmark = pytest.mark.integration

WAIT = 60.0
"""Upper bound for anything that should happen within milliseconds on loopback (generous: a
loaded machine may not schedule the receiving thread for seconds)."""


def _json(conf: zenoh.Config, key: str):
    return json.loads(conf.get_json(key))


@pytest.fixture(scope="module")
def listen_only(tmp_path_factory) -> Path:
    """A zenoh config file for a peer that connects nowhere (the defaults always connect)."""
    path = tmp_path_factory.mktemp("zenoh") / "listen_only.json5"
    path.write_text('{ mode: "peer", scouting: { multicast: { enabled: false } } }')
    return path


@contextmanager
def _peers(listen_only: Path) -> Iterator[tuple[zenoh.Session, zenoh.Session, Keys]]:
    """Two sessions of one fresh dimslam session: `a` (from a config file) listens on a free
    port, `b` (one-host defaults) connects to it and listens on another free port, so neither
    touches the default ports 7451/7452. `a` is up first, so `b` connects without retrying."""
    name = f"test-{uuid.uuid4().hex[:8]}"
    a_ep, b_ep = loopback_endpoints(2)
    a_cfg = TransportConfig(name, listen=(a_ep,), zenoh_config=listen_only)
    b_cfg = TransportConfig(name, connect=(a_ep,), listen=(b_ep,))
    with open_session(a_cfg, "tracker") as a, open_session(b_cfg, "mapper") as b:
        yield a, b, Keys(name)


# -- keys and configuration ------------------------------------------------------------------


def test_listening_ports_are_distinct_and_below_the_outgoing_connections_range():
    """A port from the range the system gives outgoing connections could be taken by one
    before the process that is to listen on it starts (a `make demo` failed so)."""
    ports = [int(ep.rsplit(":", 1)[1]) for ep in loopback_endpoints(8)]
    assert len(set(ports)) == 8
    lo, hi = _listen_ports()
    assert all(lo <= p < hi for p in ports)
    outgoing = Path("/proc/sys/net/ipv4/ip_local_port_range")
    if outgoing.is_file():
        assert hi <= int(outgoing.read_text().split()[0])


def test_keys_are_namespaced_by_session_and_schema():
    keys = Keys("lab-2.run_1")
    root = f"dimslam/lab-2.run_1/@v{SCHEMA}"
    for topic in ("frames", "poses", "mapping", "map", "keyframes"):
        assert getattr(keys, topic) == f"{root}/{topic}"
    assert keys.query("map") == f"{root}/query/map"
    assert keys.alive("tracker") == f"{root}/alive/tracker"
    assert keys.alive() == f"{root}/alive/*"
    with pytest.raises(AttributeError):
        keys.frame  # noqa: B018 - a typo must fail, not build a key
    # The verbatim @v1 chunk keeps other major versions' wildcards off our keys (zenoh trap 11).
    assert not zenoh.KeyExpr("dimslam/**").intersects(zenoh.KeyExpr(keys.frames))
    assert zenoh.KeyExpr(keys.alive()).intersects(zenoh.KeyExpr(keys.alive("mapper")))
    assert not zenoh.KeyExpr(keys.alive()).intersects(zenoh.KeyExpr(Keys("other").alive("x")))


@settings(max_examples=50, deadline=None, database=None)
@given(st.from_regex(r"[A-Za-z0-9_.-]{1,20}", fullmatch=True))
def test_every_accepted_session_name_makes_valid_keys(name):
    keys = Keys(TransportConfig(name).session)
    for key in (keys.frames, keys.map, keys.query("mesh"), keys.alive("tracker"), keys.alive()):
        zenoh.KeyExpr(key)  # raises on an invalid key expression


@pytest.mark.parametrize("name", ["", "a/b", "a b", "*", "**", "a$b", "x#", "ümlaut", "abc\n"])
def test_invalid_session_names_are_rejected(name):
    with pytest.raises(DimslamError, match="--session"):
        TransportConfig(session=name)


@pytest.mark.parametrize(
    ("role", "listen", "connect"),
    [("tracker", TRACKER_PORT, MAPPER_PORT), ("mapper", MAPPER_PORT, TRACKER_PORT)],
)
def test_default_config_is_a_one_host_peer(role, listen, connect):
    conf = zenoh_config(TransportConfig(), role)
    assert _json(conf, "mode") == "peer"
    assert _json(conf, "scouting/multicast/enabled") is False
    assert _json(conf, "listen/endpoints") == [f"tcp/127.0.0.1:{listen}"]
    assert _json(conf, "connect/endpoints") == [f"tcp/127.0.0.1:{connect}"]


def test_a_role_that_listens_nowhere_connects_to_both():
    conf = zenoh_config(TransportConfig(), "camera")
    assert sorted(_json(conf, "connect/endpoints")) == [
        f"tcp/127.0.0.1:{TRACKER_PORT}",
        f"tcp/127.0.0.1:{MAPPER_PORT}",
    ]


def test_explicit_endpoints_replace_the_defaults():
    cfg = TransportConfig(
        connect=("tcp/10.0.0.2:9000", "tcp/10.0.0.3:9000"), listen=("tcp/0.0.0.0:9001",)
    )
    conf = zenoh_config(cfg, "tracker")
    assert _json(conf, "listen/endpoints") == ["tcp/0.0.0.0:9001"]
    assert _json(conf, "connect/endpoints") == ["tcp/10.0.0.2:9000", "tcp/10.0.0.3:9000"]
    assert _json(conf, "mode") == "peer"


def test_config_file_is_used_and_endpoints_override_it(tmp_path):
    path = tmp_path / "zenoh.json5"
    path.write_text(
        '{ mode: "client", connect: { endpoints: ["tcp/192.168.1.5:7447"] },'
        " scouting: { multicast: { enabled: false } } }"
    )
    conf = zenoh_config(TransportConfig(zenoh_config=path), "mapper")
    assert _json(conf, "mode") == "client"
    assert _json(conf, "connect/endpoints") == ["tcp/192.168.1.5:7447"]
    conf = zenoh_config(TransportConfig(zenoh_config=path, connect=("tcp/10.1.1.1:1",)), "mapper")
    assert _json(conf, "connect/endpoints") == ["tcp/10.1.1.1:1"]
    assert _json(conf, "mode") == "client"


@pytest.mark.parametrize("content", [None, "{ mode: ", '{ mode: "teapot" }'])
def test_bad_config_file_is_a_user_error(tmp_path, content):
    path = tmp_path / "zenoh.json5"
    if content is not None:
        path.write_text(content)
    with pytest.raises(DimslamError, match="--zenoh-config"):
        zenoh_config(TransportConfig(zenoh_config=path), "tracker")


def test_unusable_endpoint_is_a_user_error():
    cfg = TransportConfig(f"test-{uuid.uuid4().hex[:8]}", listen=("tcp/127.0.0.1:99999",))
    with pytest.raises(DimslamError, match="cannot open the zenoh session"):
        open_session(cfg, "tracker")


# -- inbox, rejects --------------------------------------------------------------------------


def test_inbox_drops_the_oldest_when_full():
    inbox = Inbox(3, "frames")
    for i in range(5):
        inbox.put(bytes([i]))
    assert inbox.dropped == 2 and len(inbox) == 3
    assert inbox.get(timeout=0) == b"\x02"
    assert inbox.drain() == [b"\x03", b"\x04"]
    assert len(inbox) == 0


def test_inbox_of_one_keeps_the_newest():
    inbox = Inbox(1, "map")
    for i in range(4):
        inbox.put(bytes([i]))
    assert inbox.dropped == 3 and inbox.drain() == [b"\x03"]


def test_empty_inbox_get_times_out_with_none():
    inbox = Inbox(2, "poses")
    start = time.monotonic()
    assert inbox.get(timeout=0.05) is None
    assert time.monotonic() - start >= 0.04


def test_rejects_counts_and_logs(caplog):
    rejects = Rejects()
    rejects("frames", MessageError("bad"))
    rejects("frames", MessageError("worse"))
    assert rejects.count == 2
    assert "worse" in caplog.text


def test_rejects_log_each_kind_once_per_topic_then_a_sum_now_and_then(caplog, monkeypatch):
    clock = [1000.0]
    monkeypatch.setattr(transport.time, "monotonic", lambda: clock[0])
    rejects = Rejects()
    for i in range(1000):  # one kind: the reason up to ':' with the numbers left out
        rejects("frames", MessageError(f"frame {i}: not after frame {i + 1}"))
        rejects("map", MessageError(f"frame {i}: not after frame {i + 1}"))
    assert rejects.count == 2000 and len(caplog.records) == 2
    for i in range(100):  # many kinds: only the first REJECT_KINDS get a line of their own
        rejects("frames", MessageError(f"field 'f{chr(65 + i % 26)}{i // 26}': bad"))
    assert len(caplog.records) == 2 + transport.REJECT_KINDS - 1
    clock[0] += transport.REJECT_LOG_S
    rejects("frames", MessageError("frame 1: not after frame 2"))
    assert len(caplog.records) == 2 + transport.REJECT_KINDS
    unlogged = 999 + (100 - (transport.REJECT_KINDS - 1)) + 1
    assert f"rejected {unlogged} more messages on frames" in caplog.records[-1].getMessage()


def test_inbox_queues_what_admit_returns_and_logs_drops_sparsely(caplog):
    inbox = Inbox(2, "frames", lambda p: None if p == b"bad" else p.decode())

    class Sample:  # a zenoh sample's payload, as the callback reads it
        def __init__(self, data: bytes) -> None:
            self.payload = zenoh.ZBytes(data)

    for data in (b"bad", b"a", b"bad", b"b"):
        inbox.callback(Sample(data))
    assert inbox.drain() == ["a", "b"]
    for i in range(100):
        inbox.put(i)
    assert inbox.dropped == 98
    assert len([r for r in caplog.records if "queue full" in r.getMessage()]) == 7  # 1 2 4 .. 64


# -- through zenoh ---------------------------------------------------------------------------


def test_frame_travels_from_publisher_to_inbox(listen_only):
    cam = Camera(8, 6, 7.0, 7.0, 3.5, 2.5)
    rgb = np.random.default_rng(0).integers(0, 256, (6, 8, 3), dtype=np.uint8)
    sent = FrameMessage(7, 0.25, rgb, cam, live=False, stamp_ns=11)
    inbox = Inbox(4, "frames")
    matched = threading.Event()
    with _peers(listen_only) as (a, b, keys), ExitStack() as stack:
        sub = b.declare_subscriber(keys.frames, inbox.callback)
        stack.callback(sub.undeclare)
        pub = publisher(a, keys.frames, lossless=True)
        stack.callback(pub.undeclare)
        listener = pub.declare_matching_listener(lambda s: s.matching and matched.set())
        stack.callback(listener.undeclare)
        if pub.matching_status.matching:  # matched before the listener existed
            matched.set()
        assert matched.wait(WAIT), "the subscriber never matched the publisher"
        pub.put(sent.to_bytes())
        payload = inbox.get(timeout=WAIT)
    assert payload is not None, "nothing arrived"
    got = FrameMessage.from_bytes(payload)
    assert (got.seq, got.timestamp, got.camera, got.live, got.stamp_ns) == (7, 0.25, cam, False, 11)
    np.testing.assert_array_equal(got.rgb, rgb)
    assert inbox.dropped == 0


@contextmanager
def _mesh_querier(listen_only: Path, queries: Queries) -> Iterator[zenoh.Querier]:
    """A querier of one peer matched to `queries` declared as the other's mesh queryable."""
    matched = threading.Event()
    with _peers(listen_only) as (a, b, keys), ExitStack() as stack:
        queryable = a.declare_queryable(keys.query("mesh"), queries.callback)
        stack.callback(queryable.undeclare)
        querier = b.declare_querier(keys.query("mesh"), timeout=WAIT)
        stack.callback(querier.undeclare)
        listener = querier.declare_matching_listener(lambda s: s.matching and matched.set())
        stack.callback(listener.undeclare)
        if querier.matching_status.matching:
            matched.set()
        assert matched.wait(WAIT), "the querier never matched the queryable"
        yield querier


def test_queries_beyond_capacity_are_refused_and_the_waiting_ones_share_one_answer(
    listen_only, caplog
):
    queries = Queries(2, "mesh queries")
    answers: list[bytes] = []

    def answer() -> bytes:
        answers.append(b"PLY")
        return answers[-1]

    with _mesh_querier(listen_only, queries) as querier:
        asked = [querier.get() for _ in range(5)]  # in order over the one link
        # The three beyond the two waiting are answered at once, before any work is done.
        refused = [list(replies) for replies in asked[2:]]
        assert len(queries) == 2 and answers == []
        assert queries.answer_all(answer) == 2
        answered = [list(replies) for replies in asked[:2]]
        assert queries.answer_all(answer) == 0  # none left: no work either
    assert answers == [b"PLY"]  # one piece of work for both
    for replies in answered:
        assert [r.ok.payload.to_bytes() for r in replies] == [b"PLY"]
    for replies in refused:
        assert len(replies) == 1 and replies[0].ok is None
        assert replies[0].err.payload.to_bytes() == b"busy: 2 mesh queries are waiting"
    assert queries.refused == 3
    # Logged at the 1st and 2nd refusal, not the 3rd.
    assert sum("refused one" in r.getMessage() for r in caplog.records) == 2


def test_queries_pass_on_the_answers_error(listen_only):
    queries = Queries(1, "mesh queries")

    def no_surface() -> bytes:
        raise EmptyMeshError("no map yet")

    with _mesh_querier(listen_only, queries) as querier:
        replies, second = querier.get(), querier.get()
        assert [r.err is not None for r in second] == [True]  # refused: the first is waiting
        assert queries.answer_all(no_surface) == 1
        got = list(replies)
    assert [r.err.payload.to_bytes() for r in got] == [b"no map yet"]


def test_publisher_congestion_policy_per_channel(listen_only):
    with _peers(listen_only) as (a, _, keys):
        pub = publisher(a, keys.poses, lossless=True, urgent=True)
        try:
            assert pub.congestion_control == zenoh.CongestionControl.BLOCK
            assert pub.priority == zenoh.Priority.INTERACTIVE_HIGH
        finally:
            pub.undeclare()
        pub = publisher(a, keys.keyframes, lossless=False)
        try:
            assert pub.congestion_control == zenoh.CongestionControl.DROP
        finally:
            pub.undeclare()
        pub = publisher(a, keys.map, lossless=True)
        try:
            assert pub.congestion_control == zenoh.CongestionControl.BLOCK
        finally:
            pub.undeclare()


def test_presence_sees_a_peer_come_and_go(listen_only):
    changes: list[tuple[str, bool]] = []
    gone = threading.Event()

    def on_change(role: str, alive: bool) -> None:
        changes.append((role, alive))
        if (role, alive) == ("tracker", False):
            gone.set()

    with ExitStack() as stack:
        a, b, keys = stack.enter_context(_peers(listen_only))
        watcher = Presence(b, keys, "mapper", on_change)
        stack.callback(watcher.close)
        assert watcher.wait_for("mapper", WAIT), "its own token is seen too"
        assert not watcher.alive("tracker")
        announcer = Presence(a, keys, "tracker")  # referenced: a dropped token is undeclared
        assert watcher.wait_for("tracker", WAIT)
        assert watcher.alive("tracker")
        a.close()  # the peer goes away without undeclaring anything
        assert gone.wait(WAIT), f"no (tracker, False) after the peer closed; saw {changes}"
        assert not watcher.alive("tracker")
        assert watcher.alive("mapper")
    assert ("tracker", True) in changes
    del announcer


def test_presence_wait_for_times_out(listen_only):
    with _peers(listen_only) as (_, b, keys):
        watcher = Presence(b, keys, "mapper")
        try:
            assert watcher.wait_for("camera", 0.05) is False
        finally:
            watcher.close()


# -- shutdown --------------------------------------------------------------------------------


def test_stop_wakes_a_waiting_inbox():
    inbox = Inbox(2, "frames")
    waiting = threading.Event()

    class Cond(threading.Condition):
        """Tells the test that `get` is inside `wait` (the lock is held until it releases)."""

        def wait(self, timeout=None):
            waiting.set()
            return super().wait(timeout)

    inbox._cond = Cond()
    stop = Stop()
    stop.watch(inbox)
    result: list[bytes | None] = []
    worker = threading.Thread(target=lambda: result.append(inbox.get(timeout=60)), daemon=True)
    worker.start()
    assert waiting.wait(WAIT)
    assert not stop
    stop.set("test")
    worker.join(WAIT)
    assert not worker.is_alive(), "set() did not wake the waiting get"
    assert result == [None] and stop


SIGNALLED_LOOP = """
import time
from dimslam.common.net.transport import Stop
stop = Stop()
with stop.on_signals():
    print("ready", flush=True)
    end = time.monotonic() + 3
    while time.monotonic() < end:
        stop.event.wait(0)  # takes the event's lock, as every wait on the stop does
print("done", flush=True)
"""


def test_a_signal_that_lands_while_the_main_thread_holds_the_stop_s_lock_does_not_hang_it():
    child = subprocess.Popen(
        [sys.executable, "-c", SIGNALLED_LOOP], stdout=subprocess.PIPE, text=True
    )
    try:
        assert child.stdout.readline() == "ready\n"
        for _ in range(2000):  # setting the event from the handler itself hung within these
            if child.poll() is not None:
                break
            child.send_signal(signal.SIGTERM)
            time.sleep(0.0005)
        out, _ = child.communicate(timeout=30)
    finally:
        child.kill()
    assert out == "done\n" and child.returncode == 0


def test_signal_handlers_set_the_event_and_are_restored():
    before = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    stop = Stop()
    with stop.on_signals() as s:
        assert s is stop
        assert all(signal.getsignal(sig) is not before[sig] for sig in before)
        os.kill(os.getpid(), signal.SIGTERM)
        assert stop.event.wait(WAIT), "SIGTERM did not set the stop event"
    assert {sig: signal.getsignal(sig) for sig in before} == before
    stop = Stop()
    with stop.on_signals():
        os.kill(os.getpid(), signal.SIGINT)  # no KeyboardInterrupt while the handler is in place
        assert stop.event.wait(WAIT)
    assert {sig: signal.getsignal(sig) for sig in before} == before

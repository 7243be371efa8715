"""Zenoh for the service: session config, key names, inboxes, liveliness, shutdown.

Keys (built only by `Keys`): `dimslam/<session>/@v1/<topic>`; the verbatim `@v1` chunk is the
messages' schema version, so a `dimslam/**` subscription of another major version never sees
them (zenoh.md trap 11).

| topic | from -> to | message | congestion | receiver's queue |
|---|---|---|---|---|
| frames | camera -> tracker | FrameMessage, EndOfStream | BLOCK | FRAME_QUEUE, drop oldest |
| poses | tracker -> anyone | PoseMessage, EndOfStream | BLOCK, express, recoverable | per client |
| mapping | tracker -> mapper | MappingBatch, EndOfStream | BLOCK | BATCH_QUEUE, coalesced |
| map | mapper -> tracker | MapSnapshot | BLOCK | 1, newest wins |
| keyframes | mapper -> anyone | PoseMessage (refined) | BLOCK, express | per client |
| query/{map,keyframes} | tracker -> mapper | snapshot, MappingBatch of keyframes | | |
| query/mesh | anyone -> mapper | PLY | | MESH_QUERIES, refused beyond |
| query/trajectory | anyone -> mapper | TUM text | | |
| alive/<role> | every process | liveliness token | | |

Lockstep (the camera never more than K frames ahead of the published poses) bounds the frame
queue; mapping batches are coalesced: a mapper that falls behind maps all pending frames in
its next round. Poses are lossless: with DROP, the burst of poses published after the
initialization lost 4 of 8 on loopback (measured), and a client expects one pose per frame;
the tracker keeps its newest poses for clients whose link was down a while, which ask for the
ones they missed (`pose_publisher`, `pose_subscriber`: zenoh.ext's advanced pub/sub).

Default endpoints (one host, zenoh.md traps 9-10): peer mode, scouting off; the tracker listens
on `tcp/127.0.0.1:7451`, the mapper on `:7452`; every process connects to both ports it does not
listen on, and peer mode retries until they are up, so start order is free.
"""

from __future__ import annotations

import json
import logging
import math
import queue
import re
import signal
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh
import zenoh.ext

from dimslam.common.errors import DimslamError
from dimslam.common.net.messages import SCHEMA

log = logging.getLogger(__name__)

TRACKER_PORT = 7451
MAPPER_PORT = 7452
FRAME_QUEUE = 256
"""Frames the tracker holds before dropping the oldest (lockstep keeps it far below)."""
REJECT_KINDS = 16
"""Kinds of rejection on one topic that each get a line of their own (`Rejects`)."""
REJECT_LOG_S = 10.0
"""Beyond its first of each kind, a topic's rejections are summed into one line this often."""
BATCH_QUEUE = 64
"""Mapping batches the mapper holds; it coalesces all pending ones into each round."""
MESH_QUERIES = 16
"""Mesh queries the mapper holds; it answers all of them with one mesh, and refuses more."""
HEARTBEAT_S = 0.5
"""Period of the pose publisher's heartbeat (the newest sequence number, for miss detection)."""
SHARED_MEMORY = False
"""Zenoh's same-host shared memory, off: a receiver maps the sender's pool (up to its size, the
sender's choice) as it receives, which any process of the host that joins a session could use
to grow every receiver's memory; loopback TCP costs a few ms per MB (zenoh.md), nothing next
to a mapping round. A `--zenoh-config` file may turn it on."""

_SESSION_RE = re.compile(r"^[A-Za-z0-9_.-]+$")


@dataclass(frozen=True)
class TransportConfig:
    """How a process joins the service."""

    session: str = "default"
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    zenoh_config: Path | None = None

    def __post_init__(self) -> None:
        if not _SESSION_RE.fullmatch(self.session):  # match() lets a trailing newline in
            raise DimslamError(
                f"--session {self.session!r}: use letters, digits, '_', '-' and '.' only"
            )


def default_endpoints(role: str) -> tuple[list[str], list[str]]:
    """(listen, connect) endpoints of `role` on one host."""
    ports = {"tracker": TRACKER_PORT, "mapper": MAPPER_PORT}
    # A role without a port still listens, on loopback only: zenoh's own default would be a
    # random port on every interface (zenoh.md trap 9).
    listen = [f"tcp/127.0.0.1:{ports.get(role, 0)}"]
    connect = [f"tcp/127.0.0.1:{p}" for r, p in ports.items() if r != role]
    return listen, connect


def zenoh_config(cfg: TransportConfig, role: str) -> zenoh.Config:
    """The zenoh configuration of `role`: the file if given, else one-host peer defaults.

    `--connect` / `--listen` replace the endpoints of either.
    """
    if cfg.zenoh_config is not None:
        try:
            conf = zenoh.Config.from_file(str(cfg.zenoh_config))
        except Exception as e:  # zenoh raises its own error type with the parser's message
            raise DimslamError(f"--zenoh-config {cfg.zenoh_config}: {e}") from None
        listen, connect = list(cfg.listen), list(cfg.connect)
    else:
        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("transport/shared_memory/enabled", json.dumps(SHARED_MEMORY))
        listen, connect = default_endpoints(role)
        listen = list(cfg.listen) or listen
        connect = list(cfg.connect) or connect
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(listen))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(connect))
    return conf


def open_session(cfg: TransportConfig, role: str) -> zenoh.Session:
    """Open the zenoh session of `role`; use it in a `with` block (zenoh.md trap 1)."""
    try:
        return zenoh.open(zenoh_config(cfg, role))
    except zenoh.ZError as e:
        raise DimslamError(f"cannot open the zenoh session: {e}") from None


class Keys:
    """Every key expression of one session."""

    def __init__(self, session: str) -> None:
        self.root = f"dimslam/{session}/@v{SCHEMA}"

    def __getattr__(self, topic: str) -> str:
        if topic in {"frames", "poses", "mapping", "map", "keyframes"}:
            return f"{self.root}/{topic}"
        raise AttributeError(topic)

    def query(self, what: str) -> str:
        assert what in {"map", "mesh", "trajectory", "keyframes"}, what
        return f"{self.root}/query/{what}"

    def alive(self, role: str = "*") -> str:
        return f"{self.root}/alive/{role}"


def publisher(
    session: zenoh.Session, key: str, lossless: bool, urgent: bool = False
) -> zenoh.Publisher:
    """A publisher with the topic's congestion policy.

    Args:
        lossless: BLOCK when the link is congested (frames in lockstep, batches, snapshots,
            poses); otherwise DROP (live frames, display-only topics).
        urgent: express (no batching) at high priority (poses).
    """
    congestion = zenoh.CongestionControl.BLOCK if lossless else zenoh.CongestionControl.DROP
    if urgent:
        return session.declare_publisher(
            key,
            congestion_control=congestion,
            priority=zenoh.Priority.INTERACTIVE_HIGH,
            express=True,
        )
    return session.declare_publisher(key, congestion_control=congestion)


POSE_HISTORY = 4096
"""Poses the tracker keeps for subscribers that missed some (`pose_publisher`)."""


def pose_publisher(session: zenoh.Session, key: str) -> zenoh.ext.AdvancedPublisher:
    """The tracker's poses: BLOCK, express, high priority, and the newest `POSE_HISTORY` kept
    for `pose_subscriber`s that missed some (their link or the router down a while): each
    message carries a sequence number, so the next pose (or the end of stream) after a gap
    shows it, and the subscriber asks for the missed ones before taking it. (The heartbeat,
    which would also reveal a gap at the very end, does not reach subscribers of keys with a
    verbatim chunk such as our `@v1`: measured with zenoh 1.10.2; nor did periodic queries.)"""
    return zenoh.ext.declare_advanced_publisher(
        session,
        key,
        congestion_control=zenoh.CongestionControl.BLOCK,
        priority=zenoh.Priority.INTERACTIVE_HIGH,
        express=True,
        cache=zenoh.ext.CacheConfig(POSE_HISTORY),
        sample_miss_detection=zenoh.ext.MissDetectionConfig(heartbeat=HEARTBEAT_S),
        publisher_detection=True,
    )


def pose_subscriber(
    session: zenoh.Session, key: str, callback: Callable[[zenoh.Sample], None]
) -> zenoh.ext.AdvancedSubscriber:
    """A subscriber to `pose_publisher`'s poses that gets again those it missed, in order
    (only from the tracker that published them: a tracker that died took its history)."""
    return zenoh.ext.declare_advanced_subscriber(
        session, key, callback, recovery=zenoh.ext.RecoveryConfig(heartbeat=True)
    )


class Inbox:
    """A bounded, thread-safe queue of payloads fed by a zenoh callback.

    The callback copies the bytes and, with `admit`, decodes and checks them (zenoh.md trap 7:
    no more than that on zenoh's thread). When full, the oldest item is dropped and counted:
    a subscriber can never block the session's receive thread.
    """

    def __init__(
        self, capacity: int, name: str, admit: Callable[[bytes], Any] | None = None
    ) -> None:
        """
        Args:
            capacity: items held before the oldest is dropped.
            name: for the log.
            admit: run on zenoh's thread for each payload: returns what to queue (the decoded
                message), or None for a payload it refused (and counted). Refusing bad
                messages before they are queued keeps a flood of them from pushing real ones
                out of the queue. None: the raw payloads are queued.
        """
        self.name = name
        self._items: deque[Any] = deque()
        self._capacity = capacity
        self._admit = admit
        self._cond = threading.Condition()
        self.dropped = 0

    def put(self, payload: Any) -> None:
        with self._cond:
            if len(self._items) >= self._capacity:
                self._items.popleft()
                self.dropped += 1
                # Logged at the 1st, 2nd, 4th, 8th, ... drop: a flood cannot flood the log.
                if self._capacity > 1 and self.dropped & (self.dropped - 1) == 0:
                    log.warning(
                        "%s: queue full, dropped the oldest (%d so far)", self.name, self.dropped
                    )
            self._items.append(payload)
            self._cond.notify_all()

    def callback(self, sample: zenoh.Sample) -> None:
        payload = sample.payload.to_bytes()
        item = payload if self._admit is None else self._admit(payload)
        if item is not None:
            self.put(item)

    def get(self, timeout: float) -> Any | None:
        """The oldest payload, waiting up to `timeout` seconds; None if none came."""
        with self._cond:
            if not self._items:
                self._cond.wait(timeout)
            return self._items.popleft() if self._items else None

    def drain(self) -> list[Any]:
        """Everything queued, oldest first, without waiting."""
        with self._cond:
            items = list(self._items)
            self._items.clear()
            return items

    def __len__(self) -> int:
        with self._cond:
            return len(self._items)

    def wake(self) -> None:
        """Wake a waiting `get` (shutdown)."""
        with self._cond:
            self._cond.notify_all()


class Queries:
    """Queries that wait for the main loop, at most `capacity` of them.

    A query's answer may take long (the mapper's mesh: seconds to a minute), so it is not
    answered on zenoh's thread (zenoh.md trap 7); a flood of queries must not queue work
    without bound either: one beyond `capacity` is answered at once with an error, and the
    waiting ones are answered together, with one piece of work (`answer_all`).
    """

    def __init__(self, capacity: int, name: str) -> None:
        self.name = name
        self._capacity = capacity
        self._items: deque[zenoh.Query] = deque()
        self._lock = threading.Lock()
        self.refused = 0

    def callback(self, query: zenoh.Query) -> None:
        with self._lock:
            full = len(self._items) >= self._capacity
            if not full:
                self._items.append(query)
            else:
                self.refused += 1
                refused = self.refused
        if full:
            with query:  # dropping the query ends it for the asker (zenoh.md trap 3)
                query.reply_err(f"busy: {self._capacity} {self.name} are waiting".encode())
            if refused & (refused - 1) == 0:  # logged at the 1st, 2nd, 4th, 8th, ... refusal
                log.warning(
                    "%s: %d waiting, refused one (%d so far)", self.name, self._capacity, refused
                )

    def answer_all(self, answer: Callable[[], bytes]) -> int:
        """Replies to every waiting query with `answer()`, computed once (or with its error
        when it raises a DimslamError); returns how many were answered."""
        with self._lock:
            waiting = list(self._items)
            self._items.clear()
        if not waiting:
            return 0
        try:
            payload, error = answer(), None
        except DimslamError as e:
            payload, error = None, str(e).encode()
        for query in waiting:
            with query:
                if error is None:
                    query.reply(query.key_expr, payload)
                else:
                    query.reply_err(error)
        return len(waiting)

    def __len__(self) -> int:
        with self._lock:
            return len(self._items)


class Rejects:
    """Counts and logs messages that failed to decode or do not fit the stream; the process
    keeps running.

    The first rejection of each kind on a topic is logged with its reason (the kind: the
    reason up to its first ':', digits left out, at most `REJECT_KINDS` kinds per topic); the
    others are summed into at most one line per topic every `REJECT_LOG_S` seconds. A flood
    of bad messages costs a few log lines, not one per message. Thread-safe: zenoh's
    callbacks call it too.
    """

    def __init__(self) -> None:
        self.count = 0
        self._lock = threading.Lock()
        self._kinds: dict[str, set[str]] = {}
        self._unlogged: dict[str, int] = {}
        self._logged_at: dict[str, float] = {}

    def __call__(self, topic: str, error: Exception) -> None:
        reason = str(error)
        kind = re.sub(r"\d+", "#", reason.split(":", 1)[0])
        now = time.monotonic()
        with self._lock:
            self.count += 1
            count = self.count
            kinds = self._kinds.setdefault(topic, set())
            first = kind not in kinds and len(kinds) < REJECT_KINDS
            if first:
                kinds.add(kind)
            else:
                self._unlogged[topic] = self._unlogged.get(topic, 0) + 1
                if now - self._logged_at.get(topic, -math.inf) < REJECT_LOG_S:
                    return
            self._logged_at[topic] = now
            more = 0 if first else self._unlogged.pop(topic)
        if first:
            log.warning("rejected a message on %s (%d so far): %s", topic, count, reason)
        else:
            log.warning(
                "rejected %d more messages on %s (%d so far; the last: %s)",
                more, topic, count, reason,
            )  # fmt: skip


class Presence:
    """This process's liveliness token plus a watch on its peers' tokens.

    `on_change(role, alive)` runs on zenoh's thread when a peer's token appears or vanishes
    (a SIGKILLed peer's token vanishes within milliseconds on one host).
    """

    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        role: str,
        on_change: Callable[[str, bool], None] | None = None,
    ) -> None:
        self._lock = threading.Lock()
        self._alive: dict[str, int] = {}
        self._on_change = on_change
        self._changed = threading.Condition(self._lock)
        # Keep references: an unreferenced token or subscriber is undeclared (zenoh.md trap 4).
        self.token = session.liveliness().declare_token(keys.alive(role))
        self._watch = session.liveliness().declare_subscriber(
            keys.alive(), self._sample, history=True
        )

    def _sample(self, sample: zenoh.Sample) -> None:
        role = str(sample.key_expr).rsplit("/", 1)[-1]
        alive = sample.kind == zenoh.SampleKind.PUT
        with self._lock:
            count = self._alive.get(role, 0) + (1 if alive else -1)
            self._alive[role] = max(count, 0)
            self._changed.notify_all()
        if self._on_change is not None:
            self._on_change(role, alive)

    def alive(self, role: str) -> bool:
        with self._lock:
            return self._alive.get(role, 0) > 0

    def wait_for(self, role: str, timeout: float) -> bool:
        """Wait until a `role` process is alive; returns whether it is."""
        with self._lock:
            return self._changed.wait_for(lambda: self._alive.get(role, 0) > 0, timeout)

    def close(self) -> None:
        self._watch.undeclare()
        self.token.undeclare()


class Stop:
    """One event set by SIGINT/SIGTERM; loops wait on their inbox with a timeout and check it."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self._inboxes: list[Inbox] = []

    def watch(self, *inboxes: Inbox) -> None:
        self._inboxes.extend(inboxes)

    def set(self, reason: str = "") -> None:
        if reason and not self.event.is_set():
            log.info("stopping: %s", reason)
        self.event.set()
        for inbox in self._inboxes:
            inbox.wake()

    def __bool__(self) -> bool:
        return self.event.is_set()

    @contextmanager
    def on_signals(self) -> Iterator[Stop]:
        """Install SIGINT/SIGTERM handlers for the block's duration (main thread only).

        A handler runs in the main thread between two of its bytecodes, possibly while
        that thread holds the very lock `set` takes (waiting on the stop event or an inbox
        re-acquires their condition's lock): `set` from the handler then waits for itself
        forever (a SIGTERMed camera hung 1 run in about 15 under load). So the handler only
        hands the signal's name to a thread of its own (`queue.SimpleQueue.put` is reentrant),
        which calls `set`."""
        previous = {}
        names: queue.SimpleQueue[str | None] = queue.SimpleQueue()

        def relay() -> None:
            while (name := names.get()) is not None:
                self.set(name)

        def handler(signum: int, _frame) -> None:
            names.put(signal.Signals(signum).name)

        relaying = threading.Thread(target=relay, name="signals", daemon=True)
        relaying.start()
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, handler)
        try:
            yield self
        finally:
            for sig, old in previous.items():
                signal.signal(sig, old)
            names.put(None)
            relaying.join()

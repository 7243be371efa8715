"""`dimslam-camera`: the frame publisher.

A plain peer of the service (transport.py): `with open_session(...)` so nothing hangs at exit,
SIGINT/SIGTERM set one stop event, user errors print one line and exit 2 (entry.run_main).

The camera sends each frame, in order, once three gates let it through:
1. lockstep (optional; a dataset or video replayed `--live` until the map is initialized):
   fewer than `--ahead` frames beyond the last pose the tracker published;
2. pacing: the recorded rate (timestamp differences), `--rate`, or none; after a stall
   (lockstep, slow decoding) the schedule restarts instead of bursting to catch up;
3. the publisher: BLOCK for datasets and videos, so every frame arrives; DROP for a live
   camera, whose tracker only wants the newest frame.
Dataset and video frames wait until a tracker is alive and subscribed, so none is sent into the
void; `EndOfStream` follows the last frame, or the frames sent so far on a stop signal.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence

import zenoh

from dimslam.common import entry
from dimslam.common.errors import DimslamError
from dimslam.common.io.datasets import Reader, add_reader_arguments, open_from_args
from dimslam.common.io.datasets.video import CameraReader
from dimslam.common.net.messages import (
    EndOfStream,
    FrameMessage,
    MessageError,
    PoseMessage,
    decode_or_end,
)
from dimslam.common.net.service import (
    TICK_S,
    add_transport_options,
    log_peer,
    positive_int,
    positive_seconds,
    transport_config,
)
from dimslam.common.net.transport import (
    Keys,
    Presence,
    Rejects,
    Stop,
    open_session,
    pose_subscriber,
    publisher,
)
from dimslam.common.progress import Progress

# Named, not __name__: under `python -m` (how `dimslam run` starts it) that is "__main__".
log = logging.getLogger("dimslam.common.net.camera")

STALL_WARN_S = 10.0
"""A lockstep camera that waited this long without any pose says why it may be stuck."""
DEFAULT_AHEAD = 32

CAMERA_DESCRIPTION = (
    "Publish frames from a dataset folder, a video file or a live camera index to the dimslam "
    "tracker, at the recorded rate or in lockstep with the tracker; intrinsics travel with the "
    "stream."
)


def _rate(text: str) -> float:
    value = float(text)
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"must be 0 or a positive frame rate, got {text}")
    return value


def _camera_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("source", help="dataset folder, video file or live camera index")
    add_reader_arguments(p)
    g = p.add_argument_group("streaming")
    g.add_argument(
        "--rate",
        type=_rate,
        default=None,
        metavar="FPS",
        help="frames per second; 0: as fast as allowed (default: the recorded rate; a live "
        "camera's own rate)",
    )
    g.add_argument(
        "--live",
        action="store_true",
        help="replay a dataset or video as a live camera would send it: at its rate, frames "
        "marked live and sent with DROP congestion control, so a busy tracker keeps only the "
        "newest (a live camera index always is); the first frames go in lockstep until the "
        "map is initialized, as a user holds a live camera still until then",
    )
    g.add_argument(
        "--lockstep",
        action="store_true",
        help="never run more than --ahead frames beyond the tracker's published poses",
    )
    g.add_argument(
        "--ahead",
        type=positive_int,
        default=DEFAULT_AHEAD,
        metavar="K",
        help=f"with --lockstep (or --live until the map exists), frames sent beyond the last "
        f"pose (default: {DEFAULT_AHEAD}); "
        "must exceed the tracker's initialization frames (13 for the paper and cpu presets), "
        "since no pose is published before the map is initialized",
    )
    g.add_argument(
        "--max-frames",
        type=positive_int,
        default=None,
        metavar="N",
        help="stop after this many frames",
    )
    g.add_argument(
        "--no-wait",
        action="store_true",
        help="send at once instead of waiting for a subscribed tracker (datasets and videos)",
    )
    g.add_argument(
        "--grace",
        type=positive_seconds,
        default=10.0,
        metavar="S",
        help="when the tracker goes away mid-stream, wait S seconds for one to come back "
        "(a restarted tracker, a router back up) before ending the stream (default: 10)",
    )
    g.add_argument(
        "--also-wait-for",
        action="append",
        default=[],
        metavar="ROLE",
        help="also wait until a process of ROLE (e.g. viewer) is alive and connected before "
        "the first frame, so that it sees them all (repeatable; datasets and videos)",
    )
    g.add_argument(
        "--wait-timeout",
        type=positive_seconds,
        default=60.0,
        metavar="S",
        help="give up (exit 2) if no tracker is subscribed after S seconds (default: 60)",
    )


class _PoseMark:
    """The highest frame seq the tracker has published a pose for, to hold a lockstep camera."""

    def __init__(self, topic: str) -> None:
        self.topic = topic
        self.highest = -1
        self.last_sent = -1
        self.ended = False
        self.ended_early = False  # the tracker ended while frames were held back for it
        self.resend = False  # a tracker is back: frames without a pose go to it again
        self.rejects = Rejects()
        self._cond = threading.Condition()

    def callback(self, sample: zenoh.Sample) -> None:
        # A pose is ~200 bytes: decoding it on zenoh's thread costs less than queueing it.
        payload = sample.payload.to_bytes()
        try:
            msg = decode_or_end(payload, PoseMessage)
            seq = msg.seq if isinstance(msg, PoseMessage) else None
            if seq is not None and seq > self.last_sent:
                # It would release the lockstep for frames the tracker has not seen.
                raise MessageError(f"a pose of frame {seq}, which was never sent")
        except MessageError as e:
            self.rejects(self.topic, e)
            return
        with self._cond:
            self.ended = self.ended or isinstance(msg, EndOfStream)
            if seq is not None:
                self.highest = max(self.highest, seq)
            self._cond.notify_all()

    def tracker_back(self) -> None:
        """A tracker came back (a new one, or the same one after a link cut): the frames
        without a pose are sent again (`take_resend`), since the ones it had may be lost."""
        with self._cond:
            self.resend = True
            self._cond.notify_all()

    def take_resend(self) -> bool:
        """Whether frames are to be sent again (once per `tracker_back`)."""
        with self._cond:
            due, self.resend = self.resend, False
            return due

    def wait_until(self, seq: int, ahead: int, stop: Stop) -> bool:
        """Wait until frame `seq` is fewer than `ahead` frames beyond the last pose, or frames
        are to be sent again (`take_resend`).

        Returns:
            False if the stop event was set or the tracker ended its stream first.
        """
        warn_at = time.monotonic() + STALL_WARN_S
        with self._cond:
            while seq - (self.highest + 1) >= ahead and not self.resend:
                self.ended_early = self.ended
                if stop or self.ended:
                    return False
                if self.highest < 0 and warn_at < time.monotonic():
                    warn_at = math.inf
                    log.warning(
                        "no pose yet after %d frames: --ahead must exceed the tracker's "
                        "initialization frames, or the tracker is still starting",
                        seq,
                    )
                self._cond.wait(TICK_S)
            return True


class _Pacer:
    """When each frame is due: the recorded rate (`rate` None), `rate` fps, or at once (0)."""

    def __init__(self, rate: float | None) -> None:
        self.rate = rate
        self._due: float | None = None
        self._last_timestamp: float | None = None

    def delay(self, timestamp: float) -> float:
        """Seconds to wait before sending the frame taken at `timestamp` (source seconds)."""
        if self.rate is None:
            last = self._last_timestamp
            interval = 0.0 if last is None else max(timestamp - last, 0.0)
        else:
            interval = 1.0 / self.rate if self.rate > 0 else 0.0
        self._last_timestamp = timestamp
        now = time.monotonic()
        # A frame is due one interval after the previous one was due, or now if that has passed.
        self._due = now if self._due is None else max(self._due + interval, now)
        return self._due - now


def _wait_for_tracker(
    pub: zenoh.Publisher,
    presence: Presence,
    changed: threading.Event,
    stop: Stop,
    timeout: float,
    others: Sequence[str] = (),
) -> bool:
    """Wait until a tracker is alive and subscribed to the frames, and a process of each of
    `others` alive (its token reaches us over a direct link, after its subscriptions); False
    on timeout or stop."""
    deadline = time.monotonic() + timeout
    # Cleared before each check, so a change during the check wakes the next wait.
    changed.clear()
    roles = ("tracker", *others)
    while not (all(presence.alive(r) for r in roles) and pub.matching_status.matching):
        remaining = deadline - time.monotonic()
        if stop or remaining <= 0:
            return False
        changed.wait(min(remaining, TICK_S))
        changed.clear()
    return True


def _stream(
    reader: Reader,
    device: bool,
    live: bool,
    pub: zenoh.Publisher,
    args: argparse.Namespace,
    stop: Stop,
    mark: _PoseMark,
    tracker_ready: Callable[[], bool],
) -> int:
    """Send the source's frames until it ends, `--max-frames`, or a stop; returns how many.

    A frame that waits for the tracker (lockstep, or a replay until the map exists) also
    waits, up to `--grace`, while no tracker is there to take it (`tracker_ready`): a frame
    put with nobody subscribed is lost."""
    # A camera device paces itself; waiting on its wall-clock stamps would only add latency.
    pacer = _Pacer(args.rate if args.rate is not None else 0.0 if device else None)
    camera = reader.camera
    try:
        total = len(reader)
    except TypeError:  # an unbounded live stream
        total = None
    if args.max_frames is not None:
        total = args.max_frames if total is None else min(total, args.max_frames)
    bar = Progress(total, "sent")
    sent = 0
    # Frames sent and not yet posed, for a tracker that comes back (live frames are not kept:
    # a late one is worth nothing to the tracker).
    unposed: deque[tuple[int, bytes]] = deque(maxlen=0 if live else args.ahead)

    def send_unposed_again() -> None:
        again = [payload for seq, payload in unposed if seq > mark.highest]
        if again and tracker_ready():
            log.info("sending again %d frame(s) without a pose", len(again))
            for payload in again:
                pub.put(payload)

    def may_send(gated: bool) -> bool:
        """Wait until the next frame may go (frames without a pose sent again meanwhile if a
        tracker came back); False on a stop or the tracker's end."""
        while True:
            if gated and not (mark.wait_until(sent, args.ahead, stop) and tracker_ready()):
                return False
            if not mark.take_resend():
                return True
            send_unposed_again()

    # A replayed stream starts its live clock once the map exists: until the tracker's first
    # pose it goes in lockstep, as a user holds a live camera until the system is initialized.
    replayed = live and not device
    for frame in reader:
        gated = args.lockstep or (replayed and mark.highest < 0)
        if stop or not may_send(gated):
            break
        if stop.event.wait(pacer.delay(frame.timestamp)):
            break
        # Held frames are not live: the tracker must not skip one of its initialization's.
        message = FrameMessage(sent, frame.timestamp, frame.rgb, camera, live=live and not gated)
        mark.last_sent = sent  # before the put: its pose may come back at once
        payload = message.to_bytes()
        pub.put(payload)
        unposed.append((sent, payload))
        sent += 1
        bar.update(sent, tracked=mark.highest + 1)
        if sent == args.max_frames:
            break
    bar.close(tracked=mark.highest + 1)
    return sent


def run_camera(args: argparse.Namespace) -> int:
    """Stream the source; 0 at its end or on a stop signal, 1 if the tracker left first."""
    cfg = transport_config(args)
    keys = Keys(cfg.session)
    stop = Stop()
    changed = threading.Event()
    tracker_lost = threading.Event()

    grace: list[threading.Timer] = []

    def give_up() -> None:
        if not presence.alive("tracker"):
            tracker_lost.set()
            stop.set("the tracker went away")

    def on_peer(role: str, alive: bool) -> None:
        log_peer(role, alive)
        changed.set()
        if role != "tracker" or not watch_tracker.is_set():
            return
        if alive and grace:
            log.info("a tracker is back")
            mark.tracker_back()
        for timer in grace:  # a tracker is back (or another token changed): start afresh
            timer.cancel()
        grace.clear()
        if not alive:
            # A restarted tracker (it continues the running map) or a router that came back
            # within the grace keeps the stream going; the frames without a pose go again.
            log.warning("the tracker went away: waiting %g s for it to come back", args.grace)
            grace.append(threading.Timer(args.grace, give_up))
            grace[0].daemon = True
            grace[0].start()

    watch_tracker = threading.Event()  # set once a tracker was waited for
    with (
        stop.on_signals(),
        open_from_args(args, args.source) as reader,
        open_session(cfg, "camera") as session,
    ):
        device = reader.layout == CameraReader.layout
        live = device or args.live
        if live and args.lockstep:
            raise DimslamError("--lockstep waits for the tracker; a live stream never waits")
        pub = publisher(session, keys.frames, lossless=not live)
        presence = Presence(session, keys, "camera", on_change=on_peer)
        matching = pub.declare_matching_listener(lambda _status: changed.set())
        mark = _PoseMark(keys.poses)
        poses = pose_subscriber(session, keys.poses, mark.callback)
        if not (device or args.no_wait):
            log.info("waiting for a tracker in session %r", cfg.session)
            waited = (pub, presence, changed, stop, args.wait_timeout, args.also_wait_for)
            if _wait_for_tracker(*waited):
                watch_tracker.set()
            elif not stop:
                missing = [r for r in args.also_wait_for if not presence.alive(r)]
                if missing and presence.alive("tracker"):
                    raise DimslamError(
                        f"no {', '.join(missing)} connected in session {cfg.session!r} after "
                        f"{args.wait_timeout:g} s (--also-wait-for)"
                    )
                raise DimslamError(
                    f"no tracker subscribed in session {cfg.session!r} after "
                    f"{args.wait_timeout:g} s: start dimslam-tracker with the same --session "
                    "and endpoints, or pass --no-wait"
                )

        def tracker_ready() -> bool:
            if presence.alive("tracker") and pub.matching_status.matching:
                return True
            back = _wait_for_tracker(pub, presence, changed, stop, args.grace)
            if back:
                mark.tracker_back()  # before the next frame: the ones it may lack go first
            return back

        sent = 0 if stop else _stream(reader, device, live, pub, args, stop, mark, tracker_ready)
        # A tracker that leaves after the last frame has simply finished.
        watch_tracker.clear()
        end = EndOfStream(sent).to_bytes()
        if live:
            # Live frames may be dropped, the end may not: BLOCK, at the frames' own priority
            # so that it cannot overtake the last frame.
            session.put(
                keys.frames,
                end,
                congestion_control=zenoh.CongestionControl.BLOCK,
                priority=pub.priority,
                express=True,
            )
        else:
            pub.put(end)
        log.info(
            "sent %d frames, then the end of stream (%d unreadable, %d poses rejected)",
            sent, reader.skipped, mark.rejects.count,
        )  # fmt: skip
        matching.undeclare()
        poses.undeclare()
        presence.close()
    if tracker_lost.is_set():
        log.error("the tracker went away after %d frames", sent)
        return 1
    if mark.ended_early:
        log.error("the tracker ended its stream after pose %d; %d frames sent", mark.highest, sent)
        return 1
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="dimslam-camera", description=CAMERA_DESCRIPTION)
    _camera_options(parser)
    add_transport_options(parser)
    return entry.main(parser, run_camera, argv)


if __name__ == "__main__":
    sys.exit(main())

"""`dimslam-poses`: the pose subscriber.

A plain peer of the service (transport.py): `with open_session(...)` so nothing hangs at exit,
SIGINT/SIGTERM set one stop event, user errors print one line and exit 2 (entry.run_main).
It prints each pose the tracker publishes (TUM or JSON lines), with `--keyframes` also the
mapper's refinements, and can write the newest pose of every frame as a TUM file at exit.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import zenoh

from dimslam.common import entry
from dimslam.common.errors import DimslamError
from dimslam.common.io.trajectory import Trajectory, tum_lines, write_tum
from dimslam.common.net.messages import (
    EndOfStream,
    MessageError,
    PoseMessage,
    decode_or_end,
)
from dimslam.common.net.ros2 import Ros2Bridge, Ros2Topics, topic_key
from dimslam.common.net.service import (
    TICK_S,
    add_transport_options,
    log_peer,
    positive_int,
    positive_seconds,
    transport_config,
)
from dimslam.common.net.transport import (
    Inbox,
    Keys,
    Presence,
    Rejects,
    Stop,
    open_session,
    pose_subscriber,
)

# Named, not __name__: under `python -m` (how `dimslam run` starts it) that is "__main__".
log = logging.getLogger("dimslam.common.net.poses")

POSE_QUEUE = 4096
"""Poses the client holds before dropping the oldest; printing outpaces any tracker."""

POSES_DESCRIPTION = (
    "Subscribe to the dimslam pose topic and print the camera trajectory (TUM lines, or JSON "
    "lines), optionally writing it to a TUM file."
)


END_GRACE_S = 1.0
"""How long the client still takes refinements after the end of stream."""


def _poses_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--out",
        type=Path,
        metavar="FILE",
        help="also write the trajectory as a TUM file on exit: one line per frame, sorted by "
        "time, with the frame's pose from the newest map (the last received of that map)",
    )
    p.add_argument("--json", action="store_true", help="print JSON lines instead of TUM lines")
    p.add_argument(
        "--keyframes",
        action="store_true",
        help="also print the mapper's refined keyframe poses (they replace the tracked ones)",
    )
    p.add_argument(
        "--count",
        type=positive_int,
        default=None,
        metavar="N",
        help="exit after N poses from the tracker",
    )
    p.add_argument(
        "--timeout",
        type=positive_seconds,
        default=None,
        metavar="S",
        help="exit 1 if no pose for S s",
    )
    g = p.add_argument_group(
        "ROS 2",
        "republish the poses as ROS 2 messages (CDR) on the zenoh keys that "
        "zenoh-bridge-ros2dds routes to ROS 2 topics (needs the [ros] extra; deploy/README.md)",
    )
    g.add_argument(
        "--ros2",
        action="store_true",
        help="publish every tracked pose as geometry_msgs/msg/PoseStamped and, after each map "
        "refinement, the keyframes as nav_msgs/msg/Path",
    )
    g.add_argument(
        "--ros2-pose-topic",
        default=Ros2Topics.pose,
        metavar="TOPIC",
        help=f"ROS 2 topic of the poses (default {Ros2Topics.pose}: zenoh key "
        f"{topic_key(Ros2Topics.pose)})",
    )
    g.add_argument(
        "--ros2-path-topic",
        default=Ros2Topics.path,
        metavar="TOPIC",
        help=f"ROS 2 topic of the keyframe path (default {Ros2Topics.path})",
    )
    g.add_argument(
        "--ros2-frame-id",
        default=Ros2Topics.frame_id,
        metavar="FRAME",
        help=f"header.frame_id of the messages: the map's frame (default {Ros2Topics.frame_id})",
    )


def _format(msg: PoseMessage, as_json: bool, refined: bool) -> str:
    """A JSON line, or a TUM line (a lost frame: a `#` comment line, which TUM readers skip)."""
    if as_json:
        return json.dumps(
            {
                "seq": msg.seq,
                "timestamp": msg.timestamp,
                "status": msg.status,
                "T_wc": None if msg.T_wc is None else msg.T_wc.tolist(),
                "keyframe": msg.keyframe,
                "map_version": msg.map_version,
                "stamp_ns": msg.stamp_ns,
                "refined": refined,
            }
        )
    if msg.lost:
        return f"# lost {msg.timestamp:.6f} frame {msg.seq}"
    return tum_lines(Trajectory.from_lists([msg.timestamp], [msg.T_wc]))[0]


def _emit(line: str, stop: Stop) -> None:
    try:
        print(line, flush=True)
    except BrokenPipeError:
        # Whoever read our output is gone (`| head`): stop as on a signal, and point stdout at
        # /dev/null so that the interpreter's final flush does not fail again.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        stop.set("output closed")


def _receive(
    args: argparse.Namespace,
    keys: Keys,
    inbox: Inbox,
    refined: Inbox,
    stop: Stop,
    latest: dict[int, PoseMessage],
    bridge: Ros2Bridge | None = None,
) -> int:
    """Print poses until the end of stream, `--count`, a stop (0) or `--timeout` (1).

    After the end, refinements still on their way on the keyframes topic (sent before the end,
    but zenoh orders per topic only) are taken for `END_GRACE_S` more."""
    rejects = Rejects()
    refinements = 0  # since the keyframe path was last published

    def publish_path() -> None:
        nonlocal refinements
        if bridge is not None and refinements:
            bridge.keyframes(latest.values())
            refinements = 0

    tracked = 0
    ended = False
    last = time.monotonic()

    def take(topic: str, payload: bytes) -> None:
        nonlocal ended, last, tracked, refinements
        try:
            msg = decode_or_end(payload, PoseMessage)
        except MessageError as e:
            rejects(topic, e)
            return
        if isinstance(msg, EndOfStream):
            if topic == keys.poses:
                log.info("end of stream: %d frames, %d poses received", msg.frames, tracked)
                ended = True
            return
        last = time.monotonic()
        if bridge is not None and topic == keys.poses:
            bridge.pose(msg)
        if msg.supersedes(latest.get(msg.seq)):
            latest[msg.seq] = msg
        if topic == keys.poses or args.keyframes:
            _emit(_format(msg, args.json, refined=topic == keys.keyframes), stop)
        if topic == keys.poses:
            tracked += 1
        else:
            refinements += 1  # the keyframe path goes out once per batch (publish_path)

    while not (stop or ended):
        payload = inbox.get(TICK_S)
        batch = [] if payload is None else [(keys.poses, payload)]
        # Refinements that came with the end still belong to the run: the batch is finished.
        batch += [(keys.keyframes, p) for p in refined.drain()]
        for topic, payload in batch:
            take(topic, payload)
            if args.count is not None and tracked >= args.count:
                publish_path()
                return 0
        publish_path()
        if not ended and args.timeout is not None and time.monotonic() - last > args.timeout:
            log.error("no pose for %g s; giving up after %d poses", args.timeout, tracked)
            return 1
    if ended and (args.keyframes or bridge is not None):
        deadline = time.monotonic() + END_GRACE_S
        while not stop and (left := deadline - time.monotonic()) > 0:
            payload = refined.get(min(left, TICK_S))
            if payload is not None:
                take(keys.keyframes, payload)
        publish_path()
    return 0


def _write_trajectory(path: Path, latest: dict[int, PoseMessage], session: str) -> None:
    ordered = sorted(latest.values(), key=lambda m: (m.timestamp, m.seq))
    traj = Trajectory.from_lists([m.timestamp for m in ordered], [m.T_wc for m in ordered])
    try:
        write_tum(path, traj, header=f"dimslam-poses, session {session}: camera-to-world")
    except OSError as e:
        raise DimslamError(f"{path}: cannot write the trajectory ({e.strerror})") from None
    log.info("wrote %d poses to %s", len(traj), path)


def run_poses(args: argparse.Namespace) -> int:
    """Print the poses; the TUM file, if asked for, is written however the loop ends."""
    cfg = transport_config(args)
    keys = Keys(cfg.session)
    stop = Stop()
    inbox = Inbox(POSE_QUEUE, keys.poses)
    refined = Inbox(POSE_QUEUE, keys.keyframes)
    stop.watch(inbox)
    latest: dict[int, PoseMessage] = {}
    topics = None
    if args.ros2:
        topics = Ros2Topics(args.ros2_pose_topic, args.ros2_path_topic, args.ros2_frame_id)

    def on_refined(sample: zenoh.Sample) -> None:
        refined.callback(sample)
        inbox.wake()  # the main loop waits on the tracker's inbox only

    try:
        with stop.on_signals(), open_session(cfg, "poses") as session:
            # Keep references: an unreferenced subscriber is undeclared (zenoh.md trap 4).
            subscribers = [pose_subscriber(session, keys.poses, inbox.callback)]
            if args.keyframes or topics is not None:
                subscribers.append(session.declare_subscriber(keys.keyframes, on_refined))
            bridge = None if topics is None else Ros2Bridge(session, topics)
            # Declared after the subscriptions: a peer that sees this token knows we listen.
            presence = Presence(session, keys, "poses", on_change=log_peer)
            code = _receive(args, keys, inbox, refined, stop, latest, bridge)
            presence.close()
            if bridge is not None:
                log.info("published %d poses as ROS 2 messages", bridge.published)
                bridge.close()
            for subscriber in subscribers:
                subscriber.undeclare()
    finally:
        if args.out is not None and latest:
            _write_trajectory(args.out, latest, cfg.session)
    if args.out is not None and not latest:
        log.warning("no pose received; %s not written", args.out)
    return code


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="dimslam-poses", description=POSES_DESCRIPTION)
    _poses_options(parser)
    add_transport_options(parser)
    return entry.main(parser, run_poses, argv)


if __name__ == "__main__":
    sys.exit(main())

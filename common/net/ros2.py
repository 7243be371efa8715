"""Poses as ROS 2 messages on the zenoh keys that zenoh-bridge-ros2dds routes to ROS 2.

zenoh-bridge-ros2dds (zenoh-plugin-ros2dds, `ros2_name_to_key_expr`) maps a ROS 2 topic `/a/b`
to the zenoh key `a/b` (the leading `/` dropped; a bridge configured with the namespace `/ns`
uses `ns/a/b`: give the topic as `/ns/a/b` here), and the payload is the message as DDS
carries it: CDR with its 4-byte encapsulation header. Publishing that payload on that key is
what a ROS 2 node subscribed to the topic receives through the bridge; `ros2 topic echo
/dimslam/pose` shows it (deploy/README.md).

Messages:
- each tracked frame: `geometry_msgs/msg/PoseStamped`, the camera's pose in the map frame
  (`T_wc`: OpenCV camera axes, x right, y down, z forward), stamped with the frame's own time;
  a lost frame publishes nothing (no pose is invented for it);
- each map refinement: `nav_msgs/msg/Path` of every keyframe's newest refined pose, oldest
  first, stamped with the newest keyframe's time.

CDR comes from `rosbags` (the `[ros]` extra), imported only here and only when a bridge is
asked for: the service itself never needs it.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from dataclasses import dataclass
from functools import cache

import numpy as np
import torch
import zenoh

from dimslam.common.errors import DimslamError
from dimslam.common.geometry.pose import matrix_to_quat
from dimslam.common.net.messages import PoseMessage
from dimslam.common.net.transport import publisher

POSE_TYPE = "geometry_msgs/msg/PoseStamped"
PATH_TYPE = "nav_msgs/msg/Path"

_NAME_RE = re.compile(r"^/?[A-Za-z][A-Za-z0-9_]*(/[A-Za-z][A-Za-z0-9_]*)*$")


def topic_key(topic: str) -> str:
    """The zenoh key zenoh-bridge-ros2dds uses for the ROS 2 topic `topic` (`/a/b` -> `a/b`).

    Raises:
        DimslamError: `topic` is not a valid ROS 2 topic name (no `~`, `{}` substitutions:
            the bridge sees fully resolved names only).
    """
    if not _NAME_RE.fullmatch(topic):
        raise DimslamError(
            f"ROS 2 topic {topic!r}: use names like /dimslam/pose (letters, digits and '_' "
            "between '/', each part starting with a letter)"
        )
    return topic.lstrip("/")


@cache
def _typestore():
    try:
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise DimslamError(
            "ROS 2 messages need the rosbags package: pip install 'dimslam[ros]'"
        ) from None
    return get_typestore(Stores.ROS2_HUMBLE)


def _stamp(seconds: float):
    """`builtin_interfaces/msg/Time` of a frame's time in seconds."""
    Time = _typestore().types["builtin_interfaces/msg/Time"]
    sec = int(np.floor(seconds))
    return Time(sec=sec, nanosec=min(int(round((seconds - sec) * 1e9)), 999_999_999))


def _pose(T_wc: np.ndarray):
    """`geometry_msgs/msg/Pose` of a camera-to-world `(4, 4)` pose."""
    types = _typestore().types
    q = matrix_to_quat(torch.from_numpy(np.asarray(T_wc, np.float64)[:3, :3])).tolist()
    x, y, z = (float(v) for v in T_wc[:3, 3])
    return types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=x, y=y, z=z),
        orientation=types["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
    )


def _stamped(msg: PoseMessage, frame_id: str):
    types = _typestore().types
    header = types["std_msgs/msg/Header"](stamp=_stamp(msg.timestamp), frame_id=frame_id)
    return types[POSE_TYPE](header=header, pose=_pose(msg.T_wc))


def pose_stamped(msg: PoseMessage, frame_id: str) -> bytes:
    """A tracked frame's pose as CDR-serialized `PoseStamped` (header included).

    Raises:
        ValueError: the frame is lost (it has no pose to send).
    """
    if msg.lost:
        raise ValueError(f"frame {msg.seq} is lost: it has no pose")
    return bytes(_typestore().serialize_cdr(_stamped(msg, frame_id), POSE_TYPE))


def path(poses: Iterable[PoseMessage], frame_id: str) -> bytes:
    """Poses (oldest first by frame time) as CDR-serialized `nav_msgs/msg/Path`."""
    ordered = sorted((m for m in poses if not m.lost), key=lambda m: (m.timestamp, m.seq))
    if not ordered:
        raise ValueError("a path needs at least one pose")
    types = _typestore().types
    header = types["std_msgs/msg/Header"](stamp=_stamp(ordered[-1].timestamp), frame_id=frame_id)
    return bytes(
        _typestore().serialize_cdr(
            types[PATH_TYPE](header=header, poses=[_stamped(m, frame_id) for m in ordered]),
            PATH_TYPE,
        )
    )


def decode(payload: bytes, typename: str):
    """A CDR payload as the `rosbags` message object (what a ROS 2 node would receive)."""
    return _typestore().deserialize_cdr(payload, typename)


@dataclass(frozen=True)
class Ros2Topics:
    """Where the bridge publishes: a ROS 2 topic per stream, and the frame the poses are in."""

    pose: str = "/dimslam/pose"
    path: str = "/dimslam/keyframes"
    frame_id: str = "map"

    def __post_init__(self) -> None:
        topic_key(self.pose)
        topic_key(self.path)
        if not self.frame_id:
            raise DimslamError("--ros2-frame-id: give the name of the map frame, e.g. map")
        _typestore()  # say now, not at the first pose, when rosbags is missing


class Ros2Bridge:
    """Publishes what a pose client receives as ROS 2 messages (`Ros2Topics`)."""

    def __init__(self, session: zenoh.Session, topics: Ros2Topics) -> None:
        self.topics = topics
        # Lossless like the service's own poses (transport.py): a subscriber expects one per frame.
        self._pose_pub = publisher(session, topic_key(topics.pose), lossless=True, urgent=True)
        self._path_pub = publisher(session, topic_key(topics.path), lossless=True)
        self.published = 0

    def pose(self, msg: PoseMessage) -> None:
        """Publish a tracked frame's pose (a lost frame: nothing)."""
        if not msg.lost:
            self._pose_pub.put(pose_stamped(msg, self.topics.frame_id))
            self.published += 1

    def keyframes(self, newest: Iterable[PoseMessage]) -> None:
        """Publish the path of the keyframes among `newest` (each frame's newest pose)."""
        keyframes = [m for m in newest if m.keyframe and not m.lost]
        if keyframes:
            self._path_pub.put(path(keyframes, self.topics.frame_id))

    def close(self) -> None:
        self._pose_pub.undeclare()
        self._path_pub.undeclare()

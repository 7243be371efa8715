"""`dimslam-camera` and `dimslam-poses` as a user runs them: real processes on loopback.

The test plays the tracker's side of the protocol (transport.py): it declares the "tracker"
liveliness token, subscribes to the frames and publishes poses. Every wait is bounded and
synchronised on liveliness, matching status or a received message, never on a sleep.
"""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh

from dimslam.common.io.datasets import open_dataset
from dimslam.common.io.synth import write_sequence
from dimslam.common.io.trajectory import read_tum
from dimslam.common.net import ros2
from dimslam.common.net.launch import loopback_endpoints
from dimslam.common.net.messages import EndOfStream, FrameMessage, PoseMessage, message_type
from dimslam.common.net.transport import Inbox, Keys, Presence, publisher

pytestmark = pytest.mark.integration

FRAMES = 12
WAIT_S = 120.0
"""Bound of every wait: far above what any step takes, so only a real hang reaches it (a
client's start alone took over 20 s under `nice` beside two SLAM runs on 2 cores)."""
BIN = Path(sys.executable).parent


class TrackerSide:
    """The tracker's end of the protocol, played by the test on its own listening endpoint."""

    def __init__(self, name: str | None = None, endpoint: str | None = None) -> None:
        self.name = name or f"test{uuid.uuid4().hex[:12]}"
        self.endpoint = endpoint or loopback_endpoints(1)[0]
        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("listen/endpoints", json.dumps([self.endpoint]))
        self.session = zenoh.open(conf)
        self.keys = Keys(self.name)
        self.frames = Inbox(1024, "frames")
        self._frames_sub = self.session.declare_subscriber(self.keys.frames, self.frames.callback)
        # Lossless here (the tracker uses DROP) so that no test depends on queue sizes.
        # As the tracker and mapper declare them: both express at one priority, so a message put
        # on one topic before another on the other arrives first (the test relies on it).
        self.poses = publisher(self.session, self.keys.poses, lossless=True, urgent=True)
        self.keyframes = publisher(self.session, self.keys.keyframes, lossless=True, urgent=True)
        self.presence = Presence(self.session, self.keys, "tracker")
        self._tokens = threading.Condition()
        self._clients = 0
        self._watch = self.session.liveliness().declare_subscriber(
            self.keys.alive("poses"), self._token, history=True
        )

    def _token(self, sample: zenoh.Sample) -> None:
        with self._tokens:
            self._clients += 1 if sample.kind == zenoh.SampleKind.PUT else -1
            self._tokens.notify_all()

    def wait_for_pose_client(self, keyframes: bool = False) -> None:
        """Until a dimslam-poses process listens (it declares its token after subscribing)."""
        with self._tokens:
            assert self._tokens.wait_for(lambda: self._clients > 0, WAIT_S), "no pose client"
        # The token can reach us before the subscriptions' routes do: wait for both to match.
        tick = threading.Event()
        for pub in (self.poses, self.keyframes) if keyframes else (self.poses,):
            deadline = time.monotonic() + WAIT_S
            while not pub.matching_status.matching:
                assert time.monotonic() < deadline, "the pose client's subscription never matched"
                tick.wait(0.02)

    def args(self) -> list[str]:
        return ["--session", self.name, "--connect", self.endpoint]

    def next_frame(self, timeout: float = WAIT_S) -> FrameMessage | EndOfStream:
        payload = self.frames.get(timeout)
        assert payload is not None, "no frame from the camera"
        if message_type(payload) == EndOfStream.TYPE:
            return EndOfStream.from_bytes(payload)
        return FrameMessage.from_bytes(payload)

    def publish_pose(self, seq: int, x: float = 0.0) -> int:
        """Publish a pose for frame `seq` (translated by `x`); returns when it was sent (ns)."""
        T = np.eye(4)
        T[0, 3] = x
        sent_ns = time.time_ns()
        self.poses.put(PoseMessage(seq, 1.0 + seq / 30, T, map_version=1).to_bytes())
        return sent_ns

    def close(self) -> None:
        self.session.close()


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("clients") / "scene"
    write_sequence(out, frames=FRAMES, width=64, height=48, seed=1)
    return out


@pytest.fixture
def tracker() -> Iterator[TrackerSide]:
    side = TrackerSide()
    yield side
    side.close()


@pytest.fixture
def start() -> Iterator:
    """Start a client process; any still running at the end of the test is killed."""
    procs: list[subprocess.Popen] = []

    def run(script: str, *args: str) -> subprocess.Popen:
        proc = subprocess.Popen(
            [str(BIN / script), *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        procs.append(proc)
        return proc

    yield run
    for proc in procs:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


def _finish(proc: subprocess.Popen) -> tuple[int, str, str]:
    out, err = proc.communicate(timeout=WAIT_S)
    return proc.returncode, out, err


def test_camera_sends_every_frame_in_order_then_the_end(scene, tracker, start):
    camera = start("dimslam-camera", str(scene), *tracker.args())
    messages = [tracker.next_frame() for _ in range(FRAMES + 1)]
    code, _, err = _finish(camera)
    assert code == 0, err

    frames, end = messages[:-1], messages[-1]
    assert isinstance(end, EndOfStream) and end.frames == FRAMES
    reader = open_dataset(scene)
    assert [f.seq for f in frames] == list(range(FRAMES))
    np.testing.assert_allclose([f.timestamp for f in frames], 1 + np.arange(FRAMES) / 30, atol=1e-6)
    assert all(f.camera == reader.camera and not f.live for f in frames)
    np.testing.assert_array_equal(frames[0].rgb, next(iter(reader)).rgb)
    # The recorded rate, 30 frames/s: the camera cannot have sent them faster.
    span_s = (frames[-1].stamp_ns - frames[0].stamp_ns) / 1e9
    assert span_s >= (FRAMES - 1) / 30 - 1e-3


def test_lockstep_never_runs_more_than_ahead_frames_beyond_the_poses(scene, tracker, start):
    ahead = 3
    camera = start(
        "dimslam-camera", str(scene), *tracker.args(), "--lockstep", "--ahead", str(ahead),
        "--rate", "0",
    )  # fmt: skip
    assert [tracker.next_frame().seq for _ in range(ahead)] == list(range(ahead))
    # Without poses, a camera as fast as allowed is held back (it would need milliseconds).
    assert tracker.frames.get(0.5) is None

    sent_ns = {}
    for seq in range(ahead, FRAMES):
        sent_ns[seq - ahead] = tracker.publish_pose(seq - ahead)
        frame = tracker.next_frame()
        assert frame.seq == seq
        # The frame was made only after the pose that let it through was published.
        assert frame.stamp_ns >= sent_ns[seq - ahead]
    end = tracker.next_frame()
    assert isinstance(end, EndOfStream) and end.frames == FRAMES
    code, _, err = _finish(camera)
    assert code == 0, err


def test_sigterm_stops_the_camera_with_an_end_of_stream(scene, tracker, start):
    camera = start("dimslam-camera", str(scene), *tracker.args(), "--rate", "2")
    assert [tracker.next_frame().seq for _ in range(2)] == [0, 1]
    camera.send_signal(signal.SIGTERM)
    code, _, err = _finish(camera)
    assert code == 0, err

    rest = []
    while not isinstance(message := tracker.next_frame(), EndOfStream):
        rest.append(message.seq)
    assert 2 <= message.frames < FRAMES
    assert rest == list(range(2, message.frames))


def test_camera_stops_when_the_tracker_goes_away(scene, tracker, start):
    camera = start("dimslam-camera", str(scene), *tracker.args(), "--rate", "2", "--grace", "1")
    assert tracker.next_frame().seq == 0
    tracker.close()  # its liveliness token vanishes with the session
    code, _, err = _finish(camera)
    assert code == 1 and "the tracker went away after" in err


def test_pose_client_prints_json_writes_the_file_and_survives_garbage(tracker, start, tmp_path):
    out = tmp_path / "poses.txt"
    client = start("dimslam-poses", *tracker.args(), "--json", "--keyframes", "--out", str(out))
    tracker.wait_for_pose_client(keyframes=True)

    # The refinement goes out twice, first and last: zenoh orders messages per publisher, not
    # across topics (the client's two subscriptions run on their own threads; the client stops
    # at the end), and a just-matched route may still miss the very first message (measured:
    # about 1 run in 5 lost one of the two placements, never both).
    refined = np.eye(4)
    refined[1, 3] = 0.5
    refinement = PoseMessage(0, 1.0, refined, keyframe=True, map_version=2).to_bytes()
    tracker.keyframes.put(refinement)
    tracker.poses.put(b"\x93not a message")
    tracker.poses.put(PoseMessage(9, 1.3, np.eye(4)).to_bytes()[:-7])  # truncated
    for seq in range(5):
        tracker.publish_pose(seq, x=seq)
    tracker.publish_pose(3, x=30.0)  # the same frame again: the latest pose wins in the file
    tracker.keyframes.put(refinement)
    tracker.poses.put(EndOfStream(5).to_bytes())

    code, stdout, err = _finish(client)
    assert code == 0, err
    # Both are unreadable msgpack: one kind of rejection, logged once (transport.Rejects).
    assert err.count("rejected a message") == 1 and "(1 so far): not a msgpack" in err
    records = [json.loads(line) for line in stdout.splitlines()]
    # Two topics: each keeps its order, but they may interleave either way.
    assert [r["seq"] for r in records if not r["refined"]] == [0, 1, 2, 3, 4, 3]
    refinements = [r for r in records if r["refined"]]
    assert 1 <= len(refinements) <= 2
    for kf in refinements:
        assert kf["seq"] == 0 and kf["keyframe"] and kf["map_version"] == 2
        np.testing.assert_allclose(kf["T_wc"], refined)

    written = read_tum(out)
    np.testing.assert_allclose(written.timestamps, 1 + np.arange(5) / 30, atol=1e-6)
    np.testing.assert_allclose(written.positions[:, 0], [0, 1, 2, 30, 4], atol=1e-6)
    np.testing.assert_allclose(written.poses[0], refined, atol=1e-6)


def test_pose_client_prints_tum_lines_and_stops_after_count(tracker, start, tmp_path):
    client = start("dimslam-poses", *tracker.args(), "--count", "3")
    tracker.wait_for_pose_client()
    quarter_turn = np.array([[0.0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]])
    for seq in range(5):
        tracker.poses.put(PoseMessage(seq, 2.0 + seq, quarter_turn).to_bytes())

    code, stdout, err = _finish(client)
    assert code == 0, err
    (tmp_path / "printed.txt").write_text(stdout)
    printed = read_tum(tmp_path / "printed.txt")
    np.testing.assert_allclose(printed.timestamps, [2, 3, 4])
    np.testing.assert_allclose(printed.poses, [quarter_turn] * 3, atol=1e-6)


def test_clients_give_up_when_nobody_is_there(scene, start):
    nobody = ["--session", f"test{uuid.uuid4().hex[:12]}"]
    nobody += ["--connect", loopback_endpoints(1)[0]]
    camera = start("dimslam-camera", str(scene), *nobody, "--wait-timeout", "0.5")
    poses = start("dimslam-poses", *nobody, "--timeout", "0.5")

    code, _, err = _finish(camera)
    assert code == 2 and "error: no tracker subscribed" in err
    code, _, err = _finish(poses)
    assert code == 1 and "no pose for 0.5 s" in err


def test_pose_client_republishes_poses_as_ros2_messages(tracker, start):
    """`--ros2`: each tracked pose as a CDR PoseStamped, the keyframes as a Path, on the keys
    zenoh-bridge-ros2dds routes to ROS 2 topics, decoded here with the same library."""
    prefix = f"t{uuid.uuid4().hex[:12]}"  # ROS 2 keys are not namespaced by session
    poses, paths = Inbox(64, "ros2 poses"), Inbox(64, "ros2 paths")
    subscribers = [
        tracker.session.declare_subscriber(f"{prefix}/pose", poses.callback),
        tracker.session.declare_subscriber(f"{prefix}/path", paths.callback),
    ]
    client = start(
        "dimslam-poses", *tracker.args(), "--ros2", "--ros2-frame-id", "world",
        "--ros2-pose-topic", f"/{prefix}/pose", "--ros2-path-topic", f"/{prefix}/path",
    )  # fmt: skip
    tracker.wait_for_pose_client(keyframes=True)

    quarter_turn = np.array([[0.0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]])
    refined = np.eye(4)
    refined[1, 3] = 0.5
    refinement = PoseMessage(0, 2.25, refined, keyframe=True, map_version=2).to_bytes()
    tracker.keyframes.put(refinement)  # twice, first and last: see the test above
    tracker.poses.put(PoseMessage(0, 2.25, quarter_turn, keyframe=True).to_bytes())
    tracker.poses.put(PoseMessage(1, 3.5, None, lost=True).to_bytes())  # no message for it
    tracker.poses.put(PoseMessage(2, 4.0, np.eye(4)).to_bytes())
    tracker.keyframes.put(refinement)
    tracker.poses.put(EndOfStream(3).to_bytes())
    code, _, err = _finish(client)
    assert code == 0, err

    received = [ros2.decode(poses.get(WAIT_S), ros2.POSE_TYPE) for _ in range(2)]
    assert poses.get(0.5) is None  # the lost frame published nothing
    first, second = received
    assert (first.header.stamp.sec, first.header.stamp.nanosec) == (2, 250_000_000)
    assert (second.header.stamp.sec, second.header.stamp.nanosec) == (4, 0)
    assert first.header.frame_id == second.header.frame_id == "world"
    p, q = first.pose.position, first.pose.orientation
    np.testing.assert_allclose([p.x, p.y, p.z], [1, 2, 3])
    half = np.sqrt(0.5)  # a quarter turn about z
    np.testing.assert_allclose([q.x, q.y, q.z, q.w], [0, 0, half, half], atol=1e-12)

    last = None
    while (payload := paths.get(0.5 if last else WAIT_S)) is not None:
        last = ros2.decode(payload, ros2.PATH_TYPE)
    assert last is not None, "no keyframe path"
    assert last.header.frame_id == "world" and len(last.poses) == 1  # frame 0, the keyframe
    kf = last.poses[0]
    assert kf.header.stamp.sec == 2
    np.testing.assert_allclose([kf.pose.position.x, kf.pose.position.y], [0, 0.5])
    for subscriber in subscribers:
        subscriber.undeclare()


def test_ros2_topic_names_are_checked(tracker, start):
    client = start("dimslam-poses", *tracker.args(), "--ros2", "--ros2-pose-topic", "/bad name")
    code, _, err = _finish(client)
    assert code == 2 and "ROS 2 topic '/bad name'" in err


def test_camera_waits_for_the_roles_it_is_told_to(scene, tracker, start):
    """`--also-wait-for viewer`: a tracker alone does not start the stream."""
    camera = start(
        "dimslam-camera", str(scene), *tracker.args(), "--also-wait-for", "viewer",
        "--wait-timeout", "2",
    )  # fmt: skip
    code, _, err = _finish(camera)
    assert code == 2 and "no viewer connected" in err
    assert tracker.frames.get(0.1) is None  # nothing was sent


def test_camera_holds_its_frames_for_a_tracker_that_comes_back(scene, tracker, start):
    """A restarted tracker (same session and endpoint) within `--grace`: the frames the one
    before did not pose go to it again, then the stream goes on, and no frame is sent while
    nobody is there to take it."""
    camera = start(
        "dimslam-camera", str(scene), *tracker.args(), "--lockstep", "--ahead", "2",
        "--rate", "0", "--grace", "60",
    )  # fmt: skip
    first = [tracker.next_frame().seq for _ in range(2)]
    tracker.publish_pose(1)
    assert tracker.next_frame().seq == 2
    tracker.close()  # its token vanishes: the camera waits instead of ending the stream
    back = TrackerSide(tracker.name, tracker.endpoint)
    try:
        nxt = back.next_frame()
        assert first == [0, 1] and isinstance(nxt, FrameMessage) and nxt.seq == 2
        seqs = [nxt.seq]
        while True:
            back.publish_pose(seqs[-1])
            msg = back.next_frame()
            if isinstance(msg, EndOfStream):
                break
            seqs.append(msg.seq)
        assert seqs == list(range(seqs[0], FRAMES))  # in order, to the end
        code, _, err = _finish(camera)
        assert code == 0, err
        assert "waiting 60 s for it to come back" in err
        # Frame 2, and frame 3 if the camera sent it before it saw the tracker leave.
        assert re.search(r"sending again [12] frame\(s\) without a pose", err), err
    finally:
        back.close()

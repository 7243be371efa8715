"""Several sessions through one router: each gets all its poses, none sees another's messages.

benchmarks/load.py's fleet with two sessions (camera, tracker and mapper each, tiny preset,
every process a client of one `dimslam-router` on loopback), each replaying the scene on a
clock of its own; its harness subscribes to every session's topics and names the session
each message came from. And the checker itself, fed a message of the wrong session.
"""

import numpy as np
import pytest
from repo import benchmark

from dimslam.common.geometry.camera import Camera
from dimslam.common.io.synth import write_sequence
from dimslam.common.net.messages import FrameMessage, PoseMessage
from dimslam.common.net.transport import Keys

FRAMES = 12
RATE = 4.0


@pytest.fixture
def load(monkeypatch):
    """benchmarks/load.py as a module (it imports benchmarks/faults.py beside it)."""
    return benchmark(monkeypatch, "load")


def test_the_checker_names_a_message_of_another_session(load):
    watch = load.Watch(["a", "b"])
    try:
        camera = Camera(8, 6, 100.0, 100.0, 4.0, 3.0)
        rgb = np.zeros((6, 8, 3), np.uint8)
        own = FrameMessage(0, 1.0, rgb, camera)  # session 0's clock
        other = PoseMessage(0, load.CLOCK_S + 1.0, np.eye(4))  # session 1's clock
        watch.take(Keys("a").frames, 0, own.to_bytes())
        watch.take(Keys("a").poses, 0, other.to_bytes())
        watch.take(Keys("c").poses, 0, other.to_bytes())
    finally:
        watch.close()
    assert watch.verdict("a") == ["poses: pose 0 of session 1"]
    assert watch.verdict("b") == []
    assert sum(watch.unknown.values()) == 1


@pytest.mark.e2e
def test_two_sessions_through_one_router_keep_to_their_own_messages(load, tmp_path):
    scene = tmp_path / "scene"
    write_sequence(scene, frames=FRAMES, width=160, height=120, seed=0)
    # Every frame sent (no live skipping), so every frame must get its pose.
    fleet = load.run_fleet(2, scene, tmp_path / "fleet", RATE, live=False)
    assert fleet["unknown"] == 0
    for r in fleet["per_session"]:
        assert r["exits"] == {"mapper": 0, "tracker": 0, "camera": 0}, r["session"]
        assert r["frames_sent"] == FRAMES, r
        assert r["poses"] == FRAMES, r
        assert r["map_versions"] > 0, r
        assert (r["foreign"], r["foreign_examples"]) == (0, []), r["session"]
        assert r["final_frames"] == FRAMES, r

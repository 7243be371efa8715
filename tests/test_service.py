"""The service end to end: camera, tracker and mapper as real processes over zenoh on loopback.

1. `dimslam run` (service mode) on a freshly rendered sequence with the tiny preset: exit 0, a
   pose for every frame at the pose client, an ATE bound from the project's evaluator.
2. The mapper is SIGKILLed mid-run: the tracker notices, keeps publishing a pose for every
   frame on the last map, and exits 0 at the end of the stream.
"""

import json
import os
import signal
import subprocess
import sys
import threading

import pytest

from dimslam.common.cli import main
from dimslam.common.launch import free_port
from dimslam.common.messages import PoseMessage, message_type
from dimslam.common.trajectory import read_tum
from dimslam.common.transport import Inbox, Keys, Presence, TransportConfig, open_session

FRAMES = 36


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    out = tmp_path_factory.mktemp("service") / "seq"
    assert main(["synth", str(out), "--frames", str(FRAMES), "--size", "160x120"]) == 0
    return out


def test_run_through_the_service(sequence, tmp_path):
    out = tmp_path / "run"
    assert main(["run", str(sequence), "--out", str(out), "--preset", "tiny", "--no-mesh"]) == 0
    assert len(read_tum(out / "trajectory.txt")) == FRAMES
    assert len(read_tum(out / "trajectory_online.txt")) == FRAMES
    assert len(read_tum(out / "poses_received.txt")) == FRAMES  # no pose lost on the way
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["matched"] == FRAMES and metrics["poses_received"] == FRAMES
    # A lost tracker scores tens of centimetres; a working one ~0.5-1 cm here.
    assert metrics["ate_rmse_m"] < 0.04
    assert metrics["online_ate_rmse_m"] < 0.04


def _start(module: str, *args: str, log) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", module, *args], stdout=log, stderr=subprocess.STDOUT
    )


def test_tracker_keeps_publishing_when_the_mapper_dies(sequence, tmp_path):
    tracker_ep = f"tcp/127.0.0.1:{free_port()}"
    mapper_ep = f"tcp/127.0.0.1:{free_port()}"
    session = f"kill{os.getpid()}"
    common = ["--session", session, "--preset", "tiny", "--threads", "1"]
    logs = {r: open(tmp_path / f"{r}.log", "w") for r in ("mapper", "tracker", "camera")}  # noqa: SIM115
    transport = TransportConfig(session, connect=(tracker_ep, mapper_ep))
    with open_session(transport, "test") as zs:
        keys = Keys(session)
        poses = Inbox(1000, "poses")
        sub = zs.declare_subscriber(keys.poses, poses.callback)
        gone = threading.Event()
        presence = Presence(
            zs, keys, "test", lambda role, alive: role == "mapper" and not alive and gone.set()
        )
        procs = {
            "mapper": _start(
                "dimslam.mapper.cli", "--listen", mapper_ep, "--connect", tracker_ep, *common,
                log=logs["mapper"],
            ),
            "tracker": _start(
                "dimslam.tracker.cli", "--listen", tracker_ep, "--connect", mapper_ep, *common,
                log=logs["tracker"],
            ),
        }  # fmt: skip
        try:
            assert presence.wait_for("tracker", 60) and presence.wait_for("mapper", 60)
            procs["camera"] = _start(
                "dimslam.common.clients", "camera", str(sequence), "--lockstep", "--ahead", "12",
                "--rate", "0", "--width", "80", "--connect", tracker_ep, "--session", session,
                log=logs["camera"],
            )  # fmt: skip
            seen: set[int] = set()
            ended = False
            while not ended:
                payload = poses.get(120)
                assert payload is not None, "no pose for 120 s"
                if message_type(payload) == "end":
                    ended = True
                    continue
                seen.add(PoseMessage.from_bytes(payload).seq)
                if len(seen) == 16 and procs["mapper"].poll() is None:
                    procs["mapper"].send_signal(signal.SIGKILL)
                    assert gone.wait(30), "the mapper's liveliness token did not vanish"
                    killed_at = len(seen)
            assert killed_at == 16
            assert seen == set(range(FRAMES))  # every frame got a pose, before and after
            assert procs["tracker"].wait(60) == 0
            assert procs["camera"].wait(60) == 0
        finally:
            for p in procs.values():
                if p.poll() is None:
                    p.kill()
                p.wait()
            for f in logs.values():
                f.close()
            presence.close()
            sub.undeclare()
    assert "the mapper is gone" in (tmp_path / "tracker.log").read_text()

"""The service end to end: camera, tracker and mapper as real processes over zenoh on loopback.

1. `dimslam run` (service mode) on a freshly rendered sequence with the tiny preset: exit 0, a
   pose for every frame at the pose client, an ATE bound from the project's evaluator.
2. The mapper is SIGKILLed mid-run: the tracker notices, keeps publishing a pose for every
   frame on the last map, and exits 0 at the end of the stream.
"""

import json
import os
import re
import signal
import subprocess
import sys
import threading
from contextlib import ExitStack

import numpy as np
import pytest
from covered import covered_copy

from dimslam.common.cli import main
from dimslam.common.io.trajectory import read_tum
from dimslam.common.net.launch import loopback_endpoints
from dimslam.common.net.messages import MapperCheckpoint, MapSnapshot, PoseMessage, message_type
from dimslam.common.net.transport import Inbox, Keys, Presence, TransportConfig, open_session

pytestmark = pytest.mark.e2e

FRAMES = 36


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    out = tmp_path_factory.mktemp("service") / "seq"
    assert main(["synth", str(out), "--frames", str(FRAMES), "--size", "160x120"]) == 0
    return out


@pytest.fixture(scope="module")
def service_run(sequence, tmp_path_factory):
    """One `dimslam run` through the service, watched by the viewer into an .rrd file."""
    out = tmp_path_factory.mktemp("service") / "run"
    # Mapping rounds of 40 iterations are slower than tracking 5 frames: a tracker left free
    # would run ahead and the mapper would take several batches in one round.
    args = ["--preset", "tiny", "--mapper.iters", "40", "--no-mesh"]
    args += ["--rerun-save", str(out / "run.rrd")]
    assert main(["run", str(sequence), "--out", str(out), *args]) == 0
    return out


def test_run_through_the_service(service_run):
    out = service_run
    assert len(read_tum(out / "trajectory.txt")) == FRAMES
    assert len(read_tum(out / "trajectory_online.txt")) == FRAMES
    assert len(read_tum(out / "poses_received.txt")) == FRAMES  # no pose lost on the way
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["matched"] == FRAMES and metrics["poses_received"] == FRAMES
    # A lost tracker scores tens of centimetres; a working one ~0.5-1 cm here.
    assert metrics["ate_rmse_m"] < 0.04
    assert metrics["online_ate_rmse_m"] < 0.04
    # Initialization plus one round per batch (frames 10, 15, ..., 35), none taken together;
    # the tracker waited for each round's snapshot before its next frame (launch.MAP_LAG):
    # no frame was tracked while a batch it had sent was still being mapped.
    assert "mapper.service: 7 rounds" in (out / "mapper.log").read_text()
    assert json.loads((out / "config.json").read_text())["map_lag"] == 0
    stats = json.loads((out / "tracker_stats.json").read_text())
    assert stats["tracked"] > 0 and stats["frames_mapper_busy"] == 0


def test_the_viewer_records_the_run_as_rerun_shows_it(service_run):
    """The .rrd the viewer wrote, read back: images, the tracked path with one point per
    frame, the aligned ground truth, keyframe frusta, rendered depth and the mapper's mesh."""
    from rerun.chunk import RrdReader

    rows: dict[str, int] = {}
    columns: dict[str, set[str]] = {}
    images = 0
    for chunk in RrdReader(service_run / "run.rrd").stream():
        rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
        batch = chunk.to_record_batch()
        columns.setdefault(chunk.entity_path, set()).update(batch.schema.names)
        if "EncodedImage:blob" in batch.schema.names:
            images += sum(b is not None for b in batch.column("EncodedImage:blob").to_pylist())
        if chunk.entity_path == "/world/trajectory":
            strips = batch.column("LineStrips3D:strips").to_pylist()
            longest = max(len(s[0]) for s in strips if s)
    # The camera waits for the viewer as for the tracker: every frame is shown.
    assert images == FRAMES
    assert rows["/world/camera"] == FRAMES  # one pose per frame, none lost
    assert longest == FRAMES
    assert {"Pinhole:image_from_camera", "Transform3D:translation"} <= columns["/world/keyframes/0"]
    assert rows["/world/ground_truth"] >= 1
    assert rows["/keyframe/depth"] >= 1 and "DepthImage:buffer" in columns["/keyframe/depth"]
    assert "Mesh3D:vertex_positions" in columns["/world/mesh"]
    assert "shown:" in (service_run / "viewer.log").read_text()


def test_evo_agrees_with_the_evaluator(service_run, sequence, tmp_path):
    """evo, the field's reader of TUM trajectories, on the run's trajectory: the same ATE."""
    evo = subprocess.run(
        [os.path.join(os.path.dirname(sys.executable), "evo_ape"), "tum",
         str(sequence / "groundtruth.txt"), str(service_run / "trajectory.txt"),
         "--align", "--correct_scale"],
        capture_output=True, text=True, env={**os.environ, "HOME": str(tmp_path)}, timeout=120,
    )  # fmt: skip
    assert evo.returncode == 0, evo.stderr
    rmse = float(re.search(r"rmse\s+([0-9.eE+-]+)", evo.stdout).group(1))
    ours = json.loads((service_run / "metrics.json").read_text())["ate_rmse_m"]
    assert abs(rmse - ours) <= 1e-4, (rmse, ours)


def test_the_service_in_lockstep_computes_what_one_process_computes(sequence, tmp_path):
    """The same settings and seed through the service and in one process: the same final
    trajectory, to the last digit. With global refinement on, a mapper left to refine while
    it waits for a batch would publish maps one process never makes (`mapper.idle_chunks`,
    0 in lockstep)."""
    # One thread in each process, as in one process: another thread count sums in another
    # order, and chaotic runs part at the first rounding.
    args = ["--preset", "tiny", "--mapper.iters", "40", "--no-mesh", "--threads", "1"]
    args += ["--seed", "3"]
    args += ["--mapper.global_every", "2"]
    service, alone = tmp_path / "service", tmp_path / "alone"
    assert main(["run", str(sequence), "--out", str(service), *args]) == 0
    assert main(["run", str(sequence), "--out", str(alone), "--single-process", *args]) == 0
    config = json.loads((service / "config.json").read_text())
    assert config["map_lag"] == 0 and config["mapper"]["idle_chunks"] == 0
    assert "0 idle refinement chunks" in (service / "mapper.log").read_text()
    ours, theirs = read_tum(service / "trajectory.txt"), read_tum(alone / "trajectory.txt")
    assert len(ours) == len(theirs) == FRAMES
    assert np.array_equal(ours.poses, theirs.poses)


def test_map_lag_1_lets_the_tracker_run_a_round_ahead(sequence, tmp_path):
    out = tmp_path / "run"
    args = ["--preset", "tiny", "--mapper.iters", "40", "--no-mesh", "--map-lag", "1"]
    assert main(["run", str(sequence), "--out", str(out), *args]) == 0
    assert len(read_tum(out / "poses_received.txt")) == FRAMES
    assert json.loads((out / "config.json").read_text())["map_lag"] == 1
    # Mapping rounds of 40 iterations are slower than tracking 5 frames, yet no two batches
    # were taken into one round: the tracker stayed within one round of the map.
    assert "mapper.service: 7 rounds" in (out / "mapper.log").read_text()


def test_a_lost_tracker_hands_over_its_frames_and_relocalizes(sequence, tmp_path):
    """Ten frames blanked mid-sequence: each is published lost (no pose invented), the
    frames tracked before the loss go to the mapper at once, and tracking resumes."""
    seq = covered_copy(sequence, tmp_path / "seq", 18, 28)
    out = tmp_path / "run"
    args = ["--preset", "tiny", "--mapper.iters", "40", "--no-mesh"]
    assert main(["run", str(seq), "--out", str(out), *args]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames_lost"] == 10 and metrics["matched"] == FRAMES - 10
    stamps = read_tum(sequence / "groundtruth.txt").timestamps
    tracked = list(read_tum(out / "trajectory.txt").timestamps)
    assert tracked == pytest.approx([*stamps[:18], *stamps[28:]])
    assert "relocalized at frame 28 after 10 lost frames" in (out / "tracker.log").read_text()
    # Rounds: the initialization (frames 0-7), frames 8-10, 11-15, 16-17 (handed over at
    # the loss, off the 5-frame rhythm), 28-30 and 31-35.
    assert "mapper.service: 6 rounds" in (out / "mapper.log").read_text()
    assert metrics["ate_rmse_m"] < 0.04


def test_a_sparse_map_travels_between_the_processes(sequence, tmp_path):
    """Snapshots of a growing map (int64 block coordinates, an atlas that changes shape)
    reach the tracker, which tracks on them as on the dense map."""
    out = tmp_path / "run"
    args = ["--preset", "tiny", "--mapper.iters", "40", "--no-mesh", "--map.grids", "sparse"]
    assert main(["run", str(sequence), "--out", str(out), *args]) == 0
    assert len(read_tum(out / "poses_received.txt")) == FRAMES
    assert json.loads((out / "metrics.json").read_text())["ate_rmse_m"] < 0.04
    assert "rejected a message" not in (out / "tracker.log").read_text()
    snap = MapSnapshot.from_bytes((out / "map.msgpack").read_bytes())
    assert snap.state["geometry.blocks"].dtype == np.int64 and len(snap.state["geometry.blocks"])


def test_the_mappers_end_of_run_bundle_adjustment_reaches_the_trajectory(sequence, tmp_path):
    """`--bundle.enabled true` in the service: the mapper adjusts its keyframes when the
    stream ends and publishes them; the trajectory written is the adjusted one. With
    `--bundle.flow`, every frame the mapper gets feeds the flow's tracks."""
    out = tmp_path / "run"
    args = ["--preset", "tiny", "--mapper.iters", "40", "--no-mesh", "--bundle.enabled", "true"]
    args += ["--bundle.flow", "100", "--bundle.init_frames", "true"]
    assert main(["run", str(sequence), "--out", str(out), *args]) == 0
    log = (out / "mapper.log").read_text()
    # `--bundle.init_frames` reaches the mapper (on this scene the rule marks frame 0 alone).
    assert "the initialization's frames the tracker's rule marks: frames 0" in log
    adjusted = re.search(r"and (\d+) flow tracks", log)
    assert adjusted is not None and int(adjusted.group(1)) > 10
    final, online = read_tum(out / "trajectory.txt"), read_tum(out / "trajectory_online.txt")
    assert len(final) == len(online) == FRAMES
    assert not np.allclose(final.poses, online.poses, atol=1e-6)
    assert json.loads((out / "metrics.json").read_text())["ate_rmse_m"] < 0.04


def test_realtime_replays_the_sequence_as_a_live_camera(sequence, tmp_path, capsys):
    """`--realtime`: the camera holds only until the map exists, then sends at the rate and
    never waits; the tracker keeps the newest frame when busy and reports what it did; with
    `--bundle.live`, the mapper describes the keyframes its live rounds left at the end and
    adjusts them."""
    out = tmp_path / "run"
    args = ["--preset", "tiny", "--no-mesh", "--realtime", "10", "--mapper.live_iters", "2"]
    args += ["--tracker.live_min_inliers", "0.2", "--bundle.enabled", "true"]
    args += ["--bundle.live", "true"]
    assert main(["run", str(sequence), "--out", str(out), *args]) == 0
    assert "frames received" in capsys.readouterr().out
    # The tracker's batches say the frames are live: the mapper's rounds on them are short.
    log = (out / "mapper.log").read_text()
    summary = re.search(r"(\d+) rounds \((\d+) short", log)
    assert summary and 0 < int(summary[2]) == int(summary[1]) - 1  # all but the initialization
    described = re.search(r"described (\d+) keyframes the live rounds left", log)
    assert described and int(described[1]) > 0
    assert "feature bundle adjustment of" in log
    # The tracker judges a live stream's frames by the live share of inliers.
    assert "a live stream: a frame is lost under 20 % inliers" in (out / "tracker.log").read_text()
    metrics = json.loads((out / "metrics.json").read_text())
    assert json.loads((out / "config.json").read_text())["realtime_fps"] == 10
    received, processed = metrics["frames_received"], metrics["frames"]
    # Every frame received is processed (collected for the map, tracked or lost) or dropped
    # for a newer one; every processed frame not lost has its pose at the client.
    assert 0 < received <= FRAMES
    assert processed + metrics["frames_dropped"] >= received
    assert metrics["poses_received"] == processed - metrics["frames_lost"]
    # How many it keeps up with depends on the machine's load; none waited for the map to
    # initialize (the camera held those frames back).
    assert metrics["tracked"] > 0
    assert 0 < metrics["latency_ms_p50"] <= metrics["latency_ms_p95"] < 10_000
    assert metrics["matched"] == len(read_tum(out / "trajectory.txt"))
    # Live, the tracker takes the newest frame whenever it is free: the fewer it keeps up
    # with, the larger the motion between them and the staler the map (quiet machine: under
    # 5 cm; 13.6 cm with seven other processes on the 2 cores). Here: poses in the scene.
    assert metrics["ate_rmse_m"] < 0.25


def test_an_idle_mapper_refines_globally_and_publishes_it(sequence, tmp_path):
    """`mapper.global_every`: between batches of a slow live camera the mapper refines
    keyframes anywhere on the path and the map, and publishes each chunk as a snapshot."""
    out = tmp_path / "run"
    args = ["--preset", "tiny", "--no-mesh", "--realtime", "3", "--mapper.global_every", "2"]
    args += ["--mapper.iters", "4"]
    assert main(["run", str(sequence), "--out", str(out), *args]) == 0
    summary = re.search(
        r"(\d+) rounds .*, (\d+) idle refinement chunks, map version (\d+)",
        (out / "mapper.log").read_text(),
    )
    assert summary, "the mapper's summary line is missing"
    rounds, idle, version = map(int, summary.groups())
    # A batch every 1.7 s and rounds of a fraction of that: the mapper waited, and refined.
    assert idle > 0 and version == rounds + idle
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["poses_received"] == metrics["frames"] - metrics["frames_lost"]
    assert metrics["ate_rmse_m"] < 0.25


def _start(module: str, *args: str, log) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", module, *args], stdout=log, stderr=subprocess.STDOUT
    )


def test_tracker_keeps_publishing_when_the_mapper_dies(sequence, tmp_path):
    tracker_ep, mapper_ep = loopback_endpoints(2)
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
            # With bounded staleness, the mapper that does not come back is waited for only
            # --mapper-grace seconds.
            "tracker": _start(
                "dimslam.tracker.cli", "--listen", tracker_ep, "--connect", mapper_ep, *common,
                "--map-lag", "0", "--mapper-grace", "2",
                log=logs["tracker"],
            ),
        }  # fmt: skip
        try:
            assert presence.wait_for("tracker", 60) and presence.wait_for("mapper", 60)
            procs["camera"] = _start(
                "dimslam.common.net.camera", str(sequence), "--lockstep",
                "--ahead", "12", "--rate", "0", "--width", "80", "--connect", tracker_ep,
                "--session", session,
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
    log = (tmp_path / "tracker.log").read_text()
    assert "the mapper is gone" in log and "did not come back within 2 s" in log


class Service:
    """Service processes of one test session, with a harness session watching poses and maps.

    Use as a context manager: the harness subscribes to the poses and the map snapshots
    (`poses`, `maps`) and watches liveliness (`presence`); at the end every process is killed.
    """

    def __init__(self, tmp_path, name: str) -> None:
        self.tmp = tmp_path
        self.tracker_ep, self.mapper_ep = loopback_endpoints(2)
        self.session = f"{name}{os.getpid()}"
        self.procs: list[subprocess.Popen] = []
        self.logs: list = []
        self.poses, self.maps = Inbox(1000, "poses"), Inbox(1000, "maps")
        self._stack = ExitStack()

    def __enter__(self) -> "Service":
        transport = TransportConfig(self.session, connect=(self.tracker_ep, self.mapper_ep))
        zs = self._stack.enter_context(open_session(transport, "test"))
        keys = Keys(self.session)
        for key, inbox in ((keys.poses, self.poses), (keys.map, self.maps)):
            sub = zs.declare_subscriber(key, inbox.callback)
            self._stack.callback(sub.undeclare)
        self.presence = Presence(zs, keys, "test")
        self._stack.callback(self.presence.close)
        self._stack.callback(self.close)
        return self

    def __exit__(self, *exc) -> None:
        self._stack.close()

    def start(self, role: str, *extra: str) -> subprocess.Popen:
        common = ["--session", self.session]
        if role == "mapper":
            argv = ["dimslam.mapper.cli", "--listen", self.mapper_ep, "--connect", self.tracker_ep]
            argv += [*common, "--preset", "tiny", "--threads", "1"]
        elif role == "tracker":
            argv = ["dimslam.tracker.cli", "--listen", self.tracker_ep, "--connect", self.mapper_ep]
            argv += [*common, "--preset", "tiny", "--threads", "1"]
        else:
            argv = ["dimslam.common.net.camera", *extra[:1], "--lockstep", "--ahead", "12"]
            argv += ["--rate", "0", "--width", "80", "--connect", self.tracker_ep, *common]
            extra = extra[1:]
        log = open(self.tmp / f"{role}{len(self.procs)}.log", "w")  # noqa: SIM115
        self.logs.append(log)
        proc = _start(*argv, *extra, log=log)
        self.procs.append(proc)
        return proc

    def log(self, role: str) -> str:
        return "".join(p.read_text() for p in sorted(self.tmp.glob(f"{role}*.log")))

    def close(self) -> None:
        for p in self.procs:
            if p.poll() is None:
                p.kill()
            p.wait()
        for f in self.logs:
            f.close()


def _poses_until_end(inbox: Inbox, on_pose=None) -> dict[int, PoseMessage]:
    seen: dict[int, PoseMessage] = {}
    while True:
        payload = inbox.get(120)
        assert payload is not None, "no pose for 120 s"
        if message_type(payload) == "end":
            return seen
        msg = PoseMessage.from_bytes(payload)
        seen[msg.seq] = msg
        if on_pose is not None:
            on_pose(len(seen))


def test_a_restarted_mapper_gets_the_trackers_map(sequence, tmp_path):
    with Service(tmp_path, "restart") as svc:
        mapper = svc.start("mapper")
        # The tracker holds the stream (bounded staleness) until the new mapper is up: on a
        # loaded machine a new mapper's start alone can outlast the stream.
        svc.start("tracker", "--map-lag", "1", "--mapper-grace", "600")
        assert svc.presence.wait_for("tracker", 60) and svc.presence.wait_for("mapper", 60)
        svc.start("camera", str(sequence), "--rate", "2")
        restarted = []

        def restart(count: int) -> None:
            if count == 14 and not restarted:
                mapper.send_signal(signal.SIGKILL)
                mapper.wait()
                svc.maps.drain()
                restarted.append(svc.start("mapper"))

        seen = _poses_until_end(svc.poses, restart)
        assert set(seen) == set(range(FRAMES))
        assert "the new mapper has no map: sending map version" in svc.log("tracker")
        assert "continuing the tracker's map version" in svc.log("mapper")
        # Its first round may still run after the stream's end: wait for it, bounded.
        snap = svc.maps.get(120)
        assert snap is not None, "the restarted mapper published no snapshot"


def test_a_killed_mapper_resumes_from_its_checkpoint(sequence, tmp_path):
    """SIGKILL, then `--resume`: the new mapper goes on with its own map from disk (no map is
    asked of the tracker), the tracker (bounded staleness) waits for it and takes its maps,
    every frame gets a pose, and SIGTERM writes a checkpoint holding the whole stream."""
    ckpt = tmp_path / "ckpt"
    saving = ["--checkpoint", str(ckpt), "--checkpoint-every", "1"]
    with Service(tmp_path, "resume") as svc:
        mapper = svc.start("mapper", *saving)
        svc.start("tracker", "--map-lag", "1", "--mapper-grace", "600")
        assert svc.presence.wait_for("tracker", 60) and svc.presence.wait_for("mapper", 60)
        svc.start("camera", str(sequence), "--rate", "2")
        resumed = []

        def restart(count: int) -> None:
            if count == 18 and not resumed:
                mapper.send_signal(signal.SIGKILL)
                mapper.wait()
                svc.maps.drain()
                # Its own checkpoints only at exit: what is on disk after SIGTERM is its flush.
                later = ["--checkpoint", str(ckpt), "--checkpoint-every", "1000"]
                resumed.append(svc.start("mapper", "--resume", str(ckpt), *later))

        seen = _poses_until_end(svc.poses, restart)
        assert set(seen) == set(range(FRAMES))
        log = svc.log("mapper")
        assert "resumed from" in log and "continuing the tracker's map" not in log
        tracker_log = svc.log("tracker")
        assert "the new mapper has no map" not in tracker_log
        assert "waiting up to 600 s for it to come back" in tracker_log
        assert "did not come back" not in tracker_log
        snap = svc.maps.get(120)
        assert snap is not None, "the resumed mapper published no snapshot"
        assert resumed[0].poll() is None
        resumed[0].send_signal(signal.SIGTERM)
        assert resumed[0].wait(60) == 0
    checkpoint = MapperCheckpoint.from_bytes((ckpt / "checkpoint.msgpack").read_bytes())
    assert sorted(seq for seq, _ in checkpoint.frames) == list(range(FRAMES))
    assert checkpoint.snapshot.version > 1 and checkpoint.rounds > 1
    assert set(checkpoint.snapshot.keyframes) <= {
        f.seq for b in checkpoint.images for f in b.frames
    }


def test_a_mapper_refuses_a_checkpoint_it_cannot_use(tmp_path, capsys):
    from dimslam.mapper.cli import main as mapper_main

    (tmp_path / "checkpoint.msgpack").write_bytes(b"\x93not a checkpoint")
    args = ["--resume", str(tmp_path), "--session", f"bad{os.getpid()}", "--preset", "tiny"]
    assert mapper_main(args) == 2
    assert "checkpoint.msgpack is not a checkpoint" in capsys.readouterr().err
    assert mapper_main(["--resume", str(tmp_path / "none"), *args[2:]]) == 2
    assert "cannot read checkpoint.msgpack" in capsys.readouterr().err


def test_a_late_tracker_continues_the_running_map(sequence, tmp_path):
    half = FRAMES // 2
    with Service(tmp_path, "late") as svc:
        svc.start("mapper")
        first = svc.start("tracker")
        assert svc.presence.wait_for("tracker", 60) and svc.presence.wait_for("mapper", 60)
        svc.start("camera", str(sequence), "--end", str(half))
        before = _poses_until_end(svc.poses)
        assert first.wait(60) == 0
        # The running map: the mapper has mapped what the first tracker sent, up to its last
        # frame. How slowly a busy machine gets there is not what this test is about.
        mapped: set[int] = set()
        while half - 1 not in mapped:
            payload = svc.maps.get(120)
            assert payload is not None, (
                f"the mapper stopped having mapped {sorted(mapped)}:\n{svc.log('mapper')}"
            )
            mapped |= set(MapSnapshot.from_bytes(payload).poses)
        late = svc.start("tracker")
        assert svc.presence.wait_for("tracker", 60)
        svc.start("camera", str(sequence), "--start", str(half))
        after = _poses_until_end(svc.poses)
        assert late.wait(60) == 0
    assert "this tracker continues it" in svc.log("tracker")
    assert set(before) == set(range(half)) and set(after) == set(range(FRAMES - half))
    # One trajectory in one map frame: a tracker that started a new map instead would restart
    # at the identity, as far from the first tracker's last pose as that is from the origin.
    # (Not an ATE bound: how far the first map carries depends on how busy the machine keeps
    # the mapper; a loaded one gave 8.5 cm with every frame tracked on the first map.)
    last = before[half - 1].T_wc[:3, 3]
    gap = np.linalg.norm(after[0].T_wc[:3, 3] - last)
    assert gap < 0.3 * np.linalg.norm(last), (gap, last)


def test_start_order_is_free_and_sigterm_flushes_every_output(sequence, tmp_path):
    """Tracker and camera first: frames wait for a mapper started later; then SIGTERM to both
    service processes mid-stream: each exits 0 promptly with its outputs written."""
    out = tmp_path / "out"
    with Service(tmp_path, "order") as svc:
        tracker = svc.start("tracker", "--out", str(out))
        assert svc.presence.wait_for("tracker", 60)
        svc.start("camera", str(sequence))
        assert svc.poses.get(5) is None  # no mapper, no map: nothing can be tracked yet
        mapper = svc.start("mapper", "--out", str(out))
        seen = set()
        while len(seen) < 16:
            payload = svc.poses.get(120)
            assert payload is not None, "no pose after the mapper started"
            seen.add(PoseMessage.from_bytes(payload).seq)
        assert seen >= set(range(8))  # the frames held before the mapper came were tracked
        for p in (tracker, mapper):
            p.send_signal(signal.SIGTERM)
        assert tracker.wait(30) == 0 and mapper.wait(30) == 0
    online = read_tum(out / "trajectory_online.txt")
    final = read_tum(out / "trajectory.txt")
    assert len(online) >= 16 and len(final) >= 13
    assert (out / "map.msgpack").stat().st_size > 0

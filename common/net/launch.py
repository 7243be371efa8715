"""`dimslam run` through the real service: mapper, tracker, camera and a pose client as processes.

All four run on loopback in a session of their own (free ports, scouting off); the camera
streams in lockstep so that every frame is tracked, and the tracker runs at most `map_lag`
(default `MAP_LAG`) mapping rounds ahead of the map, so that every round is mapped (an offline
run's choice; live use leaves the tracker free). The mapper writes the final poses
(`trajectory.txt`, keyframes refined, other frames re-anchored to their keyframe), the tracker
the poses as first published (`trajectory_online.txt`), the pose client what a subscriber
received (`poses_received.txt`). Each process logs to `<role>.log` in the output folder.
"""

from __future__ import annotations

import json
import logging
import os
import random
import socket
import subprocess
import sys
import time
from contextlib import ExitStack
from dataclasses import replace
from pathlib import Path

import torch

from dimslam.common.config import SlamConfig
from dimslam.common.errors import DimslamError
from dimslam.common.eval.report import RunSummary, report_run
from dimslam.common.io.trajectory import read_tum
from dimslam.common.options import flat_settings, to_dict

log = logging.getLogger(__name__)

STOP_GRACE_S = 20.0
"""How long a process may take to flush and exit after SIGTERM before it is killed."""
MAP_LAG = 0
"""Mapping rounds the tracker may run ahead of the map (`dimslam-tracker --map-lag`): none,
so that each frame is tracked on the map one process would track it on, and (with the
mapper's idle chunks off, `run_service`) the service computes what one process computes. 1
overlaps tracking with the round in progress, but tracks a round behind: room0 3.19 cm
against one process's 1.51 over 3 seeds (docs/results.md, "The service computes what one
process computes"). Without a bound a tracker faster than its mapper tracks most frames on
a map rounds old, and the mapper, taking its pending batches together, ran 26 rounds for
7-Scenes' 500 frames instead of 100."""


LISTEN_PORTS = (20000, 32768)
"""Where `loopback_endpoints` looks for free ports when the system's own range for outgoing
connections cannot be read: Linux's default starts at 32768."""


def _listen_ports() -> tuple[int, int]:
    """A range of ports `[lo, hi)` below the one the system gives outgoing connections."""
    try:
        lo = int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return LISTEN_PORTS
    return (max(1024, lo // 2), lo) if lo > 2048 else LISTEN_PORTS


def loopback_endpoints(count: int) -> list[str]:
    """`count` distinct free loopback endpoints, `tcp/127.0.0.1:<port>`.

    The ports lie below the system's range for outgoing connections: a port the system hands
    out (bind to 0) may also be handed to a process's outgoing connection before the process
    that is to listen on it has started (`make demo` once failed so, the mapper's port taken
    while the tracker connected). The sockets stay bound until all ports are chosen, so that
    one call never repeats a port.
    """
    lo, hi = _listen_ports()
    rng = random.Random()
    with ExitStack() as stack:
        ports: list[int] = []
        for _ in range(count * 200):
            s = stack.enter_context(socket.socket())
            try:
                s.bind(("127.0.0.1", rng.randrange(lo, hi)))
            except OSError:
                continue  # in use: another
            ports.append(s.getsockname()[1])
            if len(ports) == count:
                return [f"tcp/127.0.0.1:{p}" for p in ports]
    raise DimslamError(f"no {count} free loopback ports in {lo}-{hi - 1}")


def _settings_args(cfg: SlamConfig) -> list[str]:
    """Every setting as `--section.field=value` ('=': values may start with '-'), so each
    process runs exactly `cfg`."""
    return [f"--{name}={text}" for name, text in flat_settings(to_dict(cfg)).items()]


def run_service(
    source: str,
    out_dir: Path,
    cfg: SlamConfig,
    device: torch.device,
    threads: int | None = None,
    map_lag: int = MAP_LAG,
    max_frames: int | None = None,
    layout: str | None = None,
    mesh: bool = True,
    realtime: float | None = None,
    viewer: list[str] | None = None,
    stride: int = 1,
) -> RunSummary:
    """Run the service on a dataset and write the outputs of `run_dataset` plus the online ones.

    With `realtime` (frames per second) the camera replays the dataset as a live camera would,
    at that rate once the map is initialized, without lockstep, and the tracker never waits
    for the map: frames it cannot keep up with are dropped, and the figures say how many and
    how late the poses came.

    Raises:
        DimslamError: a process failed (its log is named) or the dataset cannot be read.
    """
    if realtime is None:
        # Chunks run while the mapper waits for a batch: when they run depends on timing,
        # and with them the run is not the one-process run.
        cfg = replace(cfg, mapper=replace(cfg.mapper, idle_chunks=0))
    out_dir.mkdir(parents=True, exist_ok=True)
    for stale in ("trajectory.txt", "trajectory_online.txt", "poses_received.txt", "mesh.ply"):
        (out_dir / stale).unlink(missing_ok=True)
    tracker_ep, mapper_ep, camera_ep = loopback_endpoints(3)
    session = f"run{os.getpid()}"
    total = threads or torch.get_num_threads()
    compute = ["--threads", str(max(1, total // 2))]
    if device.type == "cuda":
        compute += ["--gpu", str(device.index or 0)]
    settings = ["--preset", "paper", *_settings_args(cfg)]
    both = ["--connect", tracker_ep, "--connect", mapper_ep]
    # Offline: in lockstep with the tracker, as fast as it goes; live: at the rate, held only
    # until the map is initialized (no frame beyond the initialization's sent before that).
    pacing = ["--lockstep", "--rate", "0"]
    if realtime is not None:
        pacing = ["--live", "--rate", str(realtime), "--ahead", str(cfg.mapper.init_frames)]
    commands = {
        "mapper": [
            "dimslam.mapper.cli",
            "--listen", mapper_ep, "--connect", tracker_ep,
            "--out", str(out_dir), "--exit-at-end", *(["--mesh"] if mesh else []),
            *compute, *settings,
        ],
        "tracker": [
            "dimslam.tracker.cli",
            "--listen", tracker_ep, "--connect", mapper_ep,
            "--out", str(out_dir), *compute, *settings,
            *(["--map-lag", str(map_lag)] if realtime is None else []),
        ],
        "poses": [
            "dimslam.common.net.poses", *both,
            "--out", str(out_dir / "poses_received.txt"),
        ],
        "camera": [
            # Its own endpoint, for the viewer: peers learn of each other's endpoints by
            # gossip, late, and a viewer without this link missed up to 31 of 36 frames;
            # with it the camera waits for the viewer as for the tracker.
            "dimslam.common.net.camera", source, *both, "--listen", camera_ep,
            *pacing,
            *(["--width", str(cfg.width)] if cfg.width else []),
            *(["--max-frames", str(max_frames)] if max_frames else []),
            *(["--layout", layout] if layout else []),
            *(["--stride", str(stride)] if stride != 1 else []),
        ],
    }  # fmt: skip
    (out_dir / "config.json").write_text(
        json.dumps(
            {
                "source": source,
                "stride": stride,
                "device": str(device),
                "mode": "service",
                "map_lag": map_lag if realtime is None else None,
                "realtime_fps": realtime,
                **to_dict(cfg),
            },
            indent=2,
        )
        + "\n"
    )
    if viewer is not None:  # started first, so that it sees the first frames
        commands = {
            "viewer": ["dimslam.common.net.viewer", *both, "--connect", camera_ep,
                       "--gt", source, "--threads", "1",
                       *settings, *viewer],
            **commands,
        }  # fmt: skip
        commands["camera"] += ["--also-wait-for", "viewer"]
    procs: dict[str, subprocess.Popen] = {}
    logs = {}
    started = time.perf_counter()
    try:
        for role, argv in commands.items():
            logs[role] = open(out_dir / f"{role}.log", "w")  # noqa: SIM115 - closed below
            procs[role] = subprocess.Popen(
                [sys.executable, "-m", *argv[:1], *argv[1:], "--session", session],
                stdout=logs[role],
                stderr=subprocess.STDOUT,
            )
        print(f"service: {', '.join(procs)} up (session {session})")
        codes = _wait(procs, out_dir)
    finally:
        for p in procs.values():
            _stop(p)
        for f in logs.values():
            f.close()
    seconds = time.perf_counter() - started
    for role in procs:
        if codes.get(role) not in (0, None):
            raise DimslamError(
                f"the {role} exited with code {codes[role]}; see {out_dir / (role + '.log')}"
            )
    traj_path = out_dir / "trajectory.txt"
    if not traj_path.is_file():
        raise DimslamError(f"the mapper wrote no trajectory; see {out_dir / 'mapper.log'}")
    frames = len(read_tum(traj_path))
    received = out_dir / "poses_received.txt"
    n_received = len(read_tum(received)) if received.is_file() else 0
    online = len(read_tum(out_dir / "trajectory_online.txt"))
    print(f"poses published {online}, received by the client {n_received}, final {frames}")
    stats = _tracker_stats(out_dir / "tracker_stats.json")
    print(_live_line(stats))
    mesh_path = out_dir / "mesh.ply"
    metrics = report_run(
        source,
        out_dir,
        layout,
        mesh_path if mesh_path.is_file() else None,
        seconds,
        frames,
        extra={
            "poses_published": online,
            "poses_received": n_received,
            "loops_closed": _count_lines(out_dir / "loops.txt"),
            **stats,
        },
    )
    keyframes = len(read_tum(out_dir / "keyframes.txt"))
    return RunSummary(frames, keyframes, seconds, stats.get("frames_lost", 0), metrics)


def _count_lines(path: Path) -> int:
    """Lines of a text file that are not comments (0 if it is missing)."""
    if not path.is_file():
        return 0
    return sum(1 for line in path.read_text().splitlines() if line and not line.startswith("#"))


def _tracker_stats(path: Path) -> dict:
    """The tracker's counts and timings (`TrackerStats.summary`), for metrics.json."""
    return json.loads(path.read_text()) if path.is_file() else {}


def _live_line(stats: dict) -> str:
    """What the tracker did with the frames it received, and how late its poses came."""
    if not stats:
        return "the tracker wrote no statistics"

    def ms(key: str) -> str:
        return "-" if stats.get(key) is None else f"{stats[key]:.0f} ms"

    return (
        f"frames received {stats['frames_received']}, tracked {stats['tracked']}, "
        f"dropped {stats['frames_dropped']}, lost {stats['frames_lost']}; tracking step "
        f"p50 {ms('track_ms_p50')} p95 {ms('track_ms_p95')}; latency camera to pose "
        f"p50 {ms('latency_ms_p50')} p95 {ms('latency_ms_p95')}"
    )


def _wait(procs: dict[str, subprocess.Popen], out_dir: Path) -> dict[str, int]:
    """Wait for the camera, tracker and mapper to finish; stop early if one of them fails."""
    codes: dict[str, int] = {}
    main = ["camera", "tracker", "mapper"]
    while len(codes) < len(main):
        for role in main:
            code = procs[role].poll()
            if code is None or role in codes:
                continue
            codes[role] = code
            if code != 0:
                log.error("%s exited with %d (log: %s)", role, code, out_dir / f"{role}.log")
                return codes
        running = [procs[r] for r in main if r not in codes]
        if running:
            try:
                running[0].wait(timeout=1.0)  # supervision tick: notice a failure elsewhere
            except subprocess.TimeoutExpired:
                pass
    for client in ("poses", "viewer"):
        if client in procs:
            try:
                codes[client] = procs[client].wait(timeout=STOP_GRACE_S)
            except subprocess.TimeoutExpired:
                log.error("the %s client did not see the end of the stream", client)
    return codes


def _stop(p: subprocess.Popen) -> None:
    if p.poll() is None:
        p.terminate()
        try:
            p.wait(timeout=STOP_GRACE_S)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()

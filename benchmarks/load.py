"""Load, measured: a fleet of N sessions of the service through one router on loopback.

    python benchmarks/load.py [--sessions 1,2,4,8] [--frames 60] [--rate 2] [--out out/load]
        [--lossless] [--json out/load.json]

For each N in `--sessions`, one `dimslam-router` on loopback and N sessions, each a camera, a
tracker and a mapper (tiny preset, one thread each) under a session name of its own, every
process a zenoh client of the router (faults.py's `Harness`, one per session). The cameras are
paced, not lockstep: each replays the built-in scene as a live camera (`dimslam-camera --live
--rate FPS`, as `dimslam run --realtime` does): held until its map is initialized, then at the
rate whatever the tracker does, with DROP congestion control, and a busy tracker skipping to the
newest frame (counted as dropped). With `--lossless` they send every frame instead (BLOCK, from
the first frame on, none skipped). The scene is rendered once; each session replays it on a
clock of its own (the scene's timestamps plus `k * CLOCK_S` for session k), so that every
frame, pose and mapping batch says which session produced it.

A harness session, a client like any other, subscribes to `dimslam/*/@v1/*`: every topic of
every session. Every message received on session A's keys must come from session A: frames,
poses, keyframe refinements and mapping batches by their timestamps, map snapshots by their
versions (1, 2, ... each once, up to the newest version of A's own refinements), ends of
stream by their count (one per topic). Anything else is counted as foreign.

Reported per session: poses received at the harness (of the frames of the scene), the pose
rate and the latency from the camera's send stamp of a frame to its pose's arrival at the
harness (p50 / p95) in the steady state (frames sent once the session's first pose had
arrived; the latency also over all frames), the tracker's own figures (the latency up to its
publication, its tracking step, the frames it dropped), the final trajectory's ATE (the
mapper's trajectory.txt) and the foreign messages seen.
"""

from __future__ import annotations

import json
import os
import queue
import re
import resource
import subprocess
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import zenoh
from faults import Harness, benchmark_parser, builtin_scene, report

from dimslam.common.config import PRESETS
from dimslam.common.io.trajectory import Trajectory, read_tum, write_tum
from dimslam.common.net.messages import (
    EndOfStream,
    FrameMessage,
    MappingBatch,
    MapSnapshot,
    MessageError,
    PoseMessage,
    message_type,
)
from dimslam.common.net.transport import Keys

CLOCK_S = 1000.0
"""Session k replays the scene `k * CLOCK_S` seconds later: its timestamps name it."""
WAIT_S = 600.0
"""Longest a fleet may take, from the start of its processes to every session's end."""
END_WAIT_S = 120.0
"""How long the processes have to exit after their session's end of stream."""
ALL_TOPICS = f"{Keys('*').root}/*"
"""Every session's frames, poses, mapping, map and keyframes (not queries, not tokens)."""
# What the mapper's log says of its initialization and its rounds (mapper/backend.py, service.py).
_MAPPER_INIT = re.compile(r"initialized on \d+ frames in ([\d.]+) s")
_MAPPER_ROUNDS = re.compile(r"\d+ rounds \(median ([\d.]+) s\)")


def session_scene(scene: Path, k: int, out: Path) -> Path:
    """Session k's view of `scene`: the same images (by absolute path), its own clock.

    Returns:
        A TUM folder (rgb.txt, groundtruth.txt, calib.txt) whose timestamps are the scene's
        plus `k * CLOCK_S`.
    """
    out.mkdir(parents=True, exist_ok=True)
    lines = []
    for line in (scene / "rgb.txt").read_text().splitlines():
        if line.startswith("#"):
            continue
        stamp, name = line.split()
        lines.append(f"{float(stamp) + k * CLOCK_S:.6f} {(scene / name).resolve()}\n")
    (out / "rgb.txt").write_text("".join(lines))
    gt = read_tum(scene / "groundtruth.txt")
    write_tum(out / "groundtruth.txt", Trajectory(gt.timestamps + k * CLOCK_S, gt.poses))
    (out / "calib.txt").write_text((scene / "calib.txt").read_text())
    return out


def owner(timestamp: float) -> int:
    """The session whose clock `timestamp` is on."""
    return int(timestamp // CLOCK_S)


@dataclass
class Seen:
    """What the harness received on one session's keys."""

    frames: dict[int, tuple[float, int]] = field(default_factory=dict)  # seq -> (ts, sent ns)
    poses: dict[int, int] = field(default_factory=dict)  # seq -> arrival ns (first pose)
    lost: set[int] = field(default_factory=set)
    map_versions: list[int] = field(default_factory=list)
    refined_version: int = 0  # newest map version of the session's own keyframe refinements
    ends: Counter = field(default_factory=Counter)  # topic -> ends of stream
    foreign: list[str] = field(default_factory=list)
    undecodable: int = 0


class Watch:
    """The harness's subscriber on every session's topics; checks each message's producer.

    The zenoh callback only copies (zenoh.md trap 7); a thread of its own decodes.
    """

    def __init__(self, sessions: list[str]) -> None:
        self.index = {name: k for k, name in enumerate(sessions)}
        self.seen = {name: Seen() for name in sessions}
        self.unknown: Counter = Counter()  # messages on keys of no session of the fleet
        self.backlog_peak = 0
        self.ended = {name: threading.Event() for name in sessions}
        # Unbounded, unlike the service's inboxes: a checker that dropped a message could not
        # vouch for it; its peak is reported (the decoding thread keeps up).
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._decode, name="watch", daemon=True)
        self._thread.start()

    def callback(self, sample: zenoh.Sample) -> None:
        self._queue.put((str(sample.key_expr), time.time_ns(), sample.payload.to_bytes()))
        self.backlog_peak = max(self.backlog_peak, self._queue.qsize())

    def close(self) -> None:
        """Decode what is queued, then stop the thread."""
        self._queue.put(None)
        self._thread.join()

    def _decode(self) -> None:
        while (item := self._queue.get()) is not None:
            self.take(*item)

    def take(self, key: str, arrived: int, payload: bytes) -> None:
        """Check and record one message received on `key` at `arrived` (ns, wall clock)."""
        _, session, _, topic = key.split("/")
        if session not in self.seen:
            self.unknown[key] += 1
            return
        try:
            self._take(session, topic, arrived, payload)
        except MessageError:
            self.seen[session].undecodable += 1

    def _take(self, session: str, topic: str, arrived: int, payload: bytes) -> None:
        seen, k = self.seen[session], self.index[session]

        def check(timestamp: float, what: str) -> None:
            if owner(timestamp) != k:
                seen.foreign.append(f"{topic}: {what} of session {owner(timestamp)}")

        kind = message_type(payload)
        if kind == EndOfStream.TYPE:
            seen.ends[topic] += 1
            if topic == "poses":
                self.ended[session].set()
        elif topic == "frames":
            frame = FrameMessage.from_bytes(payload)
            check(frame.timestamp, f"frame {frame.seq}")
            # A frame sent again (the camera repeats those without a pose after a link cut)
            # is its session's own; its latency counts from the first sending.
            seen.frames.setdefault(frame.seq, (frame.timestamp, frame.stamp_ns))
        elif topic in ("poses", "keyframes"):
            pose = PoseMessage.from_bytes(payload)
            check(pose.timestamp, f"pose {pose.seq}")
            if topic == "keyframes":
                seen.refined_version = max(seen.refined_version, pose.map_version)
            elif pose.lost:
                seen.lost.add(pose.seq)
            else:
                seen.poses.setdefault(pose.seq, arrived)
        elif topic == "mapping" and kind == MappingBatch.TYPE:
            for f in MappingBatch.from_bytes(payload).frames:
                check(f.timestamp, f"mapped frame {f.seq}")
        elif topic == "map":
            seen.map_versions.append(MapSnapshot.from_bytes(payload).version)
        else:
            seen.foreign.append(f"{topic}: an unexpected {kind}")

    def verdict(self, session: str) -> list[str]:
        """Every foreign message on `session`'s keys, including what only the counts reveal:
        map versions other than 1, 2, ... each once, and more than one end per topic."""
        seen = self.seen[session]
        found = list(seen.foreign)
        versions = sorted(seen.map_versions)
        if versions != list(range(1, seen.refined_version + 1)):
            found.append(f"map: versions {versions}, refinements up to {seen.refined_version}")
        found += [f"{t}: {n} ends of stream" for t, n in seen.ends.items() if n > 1]
        return found


def _ms(values: list[float], q: float) -> float | None:
    return float(np.percentile(values, q)) if values else None


def _cpu_s(who: int) -> float:
    """CPU seconds (user + system) of this process or of its reaped children so far."""
    usage = resource.getrusage(who)
    return usage.ru_utime + usage.ru_stime


def _process_cpu_s(pid: int) -> float | None:
    """CPU seconds (user + system) a running process has taken so far (Linux), else None."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _logged(pattern: re.Pattern, path: Path) -> float | None:
    """The newest figure `pattern` finds in the log (logs are appended to, run after run)."""
    found = pattern.findall(path.read_text()) if path.is_file() else []
    return float(found[-1]) if found else None


def _figures(h: Harness, seen: Seen, foreign: list[str]) -> dict:
    sent = {seq: stamp for seq, (_, stamp) in seen.frames.items() if seq in seen.poses}
    latency = {seq: (seen.poses[seq] - stamp) / 1e6 for seq, stamp in sent.items()}
    # Steady state: frames sent once the first pose had arrived. Before it, the frames wait
    # for the map's initialization (the mapper's first round), then go through in a burst.
    first = min(seen.poses.values(), default=0)
    steady = [seq for seq, stamp in sent.items() if stamp >= first]
    arrivals = sorted(seen.poses[seq] for seq in steady)
    span = (arrivals[-1] - arrivals[0]) / 1e9 if len(arrivals) > 1 else 0.0
    steady_ms = [latency[seq] for seq in steady]
    stats_path = h.out / "tracker" / "tracker_stats.json"
    stats = json.loads(stats_path.read_text()) if stats_path.is_file() else {}
    result = {
        "session": h.session_name,
        "frames_sent": len(seen.frames),
        "poses": len(seen.poses),
        "lost": len(seen.lost),
        "steady_poses": len(steady),
        "pose_rate_hz": (len(steady) - 1) / span if span > 0 else None,
        "latency_ms_p50": _ms(steady_ms, 50),
        "latency_ms_p95": _ms(steady_ms, 95),
        "latency_all_ms_p50": _ms(list(latency.values()), 50),
        "latency_all_ms_p95": _ms(list(latency.values()), 95),
        "tracker_latency_ms_p50": stats.get("latency_ms_p50"),
        "tracker_latency_ms_p95": stats.get("latency_ms_p95"),
        "track_ms_p50": stats.get("track_ms_p50"),
        "frames_dropped": stats.get("frames_dropped"),
        "mapper_init_s": _logged(_MAPPER_INIT, h.out / "mapper.log"),
        "mapping_round_s_p50": _logged(_MAPPER_ROUNDS, h.out / "mapper.log"),
        "map_versions": len(seen.map_versions),
        "foreign": len(foreign),
        "foreign_examples": foreign[:5],
        "undecodable": seen.undecodable,
        "exits": {role: p.returncode for role, p in h.procs.items() if role != "router"},
    }
    result.update(h.final_figures())
    return result


def run_fleet(n: int, scene: Path, out: Path, rate: float, live: bool = True) -> dict:
    """N sessions through one router on the scene; returns the fleet's figures.

    Args:
        n: sessions.
        scene: the rendered scene (a TUM folder); each session replays it on its own clock.
        out: the fleet's folder (one sub-folder per session).
        rate: each camera's frames per second.
        live: cameras replay as live ones (`dimslam-camera --live`: held until the map is
            initialized, then DROP, a busy tracker skipping to the newest frame); False: they
            send every frame from the first on.

    Returns:
        `{"sessions": n, "seconds": ..., "cpu_s": ..., "unknown": ..., "per_session":
        [figures, ...]}`.
    """
    camera_args = ["--rate", str(rate), "--wait-timeout", str(WAIT_S)]
    if live:  # held until the initialization's frames have their poses
        camera_args += ["--live", "--ahead", str(PRESETS["tiny"].mapper.init_frames)]
    fleet: list[Harness] = []
    router_ep = None
    for k in range(n):
        folder = out / f"s{k}"
        clock = session_scene(scene, k, folder / "scene")
        h = Harness(f"s{k}_", clock, folder, {"camera": camera_args}, router_ep)
        router_ep = h.router_ep
        fleet.append(h)
    watch = Watch([h.session_name for h in fleet])
    cpu = _cpu_s(resource.RUSAGE_CHILDREN), _cpu_s(resource.RUSAGE_SELF)
    started = time.monotonic()
    router_cpu = None
    try:
        fleet[0].start("router")
        with fleet[0].session() as zs:
            sub = zs.declare_subscriber(ALL_TOPICS, watch.callback)
            for h in fleet:
                for role in ("mapper", "tracker", "camera"):
                    h.start(role)
            deadline = started + WAIT_S
            for h in fleet:
                if not watch.ended[h.session_name].wait(max(deadline - time.monotonic(), 0)):
                    raise RuntimeError(f"{h.session_name}: no end of stream after {WAIT_S:g} s")
            for h in fleet:
                for role in ("camera", "tracker", "mapper"):
                    try:
                        h.procs[role].wait(END_WAIT_S)
                    except subprocess.TimeoutExpired:
                        pass  # killed below: its exit code says so
            router_cpu = _process_cpu_s(fleet[0].procs["router"].pid)
            sub.undeclare()
    finally:
        seconds = time.monotonic() - started
        for h in fleet:
            h.stop_all()
        watch.close()
    processes_cpu = _cpu_s(resource.RUSAGE_CHILDREN) - cpu[0]
    return {
        "sessions": n,
        "seconds": seconds,
        # Every process of the fleet (router, cameras, trackers, mappers), and the harness.
        "cpu_s": processes_cpu,
        "cores_busy": processes_cpu / seconds,
        "harness_cpu_s": _cpu_s(resource.RUSAGE_SELF) - cpu[1],
        "router_cpu_s": router_cpu,
        "unknown": sum(watch.unknown.values()),
        "harness_backlog_peak": watch.backlog_peak,
        "per_session": [
            _figures(h, watch.seen[h.session_name], watch.verdict(h.session_name)) for h in fleet
        ],
    }


def _cell(value: float | None, fmt: str) -> str:
    return "-" if value is None else fmt.format(value)


def fleet_table(fleets: list[dict]) -> str:
    """One row per fleet: its time, the CPU its processes took, its mappers' round times."""
    rows = [
        "| N | seconds | CPU of the processes | cores busy | the router's CPU "
        "| mapper initialization (median) | mapping round (median of the medians) "
        "| foreign, unknown keys |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for fleet in fleets:
        runs = fleet["per_session"]
        init = [r["mapper_init_s"] for r in runs if r["mapper_init_s"] is not None]
        rounds = [r["mapping_round_s_p50"] for r in runs if r["mapping_round_s_p50"] is not None]
        rows.append(
            f"| {fleet['sessions']} | {fleet['seconds']:.0f} s | {fleet['cpu_s']:.0f} s "
            f"| {fleet['cores_busy']:.2f} | {_cell(fleet.get('router_cpu_s'), '{:.1f} s')} "
            f"| {_cell(np.median(init) if init else None, '{:.1f} s')} "
            f"| {_cell(np.median(rounds) if rounds else None, '{:.1f} s')} "
            f"| {sum(r['foreign'] for r in runs)}, {fleet['unknown']} |"
        )
    return "\n".join(rows)


def table(fleets: list[dict], frames: int) -> str:
    """One row per session of every fleet."""
    rows = [
        "| N | session | poses / frames | steady poses | pose rate | latency p50 / p95 "
        "| all frames p50 / p95 | tracker's p50 / p95 | tracking step p50 | dropped | ATE "
        "| foreign |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]

    s = _cell
    for fleet in fleets:
        for k, r in enumerate(fleet["per_session"]):
            rows.append(
                f"| {fleet['sessions']} | s{k} | {r['poses']} / {frames} | {r['steady_poses']} "
                f"| {s(r['pose_rate_hz'], '{:.2f}/s')} "
                f"| {s(r['latency_ms_p50'], '{:.0f}')} / {s(r['latency_ms_p95'], '{:.0f} ms')} "
                f"| {s(r['latency_all_ms_p50'], '{:.0f}')} / "
                f"{s(r['latency_all_ms_p95'], '{:.0f} ms')} "
                f"| {s(r['tracker_latency_ms_p50'], '{:.0f}')} / "
                f"{s(r['tracker_latency_ms_p95'], '{:.0f} ms')} "
                f"| {s(r['track_ms_p50'], '{:.0f} ms')} | {s(r['frames_dropped'], '{}')} "
                f"| {s(None if r.get('ate_m') is None else 100 * r['ate_m'], '{:.2f} cm')} "
                f"| {r['foreign']} |"
            )
    return "\n".join(rows)


def main() -> int:
    parser = benchmark_parser(__doc__, "load")
    parser.add_argument("--sessions", default="1,2,4,8", help="fleet sizes, comma-separated")
    parser.add_argument("--rate", type=float, default=2.0, help="each camera's frames per second")
    parser.add_argument(
        "--lossless",
        action="store_true",
        help="cameras send every frame from the first on (BLOCK) instead of replaying as live",
    )
    args = parser.parse_args()
    sizes = [int(n) for n in args.sessions.split(",")]
    scene = builtin_scene(args.out / "scene", args.frames)
    fleets = []
    for n in sizes:
        print(f"{n} sessions ...", flush=True)
        fleets.append(run_fleet(n, scene, args.out / f"n{n}", args.rate, not args.lossless))
        print(json.dumps(fleets[-1]), flush=True)
    report(fleets, table(fleets, args.frames) + "\n" + fleet_table(fleets), args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

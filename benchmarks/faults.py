"""Faults, measured: the service on the built-in scene with one process killed (or the link cut).

    python benchmarks/faults.py [--frames 60] [--out out/faults] [--json out/faults.json]

Every scenario is a whole run of its own (tiny preset, lockstep camera at `--rate` frames per
second): router, mapper (`--checkpoint`, every round), tracker and camera, all as zenoh
clients of the router on loopback, as on two machines (deploy/README.md), and a harness
session that watches the poses and the map snapshots. At frame `--at` (counted in poses
received) the scenario's fault happens:

- clean: no fault, the reference;
- kill-mapper: SIGKILL the mapper; a new one starts with `--resume` (its checkpoint);
- term-mapper: SIGTERM the mapper (its outputs must parse); a new one with `--resume`;
- kill-tracker: SIGKILL the tracker; a new one, which continues the running map, while the
  lockstep camera waits for it (`dimslam-camera --grace`);
- term-tracker: SIGTERM the tracker: the stream ends there (it sends its last batch and the
  end of stream), its outputs must parse, and every frame it took must reach the final
  trajectory (no new tracker: the mapper has finished the stream);
- term-camera: SIGTERM the camera: the stream ends there (its end of stream is sent), and
  every frame it sent must still get a pose and reach the final trajectory;
- kill-router: SIGKILL the router; a new one on the same port;
- link-cut: the router stopped for `--cut` seconds, then started again.

Reported per scenario: frames without any pose at the harness (`missing`) and among them those
after the recovery (`missing_after`), frames marked lost, the longest gap between two poses
and how long after the recovery step the poses (and, for the mapper, the snapshots) came
again, whether the map came back from the checkpoint, and the final trajectory's ATE (the
mapper's trajectory.txt) next to the clean run's.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

from dimslam.common.eval.report import evaluate_files
from dimslam.common.io.synth import write_sequence
from dimslam.common.io.trajectory import read_tum
from dimslam.common.net.launch import loopback_endpoints
from dimslam.common.net.messages import MapperCheckpoint, PoseMessage, message_type
from dimslam.common.net.transport import Keys, pose_subscriber

SCENARIOS = (
    "clean",
    "kill-mapper",
    "term-mapper",
    "kill-tracker",
    "term-tracker",
    "term-camera",
    "kill-router",
    "link-cut",
)
WAIT_S = 300.0
"""Longest a run may go without a pose before the scenario is declared stuck."""
END_WAIT_S = 60.0
"""How long the mapper has to finish (final round, outputs, mesh) after the end of stream."""


class Harness:
    """The processes of one session, and what a client of the service saw of them.

    Args:
        name: the scenario's name; the session's name is made of it and this process's id.
        scene: the dataset the camera streams.
        out: the session's folder: logs, outputs, the client configuration.
        role_args: per role, the arguments every start of that role gets beyond the common
            ones (the camera's pacing, the mapper's checkpoints, ...).
        router_ep: the router the processes join; None: a free loopback port of its own, for
            `start("router")` (several sessions can share one router: benchmarks/load.py).
    """

    def __init__(
        self,
        name: str,
        scene: Path,
        out: Path,
        role_args: dict[str, list[str]],
        router_ep: str | None = None,
    ) -> None:
        self.name, self.scene, self.out, self.role_args = name, scene, out, role_args
        out.mkdir(parents=True, exist_ok=True)
        self.router_ep = router_ep or loopback_endpoints(1)[0]
        self.config = out / "client.json5"
        self.config.write_text(
            json.dumps(
                {
                    "mode": "client",
                    # As deploy/zenoh/client-*.json5: reconnect within ~1 s of the router.
                    "connect": {
                        "endpoints": [self.router_ep],
                        "timeout_ms": 30000,
                        "retry": {"period_init_ms": 250, "period_max_ms": 1000},
                    },
                    "scouting": {"multicast": {"enabled": False}},
                }
            )
        )
        self.session_name = f"{name.replace('-', '')}{os.getpid()}"
        self.procs: dict[str, subprocess.Popen] = {}
        self.count = 0
        self.poses: dict[float, list[tuple[float, bool]]] = {}  # timestamp -> (received, lost)
        self.maps: list[float] = []
        self.ended = threading.Event()
        self.changed = threading.Condition()

    def start(self, role: str, *extra: str) -> subprocess.Popen:
        modules = {
            "router": "dimslam.common.net.router",
            "mapper": "dimslam.mapper.cli",
            "tracker": "dimslam.tracker.cli",
            "camera": "dimslam.common.net.camera",
        }
        if role == "router":
            argv = ["--listen", self.router_ep]
        else:
            argv = ["--session", self.session_name, "--zenoh-config", str(self.config)]
            if role != "camera":
                argv += ["--preset", "tiny", "--threads", "1", "--out", str(self.out / role)]
        if role == "mapper":
            argv += ["--exit-at-end"]
        if role == "camera":
            argv = [str(self.scene), *argv]
        argv += self.role_args.get(role, [])
        log = open(self.out / f"{role}.log", "a")  # noqa: SIM115 - closed with the process
        self.procs[role] = subprocess.Popen(
            [sys.executable, "-m", modules[role], *argv, *extra],
            stdout=log,
            stderr=subprocess.STDOUT,
        )
        log.close()
        return self.procs[role]

    def _pose(self, sample: zenoh.Sample) -> None:
        payload = sample.payload.to_bytes()
        now = time.monotonic()
        if message_type(payload) == "end":
            self.ended.set()
        else:
            msg = PoseMessage.from_bytes(payload)
            self.poses.setdefault(round(msg.timestamp, 6), []).append((now, msg.lost))
        with self.changed:
            self.count = len(self.poses)
            self.changed.notify_all()

    def wait_for_poses(self, count: int, timeout: float = WAIT_S) -> None:
        with self.changed:
            if not self.changed.wait_for(lambda: self.count >= count, timeout):
                raise RuntimeError(f"{self.name}: no {count} poses after {timeout:g} s")

    def session(self) -> zenoh.Session:
        conf = zenoh.Config.from_file(str(self.config))
        return zenoh.open(conf)

    def final_figures(self) -> dict:
        """The mapper's final trajectory against the scene: `ate_m` (Sim(3) RMSE) and
        `final_frames`; empty if it wrote none."""
        traj = self.out / "mapper" / "trajectory.txt"
        if not traj.is_file():
            return {}
        figures = evaluate_files(traj, str(self.scene))
        return {"ate_m": figures["ate_rmse_m"], "final_frames": figures["matched"]}

    def stop_all(self) -> None:
        for p in self.procs.values():
            if p.poll() is None:
                p.kill()
            p.wait()


def _fault(h: Harness, scenario: str, cut_s: float) -> dict:
    """Do the scenario's fault and recovery; returns when (monotonic) the recovery step ran."""
    procs = h.procs
    info: dict = {"fault_at": time.monotonic()}
    if scenario in ("kill-mapper", "term-mapper"):
        sig = signal.SIGKILL if scenario == "kill-mapper" else signal.SIGTERM
        procs["mapper"].send_signal(sig)
        info["fault_exit"] = procs["mapper"].wait(60)
        if scenario == "term-mapper":
            info["outputs_parse"] = _outputs_parse(h.out)
        h.start("mapper", "--resume", str(h.out / "ckpt"))
    elif scenario == "kill-tracker":
        procs["tracker"].send_signal(signal.SIGKILL)
        procs["tracker"].wait(60)
        h.start("tracker")  # within the camera's --grace: the stream goes on
    elif scenario == "term-tracker":
        procs["tracker"].send_signal(signal.SIGTERM)
        info["fault_exit"] = procs["tracker"].wait(60)
        info["outputs_parse"] = found = _tracker_outputs_parse(h.out)
        info["frames_expected"] = found["stats_frames"]
    elif scenario == "term-camera":
        procs["camera"].send_signal(signal.SIGTERM)
        info["fault_exit"] = procs["camera"].wait(60)
        sent = re.findall(r"sent (\d+) frames, then the end", (h.out / "camera.log").read_text())
        info["frames_expected"] = int(sent[-1]) if sent else None
    elif scenario in ("kill-router", "link-cut"):
        if scenario == "link-cut":
            procs["router"].send_signal(signal.SIGTERM)
            procs["router"].wait(60)
            time.sleep(cut_s)  # the outage itself is what is measured
        else:
            procs["router"].send_signal(signal.SIGKILL)
            procs["router"].wait(60)
        h.start("router")
    info["recovered_at"] = time.monotonic()
    return info


def _outputs_parse(out: Path) -> dict:
    """What a SIGTERMed mapper left: every file parses (frame counts)."""
    found = {}
    traj = out / "mapper" / "trajectory.txt"
    found["trajectory_frames"] = len(read_tum(traj)) if traj.is_file() else None
    ckpt = out / "ckpt" / "checkpoint.msgpack"
    found["checkpoint_frames"] = (
        len(MapperCheckpoint.from_bytes(ckpt.read_bytes()).frames) if ckpt.is_file() else None
    )
    return found


def _tracker_outputs_parse(out: Path) -> dict:
    """What a SIGTERMed tracker left: every pose it published, as a TUM file, and its stats."""
    traj = out / "tracker" / "trajectory_online.txt"
    stats = out / "tracker" / "tracker_stats.json"
    return {
        "trajectory_frames": len(read_tum(traj)) if traj.is_file() else None,
        "stats_frames": json.loads(stats.read_text())["frames"] if stats.is_file() else None,
    }


def run_scenario(scenario: str, scene: Path, out: Path, args: argparse.Namespace) -> dict:
    folder = out / scenario
    role_args = {
        "mapper": ["--checkpoint", str(folder / "ckpt"), "--checkpoint-every", "1", "--mesh"],
        "camera": ["--lockstep", "--rate", str(args.rate)],
        # As `dimslam run` starts it (common/net/launch.py): bounded staleness, so a run's
        # accuracy does not depend on when the mapper's rounds end (nor on a mapper outage).
        "tracker": ["--map-lag", "1"],
    }
    h = Harness(scenario, scene, folder, role_args)
    gt = read_tum(scene / "groundtruth.txt").timestamps
    started = time.monotonic()
    try:
        h.start("router")
        with h.session() as zs:
            keys = Keys(h.session_name)
            subs = [
                pose_subscriber(zs, keys.poses, h._pose),
                zs.declare_subscriber(keys.map, lambda _s: h.maps.append(time.monotonic())),
            ]
            h.start("mapper")
            h.start("tracker")
            h.start("camera")
            info: dict = {}
            if scenario != "clean":
                h.wait_for_poses(args.at)
                info = _fault(h, scenario, args.cut)
            if not h.ended.wait(WAIT_S):
                raise RuntimeError(f"{scenario}: no end of stream after {WAIT_S:g} s")
            try:
                mapper_exit = h.procs["mapper"].wait(END_WAIT_S)
            except subprocess.TimeoutExpired:
                # A mapper resumed after the end of stream (its predecessor took the end with
                # it at SIGTERM) waits for an end that will not come: stop it as a user would.
                h.procs["mapper"].send_signal(signal.SIGTERM)
                mapper_exit = f"SIGTERM after the end ({h.procs['mapper'].wait(60)})"
            for sub in subs:
                sub.undeclare()
    finally:
        h.stop_all()
    received = h.poses
    posed = {t for t, v in received.items() if any(not lost for _, lost in v)}
    lost = {t for t, v in received.items() if all(lost for _, lost in v)}
    # Every frame of the scene, unless the stream was ended early (the camera or the tracker
    # SIGTERMed): then those the stream held.
    all_ts = {round(float(t), 6) for t in gt[: info.get("frames_expected") or len(gt)]}
    missing = sorted(all_ts - set(received))
    times = sorted(r for v in received.values() for r, _ in v)
    gaps = np.diff(times) if len(times) > 1 else np.zeros(1)
    result = {
        "scenario": scenario,
        "frames": len(all_ts),
        "posed": len(posed),
        "lost": len(lost),
        "missing": len(missing),
        "max_pose_gap_s": float(gaps.max()),
        "mapper_exit": mapper_exit,
        "seconds": time.monotonic() - started,
    }
    if info:
        back = info["recovered_at"]
        after = [r for r in times if r > back]
        maps_after = [m for m in h.maps if m > back]
        result["poses_again_s"] = (after[0] - back) if after else None
        result["maps_again_s"] = (maps_after[0] - back) if maps_after else None
        # Frames whose poses would have come after the recovery: those later than the newest
        # frame posed before it.
        before = [t for t, v in received.items() if min(r for r, _ in v) <= back]
        newest_before = max(before) if before else -1.0
        result["missing_after"] = sum(1 for t in missing if t > newest_before)
        result.update({k: v for k, v in info.items() if not k.endswith("_at")})
    mapper_log = (h.out / "mapper.log").read_text()
    result["resumed_from_checkpoint"] = "resumed from" in mapper_log
    result.update(h.final_figures())
    return result


def benchmark_parser(doc: str, name: str) -> argparse.ArgumentParser:
    """The options every service benchmark here has: the built-in scene's `--frames`, the
    `--out` folder (out/NAME) and `--json`; the docstring's first paragraph describes it."""
    parser = argparse.ArgumentParser(
        description=doc.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--frames", type=int, default=60, help="frames of the built-in scene")
    parser.add_argument("--out", type=Path, default=Path("out") / name, help="outputs, logs")
    parser.add_argument("--json", type=Path, help="write the figures as JSON")
    return parser


def builtin_scene(folder: Path, frames: int) -> Path:
    """The built-in scene (160x120, seed 0) in `folder`, rendered there once."""
    if not (folder / "rgb.txt").is_file():
        write_sequence(folder, frames=frames, width=160, height=120, seed=0)
    return folder


def report(results: list, text: str, path: Path | None) -> None:
    """Print the benchmark's table; with `path`, write its figures there as JSON."""
    print(text)
    if path:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(results, indent=2) + "\n")


def _median(values: list) -> float | None:
    values = [v for v in values if v is not None]
    return float(np.median(values)) if values else None


def table(results: list[dict]) -> str:
    """One row per scenario; with repeats, medians (ATE also its range) over the runs."""
    by_scenario: dict[str, list[dict]] = {}
    for r in results:
        by_scenario.setdefault(r["scenario"], []).append(r)
    clean = _median([r.get("ate_m") for r in by_scenario.get("clean", [])])
    rows = [
        "| scenario | runs | posed / frames | lost | missing (after recovery) | longest pose gap "
        "| poses again | maps again | resumed | final frames | ATE (range) | ATE / clean "
        "| outputs at SIGTERM (frames) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]

    def s(v, fmt="{:.1f} s"):
        return "-" if v is None else fmt.format(v)

    def med(runs: list[dict], key: str):
        return _median([r.get(key) for r in runs])

    for name, runs in by_scenario.items():
        ates = [r["ate_m"] for r in runs if r.get("ate_m") is not None]
        ate = _median(ates)
        spread = f" ({100 * min(ates):.2f}-{100 * max(ates):.2f})" if len(ates) > 1 else ""
        ratio = ate / clean if ate and clean else None
        resumed = sum(r["resumed_from_checkpoint"] for r in runs)
        rows.append(
            f"| {name} | {len(runs)} | {s(med(runs, 'posed'), '{:.0f}')} / {runs[0]['frames']} "
            f"| {s(med(runs, 'lost'), '{:.0f}')} | {s(med(runs, 'missing'), '{:.0f}')} "
            f"({s(med(runs, 'missing_after'), '{:.0f}')}) | {s(med(runs, 'max_pose_gap_s'))} "
            f"| {s(med(runs, 'poses_again_s'))} | {s(med(runs, 'maps_again_s'))} "
            f"| {resumed} of {len(runs)} | {s(med(runs, 'final_frames'), '{:.0f}')} "
            f"| {s(None if ate is None else 100 * ate, '{:.2f} cm')}{spread} "
            f"| {s(ratio, '{:.2f}')} | {_outputs(runs)} |"
        )
    return "\n".join(rows)


def _outputs(runs: list[dict]) -> str:
    """What the SIGTERMed process left, per run: each output file's frames (or "missing")."""
    cells = []
    for r in runs:
        found = r.get("outputs_parse")
        if found:
            cells.append(
                ", ".join(
                    f"{k.split('_')[0]} {'missing' if v is None else v}" for k, v in found.items()
                )
            )
        elif r.get("frames_expected") is not None:
            cells.append(f"exit {r.get('fault_exit')}, sent {r['frames_expected']}")
    return "; ".join(cells) or "-"


def main() -> int:
    parser = benchmark_parser(__doc__, "faults")
    parser.add_argument("--rate", type=float, default=4.0, help="camera frames per second")
    parser.add_argument("--at", type=int, default=25, help="poses received before the fault")
    parser.add_argument("--cut", type=float, default=5.0, help="link-cut: seconds of outage")
    parser.add_argument(
        "--repeats", type=int, default=1, help="runs of every scenario (medians reported)"
    )
    parser.add_argument("--scenarios", default=",".join(SCENARIOS), help="comma-separated")
    args = parser.parse_args()
    chosen = args.scenarios.split(",")
    unknown = [s for s in chosen if s not in SCENARIOS]
    if unknown:
        parser.error(f"unknown scenarios {unknown}; known: {', '.join(SCENARIOS)}")
    scene = builtin_scene(args.out / "scene", args.frames)
    results = []
    for repeat in range(args.repeats):
        for scenario in chosen:
            print(f"{scenario} ({repeat + 1} of {args.repeats}) ...", flush=True)
            results.append(run_scenario(scenario, scene, args.out / f"run{repeat}", args))
            print(json.dumps(results[-1]), flush=True)
    report(results, table(results), args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

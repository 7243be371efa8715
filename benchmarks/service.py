"""The service's overlap: tracker time per frame while the mapper runs a round vs while it idles.

    python benchmarks/service.py                          # tiny preset, 60 frames 160x120
    python benchmarks/service.py --preset cpu --frames 40 --size 320x240 --repeats 1

Renders the built-in synthetic scene, runs `dimslam run` (mapper, tracker, lockstep camera and
pose client as processes on loopback) `--repeats` times and prints, as JSON and a short table,
the tracker's median milliseconds per frame with the mapper busy (a batch sent, its snapshot
not back yet) and idle, the run's frames per second and its ATE. If the tracker waited for the
mapper, no frame would be tracked while a round runs; with both processes on one machine the
busy figure is higher because they share the cores.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import tempfile
from pathlib import Path

import dimslam.common  # noqa: F401  (OMP_WAIT_POLICY must be set before torch loads OpenMP)

# isort: split
import torch

from dimslam.common.config import PRESETS
from dimslam.common.io.synth import write_sequence
from dimslam.common.net.launch import run_service

KEYS = ("median_track_ms_mapper_busy", "median_track_ms_mapper_idle", "fps", "ate_rmse_m")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--preset", choices=sorted(PRESETS), default="tiny")
    p.add_argument("--frames", type=int, default=60)
    p.add_argument("--size", default="160x120", help="WIDTHxHEIGHT of the rendered scene")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--threads", type=int, default=None, help="CPU threads for both processes")
    p.add_argument("--json", type=Path, help="also write the figures here")
    args = p.parse_args()
    width, height = (int(v) for v in args.size.split("x"))
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        scene = Path(tmp) / "scene"
        write_sequence(scene, frames=args.frames, width=width, height=height, seed=0)
        for r in range(args.repeats):
            summary = run_service(
                str(scene),
                Path(tmp) / f"run{r}",
                PRESETS[args.preset],
                torch.device("cpu"),
                threads=args.threads,
                mesh=False,
            )
            runs.append({k: summary.metrics.get(k) for k in KEYS})
    result = {
        "preset": args.preset,
        "frames": args.frames,
        "size": args.size,
        "machine": f"{platform.processor() or platform.machine()}, {torch.get_num_threads()} "
        "threads",
        "runs": runs,
        "median": {k: statistics.median(r[k] for r in runs if r[k] is not None) for k in KEYS},
    }
    print(json.dumps(result, indent=2))
    m = result["median"]
    print(
        f"\ntracker ms/frame, mapper busy {m[KEYS[0]]:.0f} | idle {m[KEYS[1]]:.0f} | "
        f"{m['fps']:.2f} frames/s | ATE {100 * m['ate_rmse_m']:.2f} cm "
        f"(median of {len(runs)} runs, {args.preset} preset)"
    )
    if args.json:
        args.json.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()

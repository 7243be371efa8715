"""Fast motion, measured: every sequence at several strides and seeds, one table.

    python benchmarks/strides.py --out out/strides
    python benchmarks/strides.py --out out/strides --strides 4,6 --seeds 0 \
        --datasets ../shared/data/room0

Runs `dimslam run DATASET --stride K --seed S --single-process --threads 1 --no-mesh` (the
`--preset`, cpu by default) for every dataset, stride and seed, `--jobs` at a time, each into
`OUT/<dataset>_st<K>_s<S>`; a run whose folder already holds metrics.json is not run again,
so an interrupted matrix resumes and one with more strides or seeds adds only those
(`--report`: run nothing, tabulate what is there). Every
stride-th frame of the dataset is used: the camera moves stride times as far between frames,
as a faster camera would (issue "Fast motion").

Prints, per dataset and stride: the ATE of each seed (Sim(3), over the frames with a pose),
their mean, the mean over the stride-1 mean (where stride 1 was run), frames lost (the tracker
gave them no pose) and frames with a pose of those used; `--json FILE` writes the same.
A run that failed or did not reach the end is shown as such, with its log.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from dimslam.common.config import PRESETS

DATASETS = (
    "../shared/data/room0",
    "../shared/data/room3",
    "../shared/data/room5",
    "../shared/data/7scenes-redkitchen-000-499",
)


def _ints(text: str) -> list[int]:
    values = [int(v) for v in text.split(",") if v]
    if not values or min(values) < 0:
        raise argparse.ArgumentTypeError(f"want comma-separated numbers, got {text!r}")
    return values


def run_folder(out: Path, dataset: str, stride: int, seed: int) -> Path:
    return out / f"{Path(dataset).name}_st{stride}_s{seed}"


def run_one(out: Path, dataset: str, stride: int, seed: int, preset: str, report: bool) -> dict:
    """One run (or the one already there); its figures, or why there are none. `report`:
    run nothing, take what is there."""
    folder = run_folder(out, dataset, stride, seed)
    metrics = folder / "metrics.json"
    if not metrics.is_file() and report:
        return {"error": "not run"}
    if not metrics.is_file():
        log = folder.with_suffix(".log")
        folder.parent.mkdir(parents=True, exist_ok=True)
        argv = [
            sys.executable, "-m", "dimslam.common.cli", "run", dataset, "--out", str(folder),
            "--preset", preset, "--seed", str(seed), "--stride", str(stride),
            "--single-process", "--threads", "1", "--no-mesh",
        ]  # fmt: skip
        print(f"run: {' '.join(argv[2:])}", flush=True)
        with open(log, "w") as f:
            code = subprocess.run(argv, stdout=f, stderr=subprocess.STDOUT).returncode
        if code != 0 or not metrics.is_file():
            return {"error": f"exit {code}, see {log}"}
    m = json.loads(metrics.read_text())
    return {
        "ate_m": m["ate_rmse_m"],
        "matched": m["matched"],
        "lost": m.get("frames_lost", 0),
        "seconds": m.get("seconds"),
    }


def _ate_cell(run: dict) -> str:
    if "ate_m" in run:
        return f"{100 * run['ate_m']:.2f} cm"
    return run["error"] if run["error"] == "not run" else f"failed ({run['error']})"


def table(results: dict) -> str:
    rows = [
        "| sequence | stride | ATE per seed | mean | / stride 1 | frames lost | frames posed |",
        "|---|---|---|---|---|---|---|",
    ]
    for dataset, by_stride in results.items():
        base = by_stride.get(1, {}).get("mean_m")
        for stride, r in sorted(by_stride.items()):
            seeds = r["seeds"]
            ates = ", ".join(_ate_cell(s) for s in seeds.values())
            mean = r.get("mean_m")
            shown = "-" if mean is None else f"{100 * mean:.2f} cm"
            ratio = f"{mean / base:.2f}x" if mean and base else "-"
            lost = ", ".join(str(s.get("lost", "-")) for s in seeds.values())
            posed = ", ".join(str(s.get("matched", "-")) for s in seeds.values())
            rows.append(
                f"| {Path(dataset).name} | {stride} | {ates} "
                f"| {shown} | {ratio} | {lost} | {posed} |"
            )
    return "\n".join(rows)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, required=True, help="run folders (reused when complete)")
    p.add_argument("--datasets", default=",".join(DATASETS), help="comma-separated folders")
    p.add_argument("--strides", type=_ints, default=[1, 2, 3], help="comma-separated (1,2,3)")
    p.add_argument("--seeds", type=_ints, default=[0, 1, 2], help="comma-separated (0,1,2)")
    p.add_argument("--preset", choices=sorted(PRESETS), default="cpu")
    p.add_argument("--jobs", type=int, default=2, help="runs at a time, one thread each (2)")
    p.add_argument("--json", type=Path, help="write the figures as JSON")
    p.add_argument(
        "--report", action="store_true", help="run nothing: the table of the runs already there"
    )
    args = p.parse_args()
    datasets = [d for d in args.datasets.split(",") if d]
    for d in datasets:
        if not Path(d).exists():
            p.error(f"no dataset at {d}")
    # The slowest first (most frames), so the last runs to finish are short ones.
    jobs = sorted(
        ((d, k, s) for d in datasets for k in args.strides for s in args.seeds),
        key=lambda j: j[1],
    )
    with ThreadPoolExecutor(max(1, args.jobs)) as pool:
        figures = list(pool.map(lambda j: run_one(args.out, *j, args.preset, args.report), jobs))
        done = dict(zip(jobs, figures, strict=True))
    results: dict = {}
    for (d, k, s), r in done.items():
        entry = results.setdefault(d, {}).setdefault(k, {"seeds": {}})
        entry["seeds"][s] = r
    for by_stride in results.values():
        for entry in by_stride.values():
            ates = [r["ate_m"] for r in entry["seeds"].values() if "ate_m" in r]
            if len(ates) == len(entry["seeds"]):
                entry["mean_m"] = statistics.mean(ates)
    print(table(results))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"preset": args.preset, "results": results}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

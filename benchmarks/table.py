"""The development table: every sequence and seed (and stride), one preset and settings.

    python benchmarks/table.py --out out/as_is
    python benchmarks/table.py --out out/floor --set render.normalize_depth=true \
        --set render.normalize_floor=0.5 --against out/as_is
    python benchmarks/table.py --out out/strides --strides 1,2,3
    python benchmarks/table.py --out out/strides --strides 4,6 --seeds 0 \
        --datasets ../shared/data/room0

Runs `dimslam run DATASET --stride K --seed S --single-process --threads 1 --no-mesh` with
the `--preset` (cpu by default) and every `--set KEY=VALUE` (`--KEY VALUE` of `dimslam run`)
for every dataset, stride and seed, `--jobs` at a time, each into `OUT/<dataset>_st<K>_s<S>`.
A run whose folder already holds metrics.json is not run again, so an interrupted table
resumes and one with more strides or seeds adds only those (`--report`: run nothing,
tabulate what is there). `OUT/table.json` records the preset and settings; a folder made
with others is refused, so one table never mixes two settings.

Stride K uses every K-th frame: the camera moves K times as far between frames, as a faster
camera would (issue "Fast motion").

Prints, per dataset and stride: the ATE of each seed (Sim(3), over the frames with a pose),
their mean, the mean of the same runs in `--against` (another table's folder) and the ratio,
the ratio to the stride-1 mean (where stride 1 was run), frames lost (the tracker gave them
no pose) and the segment-scale spread of each run (`benchmarks/drift.py`); `--json FILE`
writes the same. A run that failed or did not reach the end is shown as such, with its log.
The project's rule reads off this table: a change is a gain when no sequence's mean is worse.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from dimslam.common.config import PRESETS
from dimslam.common.options import overrides_or_exit, setting

DATASETS = (
    "../shared/data/room0",
    "../shared/data/room3",
    "../shared/data/room5",
    "../shared/data/7scenes-redkitchen-000-499",
)
SETTINGS = "table.json"


def _ints(text: str) -> list[int]:
    values = [int(v) for v in text.split(",") if v]
    if not values or min(values) < 0:
        raise argparse.ArgumentTypeError(f"want comma-separated numbers, got {text!r}")
    return values


def claim(
    out: Path, preset: str, sets: dict[str, str], more: dict | None = None, name: str = SETTINGS
) -> None:
    """Record the runs' settings (the preset, `sets` and `more`) in `out/name`, or check that
    those recorded there are these.

    Raises:
        ValueError: `out` holds runs of other settings.
    """
    mine = {"preset": preset, "set": dict(sorted(sets.items())), **(more or {})}
    path = out / name
    if path.is_file():
        theirs = json.loads(path.read_text())
        if theirs != mine:
            raise ValueError(f"{out} holds runs of other settings: {theirs} (these: {mine})")
        return
    out.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(mine, indent=2) + "\n")


def run_folder(out: Path, dataset: str, stride: int, seed: int) -> Path:
    return out / f"{Path(dataset).name}_st{stride}_s{seed}"


def figures(folder: Path) -> dict | None:
    """A finished run's figures, or None where it has no metrics.json."""
    metrics = folder / "metrics.json"
    if not metrics.is_file():
        return None
    m = json.loads(metrics.read_text())
    return {
        "ate_m": m["ate_rmse_m"],
        "matched": m["matched"],
        "lost": m.get("frames_lost", 0),
        "spread": m.get("segment_scale_spread"),
        "seconds": m.get("seconds"),
    }


def run_logged(
    folder: Path, args: list[str], read: Callable[[Path], dict | None] = figures
) -> dict:
    """`dimslam run ARGS --out FOLDER`, its output in FOLDER.log, unless FOLDER holds a
    finished run already; the run's figures (`read`), or why there are none."""
    found = read(folder)
    if found is not None:
        return found
    log = folder.with_suffix(".log")
    argv = [sys.executable, "-m", "dimslam.common.cli", "run", *args, "--out", str(folder)]
    print(f"run: {' '.join(argv[3:])}", flush=True)
    with open(log, "w") as f:
        code = subprocess.run(argv, stdout=f, stderr=subprocess.STDOUT).returncode
    found = read(folder)
    if code != 0 or found is None:
        return {"error": f"exit {code}, see {log}"}
    return found


def run_one(
    out: Path, dataset: str, stride: int, seed: int, preset: str, sets: dict, report: bool
) -> dict:
    """One run (or the one already there); its figures, or why there are none. `report`:
    run nothing, take what is there."""
    folder = run_folder(out, dataset, stride, seed)
    if report:
        return figures(folder) or {"error": "not run"}
    args = [
        dataset, "--preset", preset, "--seed", str(seed), "--stride", str(stride),
        "--single-process", "--threads", "1", "--no-mesh",
    ]  # fmt: skip
    for key, value in sets.items():
        args += [f"--{key}", value]
    return run_logged(folder, args)


def _ate_cell(run: dict) -> str:
    if "ate_m" in run:
        return f"{100 * run['ate_m']:.2f} cm"
    return run["error"] if run["error"] == "not run" else f"failed ({run['error']})"


def _mean(runs: list[dict]) -> float | None:
    ates = [r["ate_m"] for r in runs if r and "ate_m" in r]
    return statistics.mean(ates) if ates and len(ates) == len(runs) else None


def table(results: dict) -> str:
    rows = [
        "| sequence | stride | ATE per seed | mean | against | / against | / stride 1 "
        "| frames lost | scale spread |",
        "|---|---|---|---|---|---|---|---|---|",
    ]

    def cm(value: float | None) -> str:
        return "-" if value is None else f"{100 * value:.2f} cm"

    for dataset, by_stride in results.items():
        base = by_stride.get(1, {}).get("mean_m")
        for stride, r in sorted(by_stride.items()):
            seeds = r["seeds"]
            ates = ", ".join(_ate_cell(s) for s in seeds.values())
            mean, against = r.get("mean_m"), r.get("against_m")
            ratio = f"{mean / against:.2f}x" if mean and against else "-"
            to_base = f"{mean / base:.2f}x" if mean and base and stride != 1 else "-"
            lost = ", ".join(str(s.get("lost", "-")) for s in seeds.values())
            spread = ", ".join(
                "-" if s.get("spread") is None else f"{100 * s['spread']:.0f} %"
                for s in seeds.values()
            )
            rows.append(
                f"| {Path(dataset).name} | {stride} | {ates} | {cm(mean)} | {cm(against)} "
                f"| {ratio} | {to_base} | {lost} | {spread} |"
            )
    return "\n".join(rows)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, required=True, help="run folders (reused when complete)")
    p.add_argument("--datasets", default=",".join(DATASETS), help="comma-separated folders")
    p.add_argument("--strides", type=_ints, default=[1], help="comma-separated (1)")
    p.add_argument("--seeds", type=_ints, default=[0, 1, 2], help="comma-separated (0,1,2)")
    p.add_argument("--preset", choices=sorted(PRESETS), default="cpu")
    p.add_argument(
        "--set",
        action="append",
        type=setting,
        default=[],
        metavar="KEY=VALUE",
        help="a setting of every run, e.g. render.normalize_depth=true (repeatable)",
    )
    p.add_argument(
        "--against", type=Path, help="another table's folder: its means beside these, and ratios"
    )
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
    if args.against is not None and not args.against.is_dir():
        p.error(f"--against: no folder at {args.against}")
    sets = dict(args.set)
    overrides_or_exit(p, PRESETS[args.preset], sets)  # an unknown key or a wrong type: refused
    if not args.report:
        try:
            claim(args.out, args.preset, sets)
        except ValueError as e:
            p.error(str(e))
    # The slowest first (most frames), so the last runs to finish are short ones.
    jobs = sorted(
        ((d, k, s) for d in datasets for k in args.strides for s in args.seeds),
        key=lambda j: j[1],
    )
    with ThreadPoolExecutor(max(1, args.jobs)) as pool:
        done = list(pool.map(lambda j: run_one(args.out, *j, args.preset, sets, args.report), jobs))
    results: dict = {}
    for (d, k, s), r in zip(jobs, done, strict=True):
        entry = results.setdefault(d, {}).setdefault(k, {"seeds": {}})
        entry["seeds"][s] = r
    for d, by_stride in results.items():
        for k, entry in by_stride.items():
            entry["mean_m"] = _mean(list(entry["seeds"].values()))
            if args.against is not None:
                theirs = [figures(run_folder(args.against, d, k, s)) for s in entry["seeds"]]
                entry["against_m"] = _mean(theirs)
    print(table(results))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        report = {"preset": args.preset, "set": sets, "results": results}
        args.json.write_text(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

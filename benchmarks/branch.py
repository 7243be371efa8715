"""One run up to a frame, then the rest of it once per tracker variant, from the same state.

    python benchmarks/branch.py DATASET --at F [--seed S] [--preset cpu]
        --variant '' --variant 'tracker.huber=0.0118' --variant 'tracker.solver=adam' ...
        [--out DIR] [--json FILE]

Single-process runs are chaotic: the poses feed the map, which feeds the poses, so two whole
runs that differ in one setting differ everywhere after the first frame where they part, and
a stretch that goes wrong in one run may not be reached in the other. This runs SLAM (one
process, one thread) on DATASET's first F frames once, then forks a child per variant that
continues from that state: the same map, keyframes, poses and random stream, with only the
variant's settings changed on the tracking side. Each child maps and tracks the rest of the
sequence, finishes as `dimslam run` does, writes `DIR/<k>/trajectory.txt` and reports:

- *ATE*: the whole trajectory's, after Sim(3) (as `dimslam eval`);
- *after F*: over the frames from F on, under that same alignment: the RMSE, the steps that
  point backwards (`benchmarks/drift.py --steps`), the rotation turned over the true one,
  and the error of the last frame;
- the frames lost.

With `--truth`, each child whose tracker is the direct one also prints, for every frame it
tracks, whether the solve found the minimum of its own cost or the cost itself is wrong: the
cost at its solution and at the true pose (placed in the run's world by the Sim(3) of the
`TRUTH_FRAMES` frames before F), how far apart the two are, and where a solve started at
the true pose ends. A child whose tracker is the Adam one prints, for every frame, how far
its pose is from the truth and where a direct solve (the variant's direct settings, its own
references and random stream) ends when started at that pose: whether the direct cost's
minimum lies where the Adam tracker stopped. The lines do not change the run.

A variant is `key=value` overrides joined by `;`, keys in the `tracker.` and `loss.`
sections or `mapper.refine_*` (the loss settings reach the Adam window tracker and
the keyframes' refinement only; the mapper keeps the run's other settings); '' is the run as
it is. A variant of the same solver swaps its settings in and keeps what the solver cached;
another solver (or the direct one comparing colours instead of grey, or back) starts fresh
at F (the direct one renders its references from the map at F).
Children run one after another. POSIX only (fork).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
import traceback
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from dimslam.common.config import PRESETS
from dimslam.common.eval.drift import frame_steps
from dimslam.common.eval.evaluation import Sim3, associate, evaluate_trajectory
from dimslam.common.geometry import pose
from dimslam.common.io.datasets import ReaderOptions, open_dataset
from dimslam.common.io.trajectory import Trajectory, write_tum
from dimslam.common.map.render import FieldFn
from dimslam.common.optim.window import FrameState, TrackingLost
from dimslam.common.options import apply_overrides, overrides_or_exit, setting
from dimslam.common.slam import Slam
from dimslam.tracker.direct import DirectTracker
from dimslam.tracker.tracker import Tracker, TrackResult

SECTIONS = ("tracker.", "loss.", "mapper.refine_")
TRUTH_FRAMES = 30
"""Frames before the branch point whose poses place the ground truth in a run's world."""


def parse_variant(text: str) -> dict[str, str]:
    """`key=value;key=value` -> overrides; only the tracking side's settings.

    Raises:
        argparse.ArgumentTypeError: a part that is not `key=value`, or a key elsewhere.
    """
    pairs = [setting(part) for part in filter(None, (p.strip() for p in text.split(";")))]
    outside = [key for key, _ in pairs if not key.startswith(SECTIONS)]
    if outside:
        raise argparse.ArgumentTypeError(f"{outside}: only keys in {', '.join(SECTIONS)}")
    return dict(pairs)


def switch(slam: Slam, overrides: dict[str, str]) -> None:
    """Give the tracking side `overrides`: the same solver takes the new settings, another
    one is built (and a direct one renders its references from the current map)."""
    if not overrides:
        return
    cfg = apply_overrides(slam.cfg, overrides)
    front = slam.front
    if cfg.tracker.pyramid_levels > slam.cfg.tracker.pyramid_levels:
        raise ValueError(
            "tracker.levels, tracker.reloc_levels: a branch's pyramid can be shorter, not taller"
        )
    same = (cfg.tracker.solver == "direct") == isinstance(front.tracker, DirectTracker)
    # Cached references hold grey levels or colours: another choice renders them afresh.
    same = same and cfg.tracker.colour == slam.cfg.tracker.colour
    front.cfg = cfg
    slam.back.cfg = cfg  # read per round for the keyframes' refinement; the Mapper keeps its own
    if same:
        front.tracker.cfg = cfg.tracker
        if isinstance(front.tracker, Tracker):
            front.tracker.loss_cfg = cfg.loss
        return
    if cfg.tracker.solver == "direct":
        front.tracker = DirectTracker(cfg.tracker, cfg.render, slam.camera, slam.generator)
        front.tracker.map_changed(slam.back.field, front.keyframes, slam.back.rounds)
    else:
        front.tracker = Tracker(cfg.tracker, cfg.loss, cfg.render, slam.camera, slam.generator)


def truth_in_run(
    slam: Slam, gt: Trajectory, at: int
) -> tuple[Callable[[float], np.ndarray | None], float]:
    """The true pose at a timestamp (None where the ground truth has none), in the run's
    world, and the run's scale there: the Sim(3) that takes the true poses of the
    `TRUTH_FRAMES` frames before `at` onto the run's (the rotation from the orientations,
    which a short, straight stretch of centres leaves loose; then scale and shift from the
    centres), applied to the ground truth. Timestamps are matched as the evaluation does."""
    est = slam.trajectory()
    recent = {f.timestamp for f in slam.frames if at - TRUTH_FRAMES <= f.index < at}
    i_est, i_gt = associate(est.timestamps, gt.timestamps)
    pairs = [
        (est.poses[i], gt.poses[j])
        for i, j in zip(i_est, i_gt, strict=True)
        if est.timestamps[i] in recent
    ]
    u, _, vt = np.linalg.svd(sum(E[:3, :3] @ G[:3, :3].T for E, G in pairs))
    R = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    ce = np.stack([E[:3, 3] for E, _ in pairs])
    cg = np.stack([G[:3, 3] for _, G in pairs]) @ R.T
    ce0, cg0 = ce - ce.mean(0), cg - cg.mean(0)
    s = float((ce0 * cg0).sum() / (cg0 * cg0).sum())
    sim = Sim3(s, R, ce.mean(0) - s * cg.mean(0))

    def truth(t: float) -> np.ndarray | None:
        _, j = associate(np.array([t]), gt.timestamps)
        return sim.apply_poses(gt.poses[j[0]]) if len(j) else None

    return truth, s


def _after_each_frame(
    tracker: DirectTracker | Tracker,
    truth: Callable[[float], np.ndarray | None],
    report: Callable[[FieldFn, FrameState, TrackResult, np.ndarray], None],
) -> None:
    """Call `report(field, frame, result, true pose)` after each frame `tracker` tracks that
    the ground truth has."""
    track = tracker.track

    def watched(field, local, keyframes):
        result = track(field, local, keyframes)
        true = truth(local[-1].timestamp)
        if true is not None:
            report(field, local[-1], result, true)
        return result

    tracker.track = watched


def watch_truth(
    tracker: DirectTracker, truth: Callable[[float], np.ndarray | None], scale: float
) -> None:
    """Print, for each frame `tracker` tracks, its solve's cost at the solution and at the
    true pose, the distance between them and where a solve from the true pose ends (finest
    level, the solution's references and brightness); the run itself is left as it was."""

    def report(field, frame, result, true):
        state = tracker.generator.get_state()  # the check draws its own point order
        refs = [tracker.references[i] for i in result.stats.references]
        problem = tracker._problem(tracker.images(frame), refs, tracker._points(refs), 0)
        tracker.generator.set_state(state)
        ab = tracker._brightness(refs)
        solved = frame.T_wc.double().numpy()
        end, _, _, end_cost = problem.minimize(np.linalg.inv(true), ab, 40)
        end = np.linalg.inv(end)
        print(
            f"  {frame.index}: cost {1e4 * problem.evaluate(np.linalg.inv(solved), ab).cost:.3f}"
            f" at the solution, {1e4 * problem.evaluate(np.linalg.inv(true), ab).cost:.3f} at"
            f" the truth ({_apart(solved, true, scale)}); from the truth to"
            f" {1e4 * end_cost:.3f}, {_apart(end, true, scale)} from it,"
            f" {_apart(end, solved, scale)} from the solution; references"
            f" {list(result.stats.references)}",
            flush=True,
        )

    _after_each_frame(tracker, truth, report)


def watch_adam(slam: Slam, truth: Callable[[float], np.ndarray | None], scale: float) -> None:
    """Print, for each frame the Adam tracker tracks, its pose's distance to the true pose,
    and where a direct solve started at its pose ends (its distance to both, the direct cost
    at both ends); the direct solver is a shadow with references and a random stream of its
    own, so the run itself is left as it was."""
    cfg = apply_overrides(slam.front.cfg, {"tracker.solver": "direct"})  # the variant's
    shadow = DirectTracker(cfg.tracker, cfg.render, slam.camera, torch.Generator().manual_seed(0))

    def report(field, frame, result, true):
        shadow.map_changed(field, slam.front.keyframes, slam.back.rounds)
        refs, _ = shadow.choose(field, slam.front.keyframes, frame.T_wc)
        adam = frame.T_wc.double().numpy()
        line = f"  {frame.index}: Adam {_apart(adam, true, scale)} from the truth; "
        if not refs:
            print(line + "no reference for a direct solve", flush=True)
            return
        images = shadow.images(frame)
        start = FrameState(frame.index, frame.timestamp, frame.rgb, frame.T_wc.clone())
        try:
            end = shadow.solve(start, refs, images, hold=cfg.tracker.hold).T_wc.double().numpy()
        except TrackingLost as e:
            print(line + f"a direct solve from it is lost ({e})", flush=True)
            return
        problem = shadow._problem(images, refs, shadow._points(refs), 0)
        ab = shadow._brightness(refs)
        cost = {k: 1e4 * problem.evaluate(np.linalg.inv(T), ab).cost for k, T in
                (("adam", adam), ("end", end))}  # fmt: skip
        print(
            line + f"a direct solve from it ends {_apart(end, adam, scale)} from it,"
            f" {_apart(end, true, scale)} from the truth; direct cost {cost['adam']:.3f} at"
            f" the Adam pose, {cost['end']:.3f} at the end",
            flush=True,
        )

    _after_each_frame(slam.front.tracker, truth, report)


def _apart(a: np.ndarray, b: np.ndarray, scale: float) -> str:
    turn = math.degrees(pose.rotation_angle(torch.from_numpy(a[:3, :3].T @ b[:3, :3])))
    cm = 100 * np.linalg.norm(a[:3, 3] - b[:3, 3]) / scale
    return f"{cm:.1f} cm, {turn:.2f} deg"


def figures(slam: Slam, gt, at: int) -> dict:
    """What a branch did: the whole ATE, and the frames from `at` on under its alignment."""
    est = slam.trajectory()
    whole = evaluate_trajectory(est, gt, align="sim3")
    # Matched poses are in the estimate's order; the frames from `at` on are those whose
    # index is at least `at` (lost frames have no pose).
    indices = [f.index for f in slam.frames]
    first = next((k for k, i in enumerate(indices) if i >= at), len(indices))
    steps = frame_steps(est, gt, first, len(indices) - 1)
    errors = whole.errors_m[first:]
    true_turn = sum(s.gt_deg for s in steps)
    return {
        "ate_cm": 100 * whole.ate_rmse_m,
        "after_rmse_cm": 100 * float(np.sqrt(np.mean(errors**2))) if len(errors) else math.nan,
        "steps_back": sum(1 for s in steps if s.cos < 0),
        "turned_over_true": sum(s.est_deg for s in steps) / true_turn if true_turn else math.nan,
        "last_err_cm": 100 * float(errors[-1]) if len(errors) else math.nan,
        "lost": len(slam.lost_frames),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("dataset", help="a dataset with ground truth")
    p.add_argument("--at", type=int, required=True, help="frames run once before the branches")
    p.add_argument(
        "--variant", type=parse_variant, action="append", required=True, help="'k=v;k=v' ('' as is)"
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--preset", choices=sorted(PRESETS), default="cpu")
    p.add_argument("--out", type=Path, default=Path("branch-out"), help="trajectories here")
    p.add_argument("--json", type=Path, help="also write the figures here")
    p.add_argument(
        "--truth",
        action="store_true",
        help="per frame: a direct variant's cost at its solution and at the true pose; "
        "where a direct solve from an Adam variant's pose ends",
    )
    args = p.parse_args()
    torch.set_num_threads(1)
    cfg = apply_overrides(PRESETS[args.preset], {"seed": str(args.seed)})
    for variant in args.variant:  # an unknown key or a wrong type: refused before any part runs
        overrides_or_exit(p, cfg, variant)
    reader = open_dataset(args.dataset, options=ReaderOptions(width=cfg.width or None))
    gt = reader.ground_truth()
    if gt is None:
        p.error(f"{args.dataset} has no ground truth")
    if not 0 < args.at < len(reader):
        p.error(f"--at must lie inside the sequence's {len(reader)} frames")
    slam = Slam(cfg, reader.camera, torch.device("cpu"))
    frames = iter(reader)
    started = time.perf_counter()
    for n in range(args.at):
        slam.add(next(frames))
        if n % 25 == 0:
            print(f"  frame {n}/{args.at}, {time.perf_counter() - started:.0f} s", flush=True)
    rest = list(frames)
    print(f"{args.at} frames in {time.perf_counter() - started:.0f} s; branching", flush=True)
    results = []
    for k, overrides in enumerate(args.variant):
        text = ";".join(f"{key}={value}" for key, value in overrides.items())
        out = args.out / str(k)
        out.mkdir(parents=True, exist_ok=True)
        pid = os.fork()
        if pid == 0:  # the child: the rest of the run from the shared state
            code = 1
            try:
                switch(slam, overrides)
                if args.truth and isinstance(slam.front.tracker, DirectTracker):
                    watch_truth(slam.front.tracker, *truth_in_run(slam, gt, args.at))
                elif args.truth:
                    watch_adam(slam, *truth_in_run(slam, gt, args.at))
                for frame in rest:
                    slam.add(frame)
                slam.finish()
                write_tum(out / "trajectory.txt", slam.trajectory(), header=f"variant {text!r}")
                (out / "figures.json").write_text(json.dumps(figures(slam, gt, args.at)) + "\n")
                code = 0
            except BaseException:  # os._exit below would swallow it
                traceback.print_exc()
            finally:
                sys.stdout.flush()
                os._exit(code)
        _, status = os.waitpid(pid, 0)
        got = json.loads((out / "figures.json").read_text()) if status == 0 else None
        results.append({"variant": text, **(got or {"failed": True})})
        line = (
            f"ATE {got['ate_cm']:6.2f} cm | after {args.at}: {got['after_rmse_cm']:6.2f} cm, "
            f"{got['steps_back']:2d} steps back, turned {got['turned_over_true']:.2f}, last "
            f"{got['last_err_cm']:6.2f} cm | lost {got['lost']}"
            if got
            else "failed"
        )
        print(f"[{k}] {text or '(as is)':40s} {line}", flush=True)
    if args.json:
        args.json.write_text(json.dumps({"at": args.at, "results": results}, indent=2) + "\n")


if __name__ == "__main__":
    main()

"""Where along the path an estimate's error comes from: local accuracy and local scale.

    python benchmarks/drift.py TRAJ DATASET [--segment 30] [--frames N] [--steps A-B]
        [--keyframes KEYFRAMES] [--json FILE]

TRAJ is a TUM trajectory (a run's `trajectory.txt`), DATASET anything the readers know with
ground truth. The whole trajectory is aligned once (Sim(3), as `dimslam eval` does); then the
path is cut into consecutive segments of `--segment` matched poses and each is aligned on its
own (`common/eval/drift.py`). Per segment it prints:

- *global err*: mean error of the segment's poses under the one global alignment;
- *share*: the segment's part of the whole trajectory's squared error (of the ATE's square);
- *local ATE*: RMSE after the segment's own Sim(3): how well the segment is tracked in itself;
- *local scale*: the segment's own scale relative to the global one (1: no scale drift);
- *path* and *turn*: ground-truth distance travelled and rotation turned within the segment.

A small local ATE with a large global error and local scales away from 1 says the error is
scale drift between segments, not tracking noise within them. `--frames N` keeps only the
estimate's first N poses (alignment included): what the ATE would be without a bad final
stretch. `--steps A-B` then prints, for matched poses A to B, each frame-to-frame step of
the estimate (under the global alignment) against the ground truth's: its length, the cosine
between the two directions (-1: the estimate moved back) and the rotation turned. A tracker
that trades translation for rotation shows there as a step pointing the wrong way while it
turns too far. `--keyframes` (a run's `keyframes.txt`) compares the steps' length errors
(|est / gt - 1| under the global alignment) on the steps that end on a keyframe with the
others': a trajectory whose frames between keyframes did not follow the keyframes'
corrections jumps at each keyframe.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from dimslam.common.eval.drift import SEGMENT, frame_steps, scale_spread, segment_drift
from dimslam.common.io.datasets import open_dataset
from dimslam.common.io.trajectory import Trajectory, read_tum


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("traj", help="estimated trajectory, TUM format")
    p.add_argument("dataset", help="dataset with ground truth")
    p.add_argument("--segment", type=int, default=SEGMENT, help="matched poses per segment")
    p.add_argument("--frames", type=int, help="use only the estimate's first N poses")
    p.add_argument("--steps", help="A-B: print the frame-to-frame steps of matched poses A..B")
    p.add_argument(
        "--keyframes",
        type=Path,
        help="the run's keyframes.txt: length errors of the steps onto keyframes and the rest",
    )
    p.add_argument("--json", type=Path, help="also write the figures here")
    args = p.parse_args()
    steps = None
    if args.steps is not None:
        try:
            steps = tuple(int(x) for x in args.steps.split("-"))
            if len(steps) != 2 or not 0 <= steps[0] <= steps[1]:
                raise ValueError
        except ValueError:
            p.error(f"--steps wants A-B with 0 <= A <= B, got {args.steps!r}")
    if args.segment < 3:
        p.error("--segment must be at least 3 (a Sim(3) needs 3 points)")
    if args.frames is not None and args.frames < 3:
        p.error("--frames must be at least 3 (a Sim(3) needs 3 points)")
    est = read_tum(args.traj)
    if args.frames is not None:
        est = Trajectory(est.timestamps[: args.frames], est.poses[: args.frames])
    gt = open_dataset(args.dataset).ground_truth()
    if gt is None:
        raise SystemExit(f"error: {args.dataset} has no ground truth")
    whole, rows = segment_drift(est, gt, args.segment)
    print(
        f"ATE {100 * whole.ate_rmse_m:.2f} cm, scale {whole.alignment.s:.3f}, "
        f"RPE {whole.rpe_trans_per_m:.3f} m/m, {whole.matched} poses, "
        f"segment scale spread {100 * scale_spread(rows):.1f} %"
    )
    print("frames   | global err | share | local ATE | local scale | path   | turn")
    for r in rows:
        print(
            f"{r.first:3d}-{r.last:3d}  | {100 * r.global_err_m:7.2f} cm | {100 * r.share:3.0f} % "
            f"| {100 * r.local_ate_m:6.2f} cm | {r.local_scale:11.3f} "
            f"| {100 * r.path_m:4.0f} cm | {r.turn_deg:4.0f} deg"
        )
    figures = {"whole": whole.to_dict(), "segments": [r.to_dict() for r in rows]}
    if steps is not None:
        moves = frame_steps(est, gt, *steps)
        print("frame | err      | step est / gt    | cos   | turn est / gt")
        for m in moves:
            print(
                f"{m.index:5d} | {100 * m.err_m:5.2f} cm | {100 * m.est_m:5.2f} / "
                f"{100 * m.gt_m:5.2f} cm | {m.cos:+.2f} | {m.est_deg:4.2f} / {m.gt_deg:4.2f} deg"
            )
        figures["steps"] = [m.to_dict() for m in moves]
    if args.keyframes is not None:
        figures["keyframe_steps"] = keyframe_steps(est, gt, read_tum(args.keyframes))
    if args.json:
        args.json.write_text(json.dumps(figures, indent=2) + "\n")


def keyframe_steps(est: Trajectory, gt: Trajectory, keyframes: Trajectory) -> dict:
    """Print and return the steps' length errors |est / gt - 1|, median and 90th percentile,
    on the steps that end on a keyframe and on the others."""
    at_keyframe = {round(float(t), 6) for t in keyframes.timestamps}
    groups: dict[str, list[float]] = {"onto keyframes": [], "between": []}
    for m in frame_steps(est, gt, 1, len(est) - 1):
        if m.gt_m > 0:
            name = "onto keyframes" if round(m.timestamp, 6) in at_keyframe else "between"
            groups[name].append(abs(m.est_m / m.gt_m - 1))
    figures = {}
    for name, errors in groups.items():
        if errors:
            median, p90 = np.percentile(errors, [50, 90])
            print(f"step length error {name}: {median:.3f} median, {p90:.3f} p90 ({len(errors)})")
            figures[name] = {"median": float(median), "p90": float(p90), "steps": len(errors)}
    return figures


if __name__ == "__main__":
    main()

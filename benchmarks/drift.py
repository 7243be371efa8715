"""Where along the path an estimate's error comes from: local accuracy and local scale.

    python benchmarks/drift.py TRAJ DATASET [--segment 30] [--frames N] [--json FILE]

TRAJ is a TUM trajectory (a run's `trajectory.txt`), DATASET anything the readers know with
ground truth. The whole trajectory is aligned once (Sim(3), as `dimslam eval` does); then the
path is cut into consecutive segments of `--segment` matched poses and each is aligned on its
own. Per segment it prints:

- *global err*: mean error of the segment's poses under the one global alignment;
- *local ATE*: RMSE after the segment's own Sim(3): how well the segment is tracked in itself;
- *local scale*: the segment's own scale relative to the global one (1: no scale drift);
- *path* and *turn*: ground-truth distance travelled and rotation turned within the segment.

A small local ATE with a large global error and local scales away from 1 says the error is
scale drift between segments, not tracking noise within them. `--frames N` keeps only the
estimate's first N poses (alignment included): what the ATE would be without a bad final
stretch.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import torch

from dimslam.common.eval.evaluation import associate, evaluate_trajectory, umeyama
from dimslam.common.geometry import pose
from dimslam.common.io.datasets import open_dataset
from dimslam.common.io.trajectory import Trajectory, read_tum


def segments(
    est_path: str, dataset: str, length: int, frames: int | None = None
) -> tuple[dict, list[dict]]:
    est = read_tum(est_path)
    if frames is not None:
        est = Trajectory(est.timestamps[:frames], est.poses[:frames])
    gt = open_dataset(dataset).ground_truth()
    if gt is None:
        raise SystemExit(f"error: {dataset} has no ground truth")
    whole = evaluate_trajectory(est, gt)
    idx_est, idx_gt = associate(est.timestamps, gt.timestamps)  # as evaluate_trajectory
    E = whole.alignment.apply_poses(est.poses[idx_est])
    G = gt.poses[idx_gt]
    rows = []
    for a in range(0, len(E) - length + 1, length):
        e, g = E[a : a + length, :3, 3], G[a : a + length, :3, 3]
        local = umeyama(e, g)
        err = np.linalg.norm(local.apply_points(e) - g, axis=1)
        turn = G[a, :3, :3].T @ G[a + length - 1, :3, :3]
        rows.append(
            {
                "first": a,
                "last": a + length - 1,
                "global_err_m": float(whole.errors_m[a : a + length].mean()),
                "local_ate_m": float(np.sqrt(np.mean(err**2))),
                "local_scale": float(local.s),
                "path_m": float(np.linalg.norm(np.diff(g, axis=0), axis=1).sum()),
                "turn_deg": math.degrees(pose.rotation_angle(torch.from_numpy(turn)).item()),
            }
        )
    return whole.to_dict(), rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("traj", help="estimated trajectory, TUM format")
    p.add_argument("dataset", help="dataset with ground truth")
    p.add_argument("--segment", type=int, default=30, help="matched poses per segment")
    p.add_argument("--frames", type=int, help="use only the estimate's first N poses")
    p.add_argument("--json", type=Path, help="also write the figures here")
    args = p.parse_args()
    if args.segment < 3:
        p.error("--segment must be at least 3 (a Sim(3) needs 3 points)")
    if args.frames is not None and args.frames < 3:
        p.error("--frames must be at least 3 (a Sim(3) needs 3 points)")
    whole, rows = segments(args.traj, args.dataset, args.segment, args.frames)
    print(
        f"ATE {100 * whole['ate_rmse_m']:.2f} cm, scale {whole['scale']:.3f}, "
        f"RPE {whole['rpe_trans_per_m']:.3f} m/m, {whole['matched']} poses"
    )
    print("frames   | global err | local ATE | local scale | path   | turn")
    for r in rows:
        print(
            f"{r['first']:3d}-{r['last']:3d}  | {100 * r['global_err_m']:7.2f} cm "
            f"| {100 * r['local_ate_m']:6.2f} cm | {r['local_scale']:11.3f} "
            f"| {100 * r['path_m']:4.0f} cm | {r['turn_deg']:4.0f} deg"
        )
    if args.json:
        args.json.write_text(json.dumps({"whole": whole, "segments": rows}, indent=2) + "\n")


if __name__ == "__main__":
    main()

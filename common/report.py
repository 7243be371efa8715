"""Evaluating output files against a dataset: what `dimslam eval` and `dimslam run` print.

Ties the evaluator (`evaluation.py`) to files and datasets: reads the estimated trajectory and
mesh, finds the ground truth (a TUM file, or a dataset with its camera and `mesh.ply`), and
formats the figures as the short table both commands print.
"""

from __future__ import annotations

import logging
from pathlib import Path

from dimslam.common.datasets import ReaderOptions, open_dataset
from dimslam.common.errors import DimslamError
from dimslam.common.evaluation import evaluate_mesh, evaluate_trajectory, load_mesh
from dimslam.common.trajectory import read_tum

log = logging.getLogger(__name__)


def load_ground_truth(gt: str, layout: str | None):
    """A ground-truth trajectory from a TUM file, or from a dataset with its camera and mesh."""

    path = Path(gt)
    if path.is_file() and layout is None and path.suffix == ".txt":
        return read_tum(path), None, None
    reader = open_dataset(gt, layout=layout, options=ReaderOptions())
    traj = reader.ground_truth()
    if traj is None or len(traj) == 0:
        raise DimslamError(f"{gt}: the dataset has no ground-truth poses")
    mesh = path / "mesh.ply"
    return traj, reader.camera, mesh if mesh.is_file() else None


def format_metrics(result: dict) -> str:
    """A short human-readable table of the figures in `result` (the `--json` keys)."""
    rows = [
        ("poses matched", "matched", "{:d}"),
        ("ATE RMSE", "ate_rmse_m", "{:.4f} m"),
        ("ATE mean", "ate_mean_m", "{:.4f} m"),
        ("ATE median", "ate_median_m", "{:.4f} m"),
        ("ATE max", "ate_max_m", "{:.4f} m"),
        ("ATE RMSE, poses as published", "online_ate_rmse_m", "{:.4f} m"),
        ("alignment scale", "scale", "{:.4f}"),
        ("RPE translation", "rpe_trans_per_m", "{:.4f} m/m"),
        ("RPE rotation", "rpe_rot_deg_per_frame", "{:.4f} deg/frame"),
        ("mesh accuracy", "accuracy_cm", "{:.2f} cm"),
        ("mesh completion", "completion_cm", "{:.2f} cm"),
        ("completion ratio (<5 cm)", "completion_ratio", "{:.2f} %"),
        ("tracking, mapper busy", "median_track_ms_mapper_busy", "{:.0f} ms/frame (median)"),
        ("tracking, mapper idle", "median_track_ms_mapper_idle", "{:.0f} ms/frame (median)"),
    ]
    width = max(len(name) for name, _, _ in rows)
    return "\n".join(
        f"{name:<{width}}  {fmt.format(result[key])}"
        for name, key, fmt in rows
        if result.get(key) is not None
    )


def evaluate_files(
    traj_path: Path,
    gt: str,
    *,
    layout: str | None = None,
    align: str = "sim3",
    max_dt: float = 0.02,
    mesh: Path | None = None,
    gt_mesh: Path | None = None,
    samples: int = 200_000,
    plot: Path | None = None,
) -> dict:
    """Evaluate a TUM trajectory (and optionally a mesh) against ground truth; returns figures."""

    est = read_tum(traj_path)
    gt_traj, camera, dataset_mesh = load_ground_truth(gt, layout)
    metrics = evaluate_trajectory(est, gt_traj, align=align, max_dt=max_dt)
    result = metrics.to_dict()
    if mesh is not None:
        gt_mesh = gt_mesh or dataset_mesh
        if gt_mesh is None:
            raise DimslamError("--mesh needs --gt-mesh (or a dataset folder holding mesh.ply)")
        if camera is None:
            log.warning("no camera for %s: the ground-truth mesh is not culled to the frustums", gt)
        mesh_metrics = evaluate_mesh(
            load_mesh(mesh),
            load_mesh(gt_mesh),
            metrics.alignment,
            gt_traj.poses if camera is not None else None,
            camera,
            samples=samples,
        )
        result.update(mesh_metrics.to_dict())
    elif gt_mesh is not None:
        raise DimslamError("--gt-mesh needs --mesh (the estimated mesh to compare)")
    if plot is not None:
        from dimslam.common.plot import plot_trajectory  # plotting stays out of the core

        plot_trajectory(
            plot,
            metrics.alignment.apply_trajectory(est),
            gt_traj,
            title=f"{traj_path.name}: ATE RMSE {100 * metrics.ate_rmse_m:.2f} cm",
        )
    return result

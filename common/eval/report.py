"""Evaluating output files against a dataset: what `dimslam eval` and `dimslam run` print.

Ties the evaluator (`evaluation.py`) to files and datasets: reads the estimated trajectory and
mesh, finds the ground truth (a TUM file, or a dataset with its camera and `mesh.ply`), and
formats the figures as the short table both commands print; `report_run` does all of it for
the output folder of a finished run.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from functools import partial
from pathlib import Path

from dimslam.common.errors import DimslamError, EvaluationError
from dimslam.common.eval.drift import segment_scale_spread
from dimslam.common.eval.evaluation import evaluate_trajectory, write_metrics
from dimslam.common.eval.mesh_metrics import evaluate_mesh, load_mesh
from dimslam.common.io.datasets import ReaderOptions, open_dataset
from dimslam.common.io.trajectory import read_tum

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
    """A short human-readable table of the figures in `result` (the `--json` keys); a figure
    that is missing or None (undefined) has no line. A row's format is a `str.format` template
    or a function of the figure."""
    rows = [
        ("poses matched", "matched", "{:d}"),
        ("ATE RMSE", "ate_rmse_m", "{:.4f} m"),
        ("ATE mean", "ate_mean_m", "{:.4f} m"),
        ("ATE median", "ate_median_m", "{:.4f} m"),
        ("ATE max", "ate_max_m", "{:.4f} m"),
        ("ATE RMSE, poses as published", "online_ate_rmse_m", "{:.4f} m"),
        ("alignment scale", "scale", "{:.4f}"),
        ("segment scale spread", "segment_scale_spread", lambda f: f"{100 * f:.1f} %"),
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
        f"{name:<{width}}  {fmt(result[key]) if callable(fmt) else fmt.format(result[key])}"
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
    """Evaluate a TUM trajectory (and optionally a mesh) against ground truth; returns figures:
    `TrajectoryMetrics.to_dict`'s, `segment_scale_spread` (a fraction; None where undefined, as
    on a path shorter than two segments) and, with a mesh, `MeshMetrics.to_dict`'s."""

    est = read_tum(traj_path)
    gt_traj, camera, dataset_mesh = load_ground_truth(gt, layout)
    metrics = evaluate_trajectory(est, gt_traj, align=align, max_dt=max_dt)
    result = metrics.to_dict()
    result["segment_scale_spread"] = segment_scale_spread(est, gt_traj, align=align, max_dt=max_dt)
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
        from dimslam.common.eval.plot import plot_trajectory  # plotting stays out of the core

        plot_trajectory(
            plot,
            metrics.alignment.apply_trajectory(est),
            gt_traj,
            title=f"{traj_path.name}: ATE RMSE {100 * metrics.ate_rmse_m:.2f} cm",
        )
    return result


@dataclass(frozen=True)
class RunSummary:
    """What a run did (`dimslam run`, in one process or through the service)."""

    frames: int
    keyframes: int
    seconds: float
    frames_lost: int
    metrics: dict


def report_run(
    source: str,
    out_dir: Path,
    layout: str | None,
    mesh_path: Path | None,
    seconds: float,
    frames: int,
    extra: dict | None = None,
) -> dict:
    """Evaluate `out_dir/trajectory.txt` (and the mesh) where the dataset has ground truth;
    write metrics.json and trajectory.png and print the table. Returns the figures ({} if none).
    """
    try:
        gt = open_dataset(source, layout=layout).ground_truth()
    except DimslamError:
        gt = None
    if gt is None or len(gt) == 0 or frames < 3:
        return {}
    has_gt_mesh = (Path(source) / "mesh.ply").is_file()
    evaluate = partial(evaluate_files, out_dir / "trajectory.txt", str(source), layout=layout)
    try:
        metrics = evaluate(mesh=mesh_path if has_gt_mesh else None, plot=out_dir / "trajectory.png")
    except EvaluationError as e:  # a mesh far from the truth must not cost the run its ATE
        log.warning("mesh not evaluated: %s", e)
        metrics = evaluate(plot=out_dir / "trajectory.png")
    online = out_dir / "trajectory_online.txt"
    if online.is_file():
        metrics["online_ate_rmse_m"] = evaluate_files(online, str(source), layout=layout)[
            "ate_rmse_m"
        ]
    metrics["seconds"] = seconds
    metrics["fps"] = frames / max(seconds, 1e-9)
    metrics.update(extra or {})
    write_metrics(out_dir / "metrics.json", metrics)
    print(format_metrics(metrics))
    return metrics

"""`dimslam`: the umbrella command (synth, dataset, eval, demo).

Each subcommand is a thin layer over a library function; errors a user can fix
(`DimslamError`) print one line and exit 2, anything else keeps its traceback.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from dimslam.common import logs
from dimslam.common.datasets import LAYOUTS, ReaderOptions, open_dataset
from dimslam.common.errors import DimslamError
from dimslam.common.evaluation import (
    evaluate_mesh,
    evaluate_trajectory,
    load_mesh,
    write_metrics,
)
from dimslam.common.progress import Progress
from dimslam.common.synth import write_sequence
from dimslam.common.trajectory import read_tum, write_tum

log = logging.getLogger("dimslam")

DEMO_OUT = Path("out/demo")


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected WIDTHxHEIGHT such as 320x240, got {text!r}"
        ) from None
    if w < 8 or h < 8:
        raise argparse.ArgumentTypeError(f"image size must be at least 8x8, got {text!r}")
    return w, h


def add_reader_options(p: argparse.ArgumentParser) -> None:
    """The options every dataset reader honours (see `ReaderOptions`)."""

    g = p.add_argument_group("dataset reading")
    g.add_argument(
        "--layout", choices=sorted(LAYOUTS), help="dataset layout (default: detected from the path)"
    )
    g.add_argument("--stride", type=int, default=1, help="use every N-th frame (default: 1)")
    g.add_argument("--start", type=int, default=0, help="first frame to use (default: 0)")
    g.add_argument("--end", type=int, default=None, help="frame to stop before (default: the last)")
    g.add_argument(
        "--width", type=int, default=None, help="resize frames to this width; intrinsics follow"
    )
    g.add_argument(
        "--calib",
        type=Path,
        default=None,
        help="intrinsics file 'fx fy cx cy [k1 k2 p1 p2 [k3]]' overriding the dataset's own",
    )


def reader_options(args: argparse.Namespace):

    return ReaderOptions(
        stride=args.stride, start=args.start, end=args.end, width=args.width, calib=args.calib
    )


def open_source(args: argparse.Namespace, source: str):

    return open_dataset(source, layout=args.layout, options=reader_options(args))


# ---------------------------------------------------------------------------------------------
# synth


def cmd_synth(args: argparse.Namespace) -> int:

    width, height = args.size
    bar = Progress(args.frames, "render")
    summary = write_sequence(
        args.out,
        frames=args.frames,
        width=width,
        height=height,
        seed=args.seed,
        noise=args.noise,
        progress=lambda i, n: bar.update(i + 1),
    )
    bar.close()
    print(
        f"wrote {summary.frames} frames {width}x{height} (seed {args.seed}) to {summary.out_dir} "
        f"in {summary.seconds:.2f} s ({summary.fps:.0f} frames/s)"
    )
    return 0


# ---------------------------------------------------------------------------------------------
# dataset


def cmd_dataset(args: argparse.Namespace) -> int:

    reader = open_source(args, args.path)
    cam = reader.camera
    print(f"layout      {reader.layout}")
    try:
        print(f"frames      {len(reader)}")
    except TypeError:
        print("frames      unbounded (live source)")
    print(f"image       {cam.width}x{cam.height}")
    print(f"intrinsics  fx={cam.fx:.3f} fy={cam.fy:.3f} cx={cam.cx:.3f} cy={cam.cy:.3f}")
    gt = reader.ground_truth()
    if gt is None or len(gt) == 0:
        print("groundtruth none")
    else:
        span = gt.timestamps[-1] - gt.timestamps[0]
        steps = gt.positions[1:] - gt.positions[:-1]
        length = float(np.linalg.norm(steps, axis=1).sum())
        print(f"groundtruth {len(gt)} poses over {span:.2f} s, path length {length:.2f} m")
    if args.write_gt:
        if gt is None or len(gt) == 0:
            raise DimslamError(f"{args.path}: no ground truth to write")
        write_tum(args.write_gt, gt, header=f"ground truth of {args.path} ({reader.layout})")
        print(f"wrote {len(gt)} poses to {args.write_gt}")
    if args.check:
        bar = Progress(len(reader), "decode")
        n = 0
        for n, _ in enumerate(reader, 1):
            bar.update(n)
        bar.close()
        print(f"decoded {n} frames, skipped {reader.skipped} unreadable")
    return 0


# ---------------------------------------------------------------------------------------------
# eval


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
        ("alignment scale", "scale", "{:.4f}"),
        ("RPE translation", "rpe_trans_per_m", "{:.4f} m/m"),
        ("RPE rotation", "rpe_rot_deg_per_frame", "{:.4f} deg/frame"),
        ("mesh accuracy", "accuracy_cm", "{:.2f} cm"),
        ("mesh completion", "completion_cm", "{:.2f} cm"),
        ("completion ratio (<5 cm)", "completion_ratio", "{:.2f} %"),
    ]
    width = max(len(name) for name, _, _ in rows)
    return "\n".join(
        f"{name:<{width}}  {fmt.format(result[key])}" for name, key, fmt in rows if key in result
    )


def evaluate(
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
        from dimslam.common.plot import plot_trajectory

        plot_trajectory(
            plot,
            metrics.alignment.apply_trajectory(est),
            gt_traj,
            title=f"{traj_path.name}: ATE RMSE {100 * metrics.ate_rmse_m:.2f} cm",
        )
    return result


def cmd_eval(args: argparse.Namespace) -> int:
    result = evaluate(
        args.traj,
        args.gt,
        layout=args.layout,
        align=args.align,
        max_dt=args.max_dt,
        mesh=args.mesh,
        gt_mesh=args.gt_mesh,
        samples=args.samples,
        plot=args.plot,
    )
    print(format_metrics(result))
    if args.json:
        write_metrics(args.json, result)
    if args.plot:
        print(f"plot written to {args.plot}")
    return 0


# ---------------------------------------------------------------------------------------------
# demo


def cmd_demo(args: argparse.Namespace) -> int:
    """The main job on the built-in default: render the synthetic scene, run, evaluate."""

    out: Path = args.out
    scene = out / "scene"
    width, height = args.size
    print(
        f"1/3 rendering the built-in synthetic scene ({args.frames} frames {width}x{height}, "
        f"seed {args.seed}) into {scene}"
    )
    bar = Progress(args.frames, "render")
    write_sequence(
        scene,
        frames=args.frames,
        width=width,
        height=height,
        seed=args.seed,
        progress=lambda i, n: bar.update(i + 1),
    )
    bar.close()
    # The SLAM core does not exist yet (issue 3): the ground truth stands in for its output so
    # that reading, trajectory I/O and evaluation run end to end on the same files.
    print("2/3 SLAM core not built yet: using the ground-truth trajectory and mesh as the estimate")
    reader = open_dataset(scene, options=ReaderOptions())
    traj_path = out / "trajectory.txt"
    write_tum(traj_path, reader.ground_truth(), header="demo: ground truth standing in for SLAM")
    print("3/3 evaluating against the ground truth")
    result = evaluate(traj_path, str(scene), mesh=scene / "mesh.ply", plot=out / "trajectory.png")
    write_metrics(out / "metrics.json", result)
    print(format_metrics(result))
    print(f"outputs in {out}: trajectory.txt, metrics.json, trajectory.png")
    return 0


# ---------------------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="dimslam",
        description="Dense RGB-only SLAM with neural implicit maps. Subcommands render the "
        "built-in synthetic scene, inspect datasets and evaluate trajectories and meshes.",
    )
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output")
    parser.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    p = sub.add_parser(
        "synth",
        help="render the built-in synthetic scene as a TUM RGB-D sequence",
        description="Render a textured indoor scene along a smooth handheld-like path "
        "and write it in TUM RGB-D layout with calib.txt, exact z-depth "
        "(depth/, 5000 per metre), groundtruth.txt and the exact mesh (mesh.ply).",
    )
    p.add_argument("out", type=Path, help="output folder (created)")
    p.add_argument(
        "--frames", type=int, default=300, help="number of frames at 30 Hz (default: 300)"
    )
    p.add_argument("--size", type=_size, default=(320, 240), help="WIDTHxHEIGHT (default: 320x240)")
    p.add_argument("--seed", type=int, default=0, help="scene and path seed (default: 0)")
    p.add_argument(
        "--noise", type=float, default=1.0, help="Gaussian noise sigma in 8-bit levels (default: 1)"
    )
    p.set_defaults(func=cmd_synth)

    p = sub.add_parser(
        "dataset",
        help="describe a dataset (layout, frames, intrinsics, ground truth)",
        description="Open a dataset the way the SLAM system will and describe it. "
        "Layouts: TUM RGB-D, Replica (NICE-SLAM), EuRoC ASL, 7-Scenes, image folder "
        "or video with calib.txt, live camera index.",
    )
    p.add_argument("path", help="dataset folder, video file or camera index")
    add_reader_options(p)
    p.add_argument(
        "--write-gt",
        type=Path,
        metavar="OUT.txt",
        help="write the ground truth as a TUM trajectory",
    )
    p.add_argument(
        "--check", action="store_true", help="decode every frame and count unreadable ones"
    )
    p.set_defaults(func=cmd_dataset)

    p = sub.add_parser(
        "eval",
        help="evaluate a trajectory (ATE, RPE) and optionally a mesh",
        description="ATE RMSE after Sim(3) Umeyama alignment (or SE(3)), RPE, and mesh "
        "accuracy / completion / completion ratio at 5 cm (design.md section 6).",
    )
    p.add_argument("--traj", type=Path, required=True, help="estimated trajectory, TUM format")
    p.add_argument(
        "--gt", required=True, help="ground truth: a dataset folder or a TUM trajectory file"
    )
    p.add_argument("--layout", default=None, help="layout of the --gt dataset (default: detected)")
    p.add_argument(
        "--align", choices=("sim3", "se3"), default="sim3", help="alignment (default: sim3)"
    )
    p.add_argument(
        "--max-dt", type=float, default=0.02, help="timestamp association tolerance in s"
    )
    p.add_argument("--mesh", type=Path, help="estimated mesh (PLY) to evaluate")
    p.add_argument(
        "--gt-mesh", type=Path, help="ground-truth mesh (default: mesh.ply in the --gt folder)"
    )
    p.add_argument("--samples", type=int, default=200_000, help="points sampled on each mesh")
    p.add_argument("--json", type=Path, metavar="FILE", help="write the figures as JSON")
    p.add_argument(
        "--plot", type=Path, metavar="PNG", help="draw the aligned trajectory over ground truth"
    )
    p.set_defaults(func=cmd_eval)

    p = sub.add_parser(
        "demo",
        help="the main job on the built-in default scene (no data, no GPU)",
        description="Render the built-in synthetic scene, run on it and evaluate the "
        "result; writes trajectory.txt, metrics.json and trajectory.png.",
    )
    p.add_argument(
        "--out", type=Path, default=DEMO_OUT, help=f"output folder (default: {DEMO_OUT})"
    )
    p.add_argument("--frames", type=int, default=150, help="frames to render (default: 150)")
    p.add_argument("--size", type=_size, default=(320, 240), help="WIDTHxHEIGHT (default: 320x240)")
    p.add_argument("--seed", type=int, default=0, help="scene seed (default: 0)")
    p.set_defaults(func=cmd_demo)
    return parser


def run_main(func: Callable[[argparse.Namespace], int], args: argparse.Namespace) -> int:
    """Run an entry point, turning user errors into one line on stderr and exit code 2."""
    try:
        return func(args)
    except DimslamError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logs.configure(args.verbose, args.quiet)
    return run_main(args.func, args)


if __name__ == "__main__":
    sys.exit(main())

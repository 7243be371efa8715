"""`dimslam`: the umbrella command (synth, dataset, eval, demo, run).

Each subcommand is a thin layer over a library function; errors a user can fix
(`DimslamError`) print one line and exit 2, anything else keeps its traceback.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from functools import partial
from pathlib import Path

import numpy as np
import torch

from dimslam.common import entry
from dimslam.common.config import PRESETS, device_for
from dimslam.common.errors import DimslamError
from dimslam.common.eval.evaluation import write_metrics
from dimslam.common.eval.report import RunSummary, evaluate_files, format_metrics
from dimslam.common.io.datasets import LAYOUTS, add_reader_arguments, open_from_args
from dimslam.common.io.synth import PATHS, write_sequence
from dimslam.common.io.trajectory import write_tum
from dimslam.common.net import launch
from dimslam.common.net.service import (
    add_slam_options,
    map_lag_rounds,
    positive_int,
    positive_rate,
    slam_config,
)
from dimslam.common.progress import Progress
from dimslam.common.slam import run_dataset

log = logging.getLogger("dimslam")

DEMO_OUT = Path("out/demo")
VIEW_MESH_EVERY = 5
"""A live view asks the mapper for its mesh every this many map snapshots."""


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
        path=args.path,
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

    reader = open_from_args(args, args.path)
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


def cmd_eval(args: argparse.Namespace) -> int:
    result = evaluate_files(
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
# run


def cmd_run(args: argparse.Namespace) -> int:
    cfg = slam_config(args)
    device = device_for(args.device)
    if args.realtime is not None and args.map_lag is not None:
        raise DimslamError("--realtime never holds the tracker back: it takes no --map-lag")
    viewer = viewer_args(args)
    if args.single_process:
        if args.map_lag is not None or args.realtime is not None:
            raise DimslamError(
                "--map-lag and --realtime set how the service's processes keep pace; "
                "--single-process maps every round before the next frame"
            )
        if args.threads:
            torch.set_num_threads(args.threads)
        run = run_dataset
    else:
        lag = launch.MAP_LAG if args.map_lag is None else args.map_lag
        run = partial(
            launch.run_service,
            threads=args.threads,
            map_lag=lag,
            realtime=args.realtime,
            viewer=viewer,
        )
    summary = run(
        args.dataset,
        args.out,
        cfg,
        device,
        max_frames=args.max_frames,
        layout=args.layout,
        mesh=not args.no_mesh,
        stride=args.stride,
    )
    return finish_run(summary, args.out)


def add_view_options(p: argparse.ArgumentParser) -> None:
    """`--rerun` / `--rerun-save`: a live view of the run (dimslam-viewer, the [viz] extra)."""
    g = p.add_mutually_exclusive_group()
    g.add_argument(
        "--rerun",
        action="store_true",
        help="service only: show the run live in a rerun viewer (started if none runs; needs "
        "pip install 'dimslam[viz]')",
    )
    g.add_argument(
        "--rerun-save",
        type=Path,
        metavar="FILE",
        help="service only: record the live view to FILE (.rrd) instead; open it with `rerun FILE`",
    )


def viewer_args(args: argparse.Namespace) -> list[str] | None:
    """The viewer's sink options, or None without a view; refused in one process."""
    if not (args.rerun or args.rerun_save):
        return None
    if args.single_process:
        raise DimslamError(
            "--rerun and --rerun-save watch the service's topics: drop --single-process"
        )
    if args.rerun_save is not None:
        return ["--save", str(args.rerun_save.resolve()), "--mesh-every", str(VIEW_MESH_EVERY)]
    return ["--spawn", "--mesh-every", str(VIEW_MESH_EVERY)]


def finish_run(summary: RunSummary, out: Path) -> int:
    """Say what a run did and where its outputs are."""
    print(f"{summary.frames} frames, {summary.keyframes} keyframes in {summary.seconds:.1f} s")
    if summary.frames_lost:
        print(f"{summary.frames_lost} frames lost: they have no pose in trajectory.txt")
    written = [f.name for f in sorted(out.iterdir()) if f.is_file()]
    print(f"outputs in {out}: {', '.join(written)}")
    return 0


# ---------------------------------------------------------------------------------------------
# demo


def cmd_demo(args: argparse.Namespace) -> int:
    """The main job on the built-in default: render the synthetic scene, run, evaluate."""

    out: Path = args.out
    viewer = viewer_args(args)
    scene = out / "scene"
    width, height = args.size
    print(
        f"1/2 rendering the built-in synthetic scene ({args.frames} frames {width}x{height}, "
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
    mode = "in one process" if args.single_process else "through the service"
    print(f"2/2 running SLAM {mode} ({args.preset} preset), evaluating against the ground truth")
    run = run_dataset if args.single_process else partial(launch.run_service, viewer=viewer)
    summary = run(str(scene), out, PRESETS[args.preset], torch.device("cpu"))
    return finish_run(summary, out)


# ---------------------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="dimslam",
        description="Dense RGB-only SLAM with neural implicit maps. Subcommands render the "
        "built-in synthetic scene, inspect datasets and evaluate trajectories and meshes.",
    )
    entry.add_verbosity(parser)
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
    p.add_argument(
        "--path",
        choices=PATHS,
        default="walk",
        help="camera path: 'walk' wanders through the middle of the room panning slowly; 'loop' "
        "walks once round the room looking outwards and 10 %% past its start, so that its end "
        "sees again what its start saw (a loop to close); --frames sets its speed (default: walk)",
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
    add_reader_arguments(p)
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
        description="Render the built-in synthetic scene, run SLAM on it through the service "
        "(mapper, tracker, camera and pose client as processes over zenoh on loopback) and "
        "evaluate the result against its ground truth; writes the outputs of `dimslam run` "
        "(trajectory.txt, metrics.json, trajectory.png, ...) next to the rendered scene.",
    )
    p.add_argument(
        "--out", type=Path, default=DEMO_OUT, help=f"output folder (default: {DEMO_OUT})"
    )
    p.add_argument("--frames", type=int, default=60, help="frames to render (default: 60)")
    p.add_argument("--size", type=_size, default=(160, 120), help="WIDTHxHEIGHT (default: 160x120)")
    p.add_argument("--seed", type=int, default=0, help="scene seed (default: 0)")
    p.add_argument(
        "--preset", choices=sorted(PRESETS), default="tiny", help="SLAM settings (default: tiny)"
    )
    p.add_argument(
        "--single-process",
        action="store_true",
        help="track and map in this process instead of through the service",
    )
    add_view_options(p)
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser(
        "run",
        help="run SLAM on a dataset through the service (or in one process)",
        description="Track the camera and build the map of a dataset, then write trajectory.txt, "
        "keyframes.txt, mesh.ply, config.json and, where the dataset has ground truth, "
        "metrics.json. By default the real service runs: mapper, tracker, a lockstep camera and "
        "a pose client as separate processes on loopback (their logs: <role>.log; the poses as "
        "first published: trajectory_online.txt). --single-process runs both steps in turn "
        "here (log.txt).",
    )
    p.add_argument("dataset", help="dataset folder or video (any layout `dimslam dataset` reads)")
    p.add_argument("--out", type=Path, required=True, help="output folder (created)")
    p.add_argument("--device", default="cpu", help="cpu or cuda:N (default: cpu)")
    p.add_argument("--threads", type=int, default=None, help="CPU threads (default: torch's)")
    p.add_argument("--max-frames", type=int, default=None, help="stop after this many frames")
    p.add_argument(
        "--stride",
        type=positive_int,
        default=1,
        metavar="N",
        help="use every N-th frame of the dataset: N times the motion per frame, as a faster "
        "camera (default: 1)",
    )
    p.add_argument("--layout", choices=sorted(LAYOUTS), help="dataset layout (default: detected)")
    p.add_argument("--no-mesh", action="store_true", help="skip mesh extraction")
    p.add_argument(
        "--single-process",
        action="store_true",
        help="track and map in turn in this process (the paper's one-thread variant) instead "
        "of running mapper, tracker and camera as separate processes over zenoh",
    )
    p.add_argument(
        "--map-lag",
        type=map_lag_rounds,
        metavar="ROUNDS",
        help="service only: mapping rounds the tracker may run ahead of the map (default: "
        f"{launch.MAP_LAG}: the tracker waits for every round, and the run computes what "
        "--single-process computes with the same --threads per process; 1: tracking overlaps "
        "the round in progress, a round behind the map, and less accurate; docs/results.md "
        "measures both)",
    )
    p.add_argument(
        "--realtime",
        type=positive_rate,
        metavar="FPS",
        help="service only: replay the dataset as a live camera at FPS frames per second (no "
        "lockstep; the tracker never waits for the map and keeps only the newest frame when "
        "busy) and report frames received, tracked, dropped and lost, and the latency from "
        "camera to pose",
    )
    add_view_options(p)
    add_slam_options(p)
    p.set_defaults(func=cmd_run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    return entry.main(build_parser(), lambda args: args.func(args), argv)


if __name__ == "__main__":
    sys.exit(main())

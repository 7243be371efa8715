"""Speed of the SLAM core per preset: ms per tracked frame, ms per mapping iteration, fps of
a short run, memory.

    python benchmarks/speed.py --threads 1                    # paper, cpu, tiny on the CPU
    python benchmarks/speed.py --presets cpu --dataset ../shared/data/room0 --threads 1
    python benchmarks/speed.py --presets cpu,tiny --json out/speed.json
    python benchmarks/speed.py --device cuda:0 --full-paper --full-init --max-iters 0
    python benchmarks/speed.py --presets cpu --set render.surface_samples=12 --max-iters 50

Frames are the built-in synthetic scene, rendered in memory at the preset's width (320x240
where the preset keeps the input size); the tracking timing takes `--dataset`'s instead when
given. Tracking: a map initialized on the first frames (the preset's initialization, or
`--track-init-iters`) and held fixed,
then `--track-frames` frames tracked by the preset's solver, the whole step timed per frame
(p50, p95), and the first `--adam-frames` of them also by the Adam window tracker from the same
guess (`track_ms_p50_adam`, `track_speedup` = its p50 over the solver's); `track_refined`
counts the timed frames that the window objective solved again (`tracker.window_refine_deg`,
inside the timed step). Mapping, for the
sparse map (`map_*`) and the dense one (`map_*_dense`) in turn: the system is
initialized cheaply (`--init-iters`; accuracy is not the point), its frames all become
keyframes so that keyframes join the windows, and each `Mapper.map` call (at most `--max-iters`
iterations) is timed and divided by the iterations it ran; medians over `--repeats`;
`map_samples_per_s` counts the ray samples evaluated with gradients (forward, backward and
optimizer step), `map_speedup` is the sparse map's over the dense one's, `map_mb` the stored
grid cells and decoder after those rounds; `field_ms` and `field_step_ms` (`_dense`) time
the map alone on one iteration's samples (forward + backward, then the optimizer step), so
that the rest of an iteration is the window objective's. The
preset's own initialization time is estimated from the per-iteration times. Full run:
`Slam.add` over `--frames` frames with the preset as it is except for the cheap initialization
(`--full-init` keeps the preset's: 600 iterations of the cpu preset take minutes on a CPU);
the paper preset's run is skipped on the CPU unless `--full-paper`. Tracking loss is recorded,
not raised. MB = 2**20 bytes; the peak RSS is the process's so far (presets run in turn).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import resource
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

import dimslam.common  # noqa: F401  (OMP_WAIT_POLICY must be set before torch loads OpenMP)

# isort: split
import numpy as np
import torch

from dimslam.common.config import PRESETS, SlamConfig, device_for
from dimslam.common.geometry.camera import Camera
from dimslam.common.io.datasets import ReaderOptions, open_dataset
from dimslam.common.io.datasets.base import Frame
from dimslam.common.io.synth import FPS, SynthScene, default_camera
from dimslam.common.map.field import make_field
from dimslam.common.optim.window import FrameState, TrackingLost, adam, image_tensor
from dimslam.common.options import apply_overrides, overrides_or_exit, setting
from dimslam.common.slam import Slam
from dimslam.mapper.mapper import INIT_START, MapperConfig
from dimslam.tracker.tracker import Tracker

log = logging.getLogger("speed")
MB = 2**20


def machine(device: torch.device) -> dict:
    """What the figures were measured on."""
    cpu = platform.processor() or platform.machine()
    cpuinfo = Path("/proc/cpuinfo")
    for line in cpuinfo.read_text().splitlines() if cpuinfo.is_file() else []:
        if line.startswith("model name"):
            cpu = line.split(":", 1)[1].strip()
            break
    info = {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "device": str(device),
    }
    if device.type == "cuda":
        info["gpu"] = torch.cuda.get_device_name(device)
    return info


def render(cfg: SlamConfig, count: int, seed: int) -> tuple[Camera, list[np.ndarray]]:
    """`count` frames of the synthetic path at the preset's size, `(H, W, 3)` float32 in [0, 1]."""
    width = cfg.width or 320
    camera = default_camera(width, round(width * 3 / 4))
    scene = SynthScene(seed)
    return camera, [scene.render(T, camera)[0] for T in scene.path(count)]


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _state(slam: Slam, rgb: np.ndarray, guess: torch.Tensor) -> FrameState:
    n = len(slam.frames)
    return FrameState(n, n / FPS, torch.from_numpy(rgb).to(slam.device), guess)


def _median_ms(samples: list[float]) -> float | None:
    return 1e3 * statistics.median(samples) if samples else None


def time_steps(
    cfg: SlamConfig, camera: Camera, images: list[np.ndarray], device: torch.device, repeats: int
) -> dict:
    """Per-iteration times of initialization and mapping (medians, milliseconds).

    The initialization frames all become keyframes, so that keyframes can join the windows.
    """
    slam = Slam(cfg, camera, device)
    for rgb in images[: cfg.mapper.init_frames]:
        slam.frames.append(_state(slam, rgb, torch.eye(4, device=device)))
    prior_iters = max(1, cfg.mapper.prior_iters)
    slam.back.mapper.fit_prior(slam.frames[0])  # warm-up: first calls pay one-off costs
    _sync(device)
    start = time.perf_counter()
    slam.back.mapper.fit_prior(slam.frames[0])
    _sync(device)
    prior_s = time.perf_counter() - start
    start = time.perf_counter()
    slam.back.mapper.initialize(slam.frames)  # fits the prior again, then the joint optimization
    _sync(device)
    init_s = (time.perf_counter() - start - prior_s) / max(1, cfg.mapper.init_iters)
    for f in slam.frames:
        f.keyframe = True
    lost: list[str] = []
    mapping, map_window = [], 0
    for _ in range(repeats):
        _sync(device)
        start = time.perf_counter()
        try:
            done = slam.back.mapper.map(slam.frames[-cfg.mapper.every :], slam.keyframes)
        except TrackingLost as e:
            lost.append(f"mapping: {e}")
            continue
        _sync(device)
        mapping.append((time.perf_counter() - start) / max(1, done.stats.iterations))
        map_window = len(done.window)
    return {
        "prior_ms_per_iter": 1e3 * prior_s / prior_iters,
        "init_ms_per_iter": 1e3 * init_s,
        "map_ms_per_iter": _median_ms(mapping),
        "map_iters": cfg.mapper.iters,
        "map_window": map_window,
        "map_mb": slam.back.mapper.field.memory_bytes() / MB,
        "lost": lost,
    }


def time_tracking(
    cfg: SlamConfig, camera: Camera, frames: list[Frame], device: torch.device, adam_frames: int
) -> dict:
    """Milliseconds per tracked frame, the whole step (`FrontEnd.track`: references or window
    chosen, solve, keyframe decision), for the preset's solver and, on the same frames from
    the same guesses, the Adam window tracker as a shadow whose poses are thrown away.

    The map is initialized on the first `init_frames` frames, then held fixed: the mapper's
    rounds are not part of a tracking step (the service runs them in another process).
    Medians and 95th percentiles over the frames tracked after initialization.
    """
    slam = Slam(cfg, camera, device)
    frames = iter(frames)
    for frame in frames:
        slam.add(frame)
        if slam.initialized:
            break
    else:
        raise SystemExit("too few frames to initialize the map")
    front, field = slam.front, slam.back.field
    shadow = Tracker(
        replace(cfg.tracker, solver="adam"), cfg.loss, cfg.render, camera, slam.generator
    )
    ms, ms_adam, lost = [], [], 0
    for frame in frames:
        index = slam.fed
        slam.fed += 1
        rgb = image_tensor(frame.rgb, device)
        guess = front.guess(index)  # what `track` starts from too (no continued map here)
        window = [
            replace(f, T_wc=f.T_wc.clone()) for f in front.frames[1 - cfg.tracker.local_frames :]
        ]
        keyframes = front.keyframes
        _sync(device)
        start = time.perf_counter()
        state = front.track(field, index, frame.timestamp, rgb)
        _sync(device)
        ms.append(1e3 * (time.perf_counter() - start))
        lost += state is None
        if len(ms_adam) < adam_frames:
            window.append(FrameState(index, frame.timestamp, rgb, guess))
            _sync(device)
            start = time.perf_counter()
            try:
                shadow.track(field, window, keyframes)
                shadow.is_keyframe(field, window[-1], keyframes[-1])
            except TrackingLost:
                pass  # timed all the same: it ran its iterations
            _sync(device)
            ms_adam.append(1e3 * (time.perf_counter() - start))
    if not ms:
        raise SystemExit("no frame left to track after initialization: raise --track-frames")
    p50, p50_adam = statistics.median(ms), statistics.median(ms_adam) if ms_adam else None
    return {
        "solver": cfg.tracker.solver,
        "track_frames": len(ms),
        "track_lost": lost,
        "track_refined": len(front.refined),
        "track_ms_p50": p50,
        "track_ms_p95": float(np.percentile(ms, 95)),
        "track_frames_adam": len(ms_adam),
        "track_ms_p50_adam": p50_adam,
        "track_ms_p95_adam": float(np.percentile(ms_adam, 95)) if ms_adam else None,
        "track_speedup": p50_adam / p50 if p50_adam else None,
    }


def load_frames(
    cfg: SlamConfig, args: argparse.Namespace, count: int
) -> tuple[Camera, list[Frame]]:
    """The first `count` frames of `--dataset` at the preset's width, else of the synthetic
    scene."""
    if args.dataset is None:
        camera, images = render(cfg, count, args.seed)
        return camera, [to_frame(i, rgb) for i, rgb in enumerate(images)]
    reader = open_dataset(args.dataset, options=ReaderOptions(end=count, width=cfg.width or None))
    return reader.camera, list(reader)


def to_frame(index: int, rgb: np.ndarray) -> Frame:
    return Frame(index, index / FPS, (rgb * 255 + 0.5).astype(np.uint8))


def full_run(
    cfg: SlamConfig, camera: Camera, images: list[np.ndarray], device: torch.device
) -> dict:
    """`Slam.add` over the frames with the preset as it is.

    Returns:
        `fps` over every frame fed (initialization included) and `tracked_fps` over the frames
        after initialization (lost ones included).
    """
    frames = [to_frame(i, rgb) for i, rgb in enumerate(images)]
    slam = Slam(cfg, camera, device)
    fed, init_s, init_n = 0, None, 0
    start = time.perf_counter()
    for frame in frames:
        fed += 1
        slam.add(frame)
        if init_s is None and slam.initialized:
            init_s = time.perf_counter() - start
            init_n = fed
    slam.finish()
    lost = f"{len(slam.lost_frames)} frames lost in the full run" if slam.lost_frames else None
    _sync(device)
    seconds = time.perf_counter() - start
    tracked = None
    if init_s is not None and fed > init_n:
        tracked = (fed - init_n) / (seconds - init_s)
    return {
        "frames": fed,
        "seconds": seconds,
        "fps": fed / seconds,
        "init_seconds": init_s,
        "tracked_fps": tracked,
        "keyframes": len(slam.keyframes),
        "lost": lost,
    }


def samples_per_iteration(cfg: SlamConfig) -> int:
    """Ray samples a mapping iteration evaluates with gradients: the pixels' and the
    smoothness blocks' rays, each with its stratified and importance samples (or its coarse
    and surface samples)."""
    rays = cfg.mapper.pixels + 4 * (cfg.loss.smooth_blocks if cfg.loss.smooth_weight > 0 else 0)
    r = cfg.render
    if r.surface_samples > 0:
        return rays * (r.coarse_samples + r.surface_samples)
    return rays * (r.n_stratified + r.n_importance * r.importance_rounds)


FIELD_CUBE = 4.0
"""Edge of the cube (map units, about the first camera) the field timing's points fill."""


def time_field(cfg: SlamConfig, grids: str, device: torch.device, repeats: int) -> dict:
    """The map alone, outside any window: forward and backward of one mapping iteration's
    samples (uniform in a cube, every cell of which a sparse map stores), then the optimizer
    step (medians, milliseconds). What a mapping iteration costs beyond these two is the
    window objective's: ray sampling, patch warps into the window's frames, losses."""
    field = make_field(replace(cfg.map, grids=grids), device)
    generator = torch.Generator(device).manual_seed(0)

    def cube(count: int) -> torch.Tensor:
        u = torch.rand(count, 3, generator=generator, device=device)
        return (u - 0.5) * FIELD_CUBE

    # Every cell of the cube: a lattice at half the finest voxel size, a slab at a time.
    axis = torch.arange(-FIELD_CUBE / 2, FIELD_CUBE / 2, min(cfg.map.voxel_sizes) / 2)
    yz = torch.cartesian_prod(axis, axis).to(device)
    for x in axis.tolist():
        field.allocate(torch.cat([torch.full_like(yz[:, :1], x), yz], dim=-1))
    groups = [{"params": field.grid_parameters()}, {"params": field.decoder_parameters()}]
    optimizer = field.follow(adam(groups))
    forward, step = [], []
    for i in range(repeats + 2):  # the first two pay one-off costs
        points = cube(samples_per_iteration(cfg))
        _sync(device)
        start = time.perf_counter()
        out = field(points)
        (out.occupancy.sum() + out.rgb.sum()).backward()
        _sync(device)
        middle = time.perf_counter()
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)
        _sync(device)
        if i >= 2:
            forward.append(middle - start)
            step.append(time.perf_counter() - middle)
    return {"field_ms": _median_ms(forward), "field_step_ms": _median_ms(step)}


def _ratio(a: float | None, b: float | None) -> float | None:
    return a / b if a and b else None


def init_iterations(cfg: MapperConfig) -> int:
    """Iterations of a whole initialization: each frame joining, then all together."""
    return cfg.init_grow_iters * (cfg.init_frames - INIT_START + 1) + cfg.init_iters


def bench(name: str, args: argparse.Namespace, device: torch.device) -> dict:
    """Every figure of one preset."""
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    cfg = apply_overrides(PRESETS[name], dict(args.set))
    # The cheap initialization times only its final phase, every init frame in the window: the
    # estimate below prices the growing phase (fewer frames) at that rate too, an upper bound.
    init = {
        "mapper.init_iters": str(args.init_iters),
        "mapper.prior_iters": str(args.init_iters),
        "mapper.init_grow_iters": "0",
    }
    cheap = apply_overrides(cfg, init)
    capped = {}
    if args.max_iters > 0:
        capped = {
            "tracker.iters": str(min(cfg.tracker.iters, args.max_iters)),
            "mapper.iters": str(min(cfg.mapper.iters, args.max_iters)),
        }
    full = not (name == "paper" and device.type == "cpu" and not args.full_paper)
    count = max(cfg.mapper.init_frames + args.repeats, args.frames if full else 0)
    camera, images = render(cfg, count, args.seed)
    log.info("%s: %dx%d, timing steps", name, camera.width, camera.height)
    steps = {}
    for grids in ("dense", "sparse"):  # the sparse map's figures keep the plain names
        timed = apply_overrides(cheap, {**capped, "map.grids": grids})
        figures = time_steps(timed, camera, images, device, args.repeats)
        suffix = "_dense" if grids == "dense" else ""
        steps.update({k + suffix: v for k, v in figures.items() if k.startswith("map_")})
        if grids == cfg.map.grids:
            steps.update({k: v for k, v in figures.items() if not k.startswith("map_")})
        for key, value in time_field(cfg, grids, device, args.repeats).items():
            steps[key + suffix] = value
        samples = samples_per_iteration(cfg)
        if figures["map_ms_per_iter"]:
            steps["map_samples_per_s" + suffix] = samples / figures["map_ms_per_iter"] * 1e3
    steps["map_speedup"] = _ratio(
        steps.get("map_samples_per_s"), steps.get("map_samples_per_s_dense")
    )
    estimate = (
        steps["prior_ms_per_iter"] * cfg.mapper.prior_iters
        + steps["init_ms_per_iter"] * init_iterations(cfg.mapper)
    ) / 1e3
    result = {"preset": name, "set": dict(args.set), "size": [camera.width, camera.height], **steps}
    log.info("%s: timing the tracking step per frame", name)
    track_cfg = cfg
    if args.track_init_iters is not None:
        track_cfg = apply_overrides(
            cfg,
            {
                "mapper.init_iters": str(args.track_init_iters),
                "mapper.init_grow_iters": str(
                    min(cfg.mapper.init_grow_iters, args.track_init_iters)
                ),
                "mapper.prior_iters": str(min(cfg.mapper.prior_iters, args.track_init_iters)),
            },
        )
    t_camera, t_frames = load_frames(cfg, args, cfg.mapper.init_frames + args.track_frames)
    result["tracking"] = time_tracking(track_cfg, t_camera, t_frames, device, args.adam_frames)
    result["tracking"]["source"] = args.dataset or "synthetic"
    result.update(
        {
            k: v
            for k, v in result["tracking"].items()
            if k.startswith("track_ms") or k == "track_speedup"
        }
    )
    result["init_seconds_estimate"] = estimate
    result["full_run"] = None
    if full:
        log.info("%s: full run on %d frames", name, args.frames)
        run_cfg = cfg if args.full_init else cheap
        result["full_run"] = full_run(run_cfg, camera, images[: args.frames], device)
        result["full_run"]["init_iters"] = run_cfg.mapper.init_iters
        result["full_run"]["prior_iters"] = run_cfg.mapper.prior_iters
    result["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    if device.type == "cuda":
        result["peak_cuda_mb"] = torch.cuda.max_memory_allocated(device) / MB
    return result


def _rounded(value: object) -> object:
    if isinstance(value, float):
        return round(value, 3)
    if isinstance(value, dict):
        return {k: _rounded(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_rounded(v) for v in value]
    return value


def table(results: list[dict]) -> str:
    """The figures as a Markdown table (windows in frames, in brackets)."""

    def num(value: float | None, fmt: str = ".1f") -> str:
        return "-" if value is None else format(value, fmt)

    rows = [
        "| preset | size | track ms/frame p50 / p95 | Adam p50 | speedup | init ms/it "
        "| map ms/it sparse / dense | map alone: ms fwd+bwd + step, sparse / dense "
        "| init s (est.) | run fps | fps after init "
        "| map MB sparse / dense | peak RSS MB | lost |",
        "|" + "---|" * 14,
    ]
    for r in results:
        run = r["full_run"] or {}
        lost = r["lost"] + ([run["lost"]] if run.get("lost") else [])
        if r["tracking"]["track_lost"]:
            lost.append(f"{r['tracking']['track_lost']} frames lost in the tracking timing")
        rows.append(
            f"| {r['preset']} | {r['size'][0]}x{r['size'][1]} "
            f"| {num(r['track_ms_p50'])} / {num(r['track_ms_p95'])} "
            f"| {num(r['track_ms_p50_adam'])} | {num(r['track_speedup'], '.0f')}x "
            f"| {num(r['init_ms_per_iter'])} "
            f"| {num(r['map_ms_per_iter'])} / {num(r['map_ms_per_iter_dense'])} "
            f"({r['map_window']}) "
            f"| {num(r['field_ms'])} + {num(r['field_step_ms'])} / "
            f"{num(r['field_ms_dense'])} + {num(r['field_step_ms_dense'])} "
            f"| {num(r['init_seconds_estimate'])} | {num(run.get('fps'), '.2f')} "
            f"| {num(run.get('tracked_fps'), '.2f')} "
            f"| {r['map_mb']:.1f} / {r['map_mb_dense']:.1f} "
            f"| {r['peak_rss_mb']:.0f} | {'; '.join(lost) or 'no'} |"
        )
    return "\n".join(rows)


class _Help(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """The module docstring as it is, and every option's default."""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=_Help)
    parser.add_argument("--presets", default="paper,cpu,tiny", help="comma-separated presets")
    parser.add_argument("--device", default="cpu", help="cpu or cuda:N")
    parser.add_argument("--threads", type=int, help="torch.set_num_threads (None: torch's choice)")
    parser.add_argument("--repeats", type=int, default=3, help="timed calls per step (median)")
    parser.add_argument("--frames", type=int, default=30, help="frames of the full run")
    parser.add_argument(
        "--init-iters",
        type=int,
        default=5,
        help="init and prior iterations (step timings; full run unless --full-init)",
    )
    parser.add_argument(
        "--max-iters",
        type=int,
        default=10,
        help="cap on the iterations of each timed tracking or mapping call (0: the preset's)",
    )
    parser.add_argument(
        "--full-init",
        action="store_true",
        help="initialize the full run with the preset's own iterations, not --init-iters (slow)",
    )
    parser.add_argument(
        "--full-paper",
        action="store_true",
        help="also do the paper preset's full run on the CPU (slow)",
    )
    parser.add_argument("--seed", type=int, default=0, help="synthetic scene seed")
    parser.add_argument(
        "--dataset", help="time the tracking step on this dataset's frames (default: synthetic)"
    )
    parser.add_argument(
        "--track-frames", type=int, default=40, help="frames tracked after initialization"
    )
    parser.add_argument(
        "--adam-frames", type=int, default=10, help="of those, how many the Adam shadow tracks"
    )
    parser.add_argument(
        "--track-init-iters",
        type=int,
        help="initialization iterations (and at most as many per joining frame and for the "
        "prior) of the map the tracking timing tracks against (default: the preset's)",
    )
    parser.add_argument(
        "--set",
        action="append",
        type=setting,
        default=[],
        metavar="KEY=VALUE",
        help="override a setting of every preset, e.g. render.surface_samples=12 (repeatable)",
    )
    parser.add_argument("--json", type=Path, help="write the JSON here instead of stdout")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname).1s %(name)s: %(message)s")
    names = [p.strip() for p in args.presets.split(",") if p.strip()]
    unknown = [p for p in names if p not in PRESETS]
    if unknown:
        parser.error(f"unknown presets {unknown}; known: {', '.join(PRESETS)}")
    if min(args.repeats, args.init_iters, args.track_frames, args.track_init_iters or 1) < 1:
        parser.error("need --repeats, --init-iters, --track-frames, --track-init-iters >= 1")
    if args.frames < 3 or args.adam_frames < 0:
        parser.error("need --frames >= 3 and --adam-frames >= 0")
    for name in names:  # an unknown key or a wrong type: refused before anything runs
        overrides_or_exit(parser, PRESETS[name], dict(args.set), "--set: ")
    if args.threads:
        torch.set_num_threads(args.threads)
    device = device_for(args.device)
    report = {"machine": machine(device), "presets": [bench(n, args, device) for n in names]}
    text = json.dumps(_rounded(report), indent=2)
    if args.json:
        args.json.write_text(text + "\n")
    else:
        print(text)
    print(table(report["presets"]), file=sys.stderr if args.json is None else sys.stdout)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Oracle diagnostics for the SLAM core (design.md section 5c), on sequences with ground truth.

Each half is checked against ground truth before blaming the whole:

    python benchmarks/diagnose.py map-oracle SEQ   # map fitted to GT depth and poses; track on it
    python benchmarks/diagnose.py single SEQ       # one frame off its pose, neighbours at GT
    python benchmarks/diagnose.py landscape SEQ    # objective along the optical axis
    python benchmarks/diagnose.py mapper SEQ       # map learned by the warping loss from GT poses
    python benchmarks/diagnose.py init SEQ         # initialization: poses and depth vs GT
    python benchmarks/diagnose.py run SEQ          # the whole system, error of every new frame
                                                   # (--depth-every N: and the map's scale;
                                                   # --gt-poses: frames at their true poses)
    python benchmarks/diagnose.py keyframes SEQ    # after the run, each keyframe's depth scale:
                                                   # the map's and its plane sweep's
    python benchmarks/diagnose.py mesh SEQ --out D # after the run, each mesh view's depth scale,
                                                   # the mesh as the mapper makes it, with each
                                                   # view's depth at the truth's scale, and from
                                                   # the true depth at the estimated keyframe
                                                   # poses: what the poses allow (--refit N: the
                                                   # map fitted N more iterations, poses held)
    python benchmarks/diagnose.py mesh-truth SEQ --out D  # the true depth fused at the true
                                                   # poses: what fusion and protocol allow;
                                                   # the share of the culled ground truth that
                                                   # no frame sees (occluded), and the fused
                                                   # mesh's completion of it
    python benchmarks/diagnose.py mesh-seen SEQ --out RUN  # a run's mesh: its completion
                                                   # of what some frame sees unoccluded and
                                                   # of what none does
    python benchmarks/diagnose.py basin SEQ        # run at true poses; the warping cost of the
                                                   # pixels mapped too near, at their true depth
                                                   # times 0.4-1.5; then --rounds more mapping
                                                   # rounds (--then: their settings)

SEQ is a TUM-layout sequence with `depth.txt` (exact depth: `dimslam synth` output or
../shared/data/room0). Settings: `--preset` plus `section.field=value` overrides. Ground truth
is used here only to measure; nothing of it reaches the system under test except where a
command says so (the GT poses of `map-oracle` and `mapper`). Runs use `--threads` (default 1,
as `benchmarks/table.py` runs `dimslam run`), so a whole run here is the table's run.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import math
import time
from pathlib import Path

import dimslam.common  # noqa: F401, I001  (its OpenMP setting must precede torch's import)

# isort: split
import cv2
import numpy as np
import torch

from dimslam.common.config import PRESETS
from dimslam.common.eval.evaluation import Sim3, evaluate_trajectory
from dimslam.common.geometry import pose
from dimslam.common.io.datasets import ReaderOptions, open_dataset
from dimslam.common.io.trajectory import Trajectory
from dimslam.common.map.render import render_image, render_pixels
from dimslam.common.optim import losses
from dimslam.common.optim.objective import patch_colors, window_objective
from dimslam.common.optim.window import (
    FrameState,
    TrackingLost,
    adam,
    image_tensor,
    optimize_window,
    random_pixels,
)
from dimslam.common.options import apply_overrides, overrides_or_exit, setting
from dimslam.common.slam import Slam
from dimslam.mapper.mapper import MeshDepths


def load(args):
    cfg = apply_overrides(PRESETS[args.preset], dict(args.set))
    end = args.frames * args.stride
    options = ReaderOptions(width=cfg.width or None, end=end, stride=args.stride)
    reader = open_dataset(args.seq, options=options)
    frames = list(reader)
    return cfg, reader.camera, frames


def gt_depths(seq: Path, frames, camera) -> list[np.ndarray]:
    """Exact depth of each frame (TUM depth.txt, 5000 per unit), resized to the camera."""
    lines = (seq / "depth.txt").read_text().splitlines()
    rows = [ln.split() for ln in lines if ln and ln[0] != "#"]
    stamps = np.array([float(r[0]) for r in rows])
    out = []
    for f in frames:
        name = rows[int(np.abs(stamps - f.timestamp).argmin())][1]
        d = cv2.imread(str(seq / name), cv2.IMREAD_UNCHANGED).astype(np.float32) / 5000.0
        out.append(cv2.resize(d, camera.size, interpolation=cv2.INTER_NEAREST))
    return out


def relative_gt(frames, scale: float = 1.0) -> list[torch.Tensor]:
    """GT poses relative to the first frame (identity), translations times `scale`."""
    T0 = np.linalg.inv(frames[0].T_wc)
    out = []
    for f in frames:
        T = T0 @ f.T_wc
        T[:3, 3] *= scale
        out.append(torch.from_numpy(T).float())
    return out


def states_at(frames, poses) -> list[FrameState]:
    return [
        FrameState(i, f.timestamp, _image(f), T.clone())
        for i, (f, T) in enumerate(zip(frames, poses, strict=True))
    ]


def depth_error(slam: Slam, camera, T, gt: np.ndarray, scale: float = 1.0) -> str:
    d, _ = render_image(slam.back.mapper.field, camera, T, slam.cfg.render)
    e = np.abs(d.numpy() * scale - gt)
    return f"depth error median {100 * np.median(e):.1f} cm, mean {100 * e.mean():.1f} cm"


def pose_error(T_est: torch.Tensor, T_gt: torch.Tensor) -> str:
    d = pose.log_se3(pose.compose(pose.invert(T_gt.double()), T_est.double()))
    return f"{100 * d[:3].norm():.2f} cm {57.2958 * d[3:].norm():.2f} deg"


def fit_supervised(args):
    """A map fitted to GT depth and colour at GT poses (the oracle map)."""
    cfg, camera, frames = load(args)
    depths = gt_depths(Path(args.seq), frames, camera)
    poses = relative_gt(frames)
    slam = Slam(cfg, camera, torch.device("cpu"))
    field, g = slam.back.mapper.field, slam.generator
    cache = None
    if args.map_cache is not None:
        name = f"{Path(args.seq).name}-{len(frames)}f-{args.fit_iters}it-{camera.width}px.pt"
        cache = args.map_cache / name
        if cache.is_file():
            field.load_state_dict(torch.load(cache))
            print(f"fitted map from {cache}: {depth_error(slam, camera, poses[-1], depths[-1])}")
            return cfg, camera, frames, poses, slam
    opt = torch.optim.Adam([{"params": list(field.parameters()), "lr": 1e-2}])
    rgb = torch.stack([_image(f) for f in frames])
    depth = torch.from_numpy(np.stack(depths))
    P = torch.stack(poses)
    for _ in range(args.fit_iters):
        fr, uv = random_pixels(len(frames), 2048, camera, 0, g, "cpu")
        out = render_pixels(field, camera, uv, P[fr], cfg.render, g)
        u, v = uv[:, 0].long(), uv[:, 1].long()
        loss = (out.depth - depth[fr, v, u]).abs().mean() + (out.rgb - rgb[fr, v, u]).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    print(f"fitted map: {depth_error(slam, camera, poses[-1], depths[-1])} (last frame)")
    if cache is not None:
        cache.parent.mkdir(parents=True, exist_ok=True)
        torch.save(field.state_dict(), cache)
    return cfg, camera, frames, poses, slam


def cmd_map_oracle(args) -> None:
    """Fit the map by supervision, then track every frame on it as the system would (the
    tracking half of the pipeline with the preset's solver; no mapping)."""
    cfg, camera, frames, poses, slam = fit_supervised(args)
    field, front = slam.back.field, slam.front
    start = states_at(frames[:2], poses[:2])
    start[0].keyframe = True
    front.frames = start
    front.map_changed(field, 1)
    seconds = []
    for i, f in enumerate(frames[2 : args.until], 2):
        rgb = _image(f)
        began = time.perf_counter()
        s = front.track(field, i, f.timestamp, rgb)
        seconds.append(time.perf_counter() - began)
        front.take_batch()  # nothing maps them
        if s is None:
            print(f"frame {i:3d} lost", flush=True)
            continue
        res = front.last_result
        print(
            f"frame {i:3d} kf={int(s.keyframe)} {pose_error(s.T_wc, poses[i])} "
            f"loss {res.stats.history[0]:.4f} -> {res.stats.loss:.4f} its {res.stats.iterations} "
            f"window {res.window} {1000 * seconds[-1]:.0f} ms",
            flush=True,
        )
    tracked = {s.index: s for s in front.frames}
    frames = frames[: args.until]
    stamps = np.array([frames[i].timestamp for i in sorted(tracked)])
    gt = Trajectory(stamps, torch.stack([poses[i] for i in sorted(tracked)]).double().numpy())
    est_poses = torch.stack([tracked[i].T_wc for i in sorted(tracked)])
    est = Trajectory(stamps, est_poses.double().numpy())
    print(
        f"{len(tracked)} frames tracked, {len(front.lost)} lost, {len(front.keyframes)} "
        f"keyframes; tracking step p50 {1000 * np.median(seconds):.0f} ms, "
        f"p95 {1000 * np.percentile(seconds, 95):.0f} ms"
    )
    for align in ("sim3", "se3"):
        m = evaluate_trajectory(est, gt, align=align)
        print(f"tracked on the oracle map: ATE {100 * m.ate_rmse_m:.2f} cm ({align} alignment)")


def cmd_single(args) -> None:
    """One frame pushed off its GT pose, the 8 before it fixed at GT: does tracking return?"""
    cfg, camera, frames, poses, slam = fit_supervised(args)
    k = args.frame
    states = states_at(frames, poses)[k - 8 : k + 1]
    twist = torch.tensor([0.02, -0.01, 0.015, 0.01, -0.015, 0.005])  # ~2.7 cm, ~1.1 deg
    states[-1].T_wc = pose.retract(poses[k], twist)
    print(f"frame {k} start: {pose_error(states[-1].T_wc, poses[k])}")
    uv = losses.high_gradient_pixels(states[-1].rgb, cfg.tracker.pixels, slam.generator, 5).float()
    frame = torch.full((uv.shape[0],), len(states) - 1)
    stats = optimize_window(
        slam.back.mapper.field,
        states,
        [False] * (len(states) - 1) + [True],
        camera,
        lambda it: (frame, uv),
        args.iters,
        cfg.tracker.pose_lr,
        cfg.loss,
        cfg.render,
    )
    print(f"after {stats.iterations} iterations: {pose_error(states[-1].T_wc, poses[k])}")


def cmd_landscape(args) -> None:
    """The objective of frame K along its optical axis, anchors at GT and all shifted."""
    cfg, camera, frames, poses, slam = fit_supervised(args)
    k = args.frame
    ids = [k - 3, k - 2, k - 1]
    images = torch.stack([_image(frames[i]) for i in [*ids, k]])
    uv = losses.high_gradient_pixels(images[-1], cfg.tracker.pixels, slam.generator, 5).float()
    frame = torch.full((uv.shape[0],), len(ids))
    for shift in (0.0, args.shift):
        anchors = [pose.retract(poses[i], torch.tensor([0, 0, shift, 0, 0, 0.0])) for i in ids]
        costs = []
        for dz in np.arange(-0.04, 0.041, 0.005):
            T_k = pose.retract(poses[k], torch.tensor([0, 0, float(dz), 0, 0, 0]))
            with torch.no_grad():
                r = window_objective(
                    slam.back.mapper.field,
                    images,
                    torch.stack([*anchors, T_k]),
                    camera,
                    frame,
                    uv,
                    cfg.loss,
                    cfg.render,
                )
            costs.append((float(dz), r.total.item()))
        best = min(costs, key=lambda c: c[1])[0]
        row = " ".join(f"{100 * dz:+.1f}:{c:.4f}" for dz, c in costs)
        print(f"anchors shifted {100 * shift:+.1f} cm along z: minimum at {100 * best:+.1f} cm")
        print(f"  {row}")


def cmd_mapper(args) -> None:
    """Learn the map with the window objective from GT poses (scaled to the gauge)."""
    cfg, camera, frames = load(args)
    depths = gt_depths(Path(args.seq), frames, camera)
    scale = cfg.mapper.gauge_depth / float(np.median(depths[0]))
    states = states_at(frames, relative_gt(frames, scale))
    slam = Slam(cfg, camera, torch.device("cpu"))
    slam.back.mapper.fit_prior(states[0])
    gt0 = depths[0] * scale
    print(f"after the plane prior: {depth_error(slam, camera, states[0].T_wc, gt0)} (map units)")
    n = len(states)
    for done in range(0, args.fit_iters, 50):
        stats = optimize_window(
            slam.back.mapper.field,
            states,
            [False] * n,
            camera,
            slam.back.mapper._sampler(n),
            50,
            0.0,
            cfg.loss,
            cfg.render,
            map_optimizer=adam(slam.back.mapper._init_groups(cfg.mapper.init_lr_scale)),
            generator=slam.generator,
            smooth=True,
            max_loss=float("inf"),
        )
        err = depth_error(slam, camera, states[0].T_wc, gt0)
        print(f"{done + 50:4d} iterations: loss {stats.loss:.4f} (warp {stats.warp:.4f}), {err}")


def cmd_init(args) -> None:
    """Initialize as the system does; compare poses and frame-0 depth with GT."""
    cfg, camera, frames = load(args)
    depths = gt_depths(Path(args.seq), frames, camera)
    slam = Slam(cfg, camera, torch.device("cpu"))
    started = time.perf_counter()
    used = []
    for f in frames:
        used.append(f)
        if slam.add(f):
            break
    gt = Trajectory(np.array([f.timestamp for f in used]), np.stack([f.T_wc for f in used]))
    m = evaluate_trajectory(slam.trajectory(), gt)
    path = np.linalg.norm(np.diff(gt.positions, axis=0), axis=1).sum()
    print(f"initialized on {len(used)} frames in {time.perf_counter() - started:.1f} s")
    scale = m.alignment.s
    print(f"ATE {100 * m.ate_rmse_m:.2f} cm over a {100 * path:.1f} cm path, scale {scale:.3f}")
    print(f"frame 0 (scaled): {depth_error(slam, camera, slam.frames[0].T_wc, depths[0], scale)}")
    # Where no frame has looked: frame 0 turned about its vertical axis.
    for turn in (90, 180):
        T = slam.frames[0].T_wc @ pose.make_pose(
            pose.exp_so3(torch.tensor([0.0, math.radians(turn), 0.0])), torch.zeros(3)
        )
        _, uv = random_pixels(1, 2000, camera, 0, torch.Generator().manual_seed(0), "cpu")
        with torch.no_grad():
            out = render_pixels(slam.back.mapper.field, camera, uv, T, cfg.render)
        p10, p50, p90 = np.percentile(out.depth.numpy(), [10, 50, 90])
        print(
            f"frame 0 turned {turn} degrees (unseen): depth median {p50:.2f} (10th-90th "
            f"percentile {p10:.2f}-{p90:.2f}) map units, opacity median {out.opacity.median():.2f}"
        )


def depth_scale(slam: Slam, camera, frame: FrameState, gt: np.ndarray, scale: float) -> str:
    """The map's scale at a frame: rendered over true depth (times the initialization's scale,
    so 1 means the scale the system started with), median and spread over the pixels, and
    the median over the textured pixels (the strongest tenth of the image gradient, where the
    tracker draws its points: a textureless far wall mapped too near does not move it), also
    per third of the image's width with the median opacity there (a turn brings new surfaces
    in from one side: where they start and whether the map stops their rays yet)."""
    known = gt > 0
    rows, cols = np.nonzero(known)
    uv = torch.from_numpy(np.stack([cols, rows], 1)).float()
    with torch.no_grad():  # depth and opacity in one pass, only where the truth is known
        outs = [
            render_pixels(
                slam.back.mapper.field, camera, c, frame.T_wc, slam.cfg.render, with_color=False
            )
            for c in uv.split(4096)
        ]
    rendered = torch.cat([o.depth for o in outs]).numpy()
    opacity = torch.cat([o.opacity for o in outs]).numpy()
    true = gt[known]
    ratio = scale * rendered / true
    med = float(np.median(ratio))
    within = float(np.mean(np.abs(ratio / med - 1) < 0.05))
    p10, p90 = np.percentile(ratio, [10, 90])
    # The part of the view the map puts much nearer than the rest (a newly seen far wall):
    # its depth as rendered, and where it would be at the view's median scale.
    low = ratio < 0.8 * med
    nearer = ""
    if low.any():
        expected = true[low] * med / scale
        nearer = (
            f"; {100 * low.mean():.0f}% below 0.8 of it, rendered at "
            f"{np.median(rendered[low]):.2f} map units where {np.median(expected):.2f} "
            "at that scale"
        )
    strong = _textured(frame.rgb, known)[known]
    thirds = []
    for k in range(3):
        part = strong & (cols * 3 // known.shape[1] == k)
        enough = part.sum() > 20
        thirds.append(
            f"{np.median(ratio[part]):.3f}@{np.median(opacity[part]):.2f}" if enough else "-"
        )
    return (
        f"map scale {med:.3f} ({100 * within:.0f}% of pixels within 5%; "
        f"10th-90th percentile {p10:.2f}-{p90:.2f}{nearer}); "
        f"thirds left/middle/right {' '.join(thirds)} (scale@opacity); "
        f"textured pixels {np.median(ratio[strong]):.3f}"
    )


def _feed(slam: Slam, frames):
    """Feed `frames` to `slam` one by one; after each, once it is initialized, yield how many
    were fed. Stops at a lost frame (printed)."""
    for n, f in enumerate(frames, 1):
        try:
            slam.add(f)
        except TrackingLost as e:
            print(f"frame {n - 1}: lost ({e})")
            return
        if slam.initialized:
            yield n


def _ground_truth(frames) -> Trajectory:
    return Trajectory(np.array([f.timestamp for f in frames]), np.stack([f.T_wc for f in frames]))


def cmd_run(args) -> None:
    """The whole system; the error of each new frame after aligning on the initialization."""
    cfg, camera, frames = load(args)
    depths = gt_depths(Path(args.seq), frames, camera) if args.depth_every else None
    slam = Slam(cfg, camera, torch.device("cpu"))
    alignment = None
    for n in _feed(slam, frames):
        gt = _ground_truth(frames[:n])
        est = slam.trajectory()
        m = evaluate_trajectory(est, gt)
        if alignment is None:
            alignment = m.alignment
            print(f"initialized on {n} frames: ATE {100 * m.ate_rmse_m:.2f} cm")
            if args.gt_poses:
                _track_at_ground_truth(slam, frames, alignment.inverse())
            continue
        # The newest frame as tracked: the trajectory holds only the frames mapped so far.
        newest = slam.frames[-1].T_wc.detach().cpu().double().numpy()
        T = alignment.apply_poses(newest[None])[0]
        drift = np.linalg.norm(T[:3, 3] - gt.poses[-1][:3, 3])
        scale = ""
        if depths is not None and (n - 1) % args.depth_every == 0:
            if len(slam.frames) > 10:  # the last 10 frames' path over the true one
                before = slam.frames[-11].T_wc.detach().double().numpy()
                step = np.linalg.norm(T[:3, 3] - alignment.apply_poses(before[None])[0][:3, 3])
                true_step = np.linalg.norm(gt.poses[-1][:3, 3] - gt.poses[-11][:3, 3])
                scale = f"step {step / max(true_step, 1e-9):.3f}, "
            scale += depth_scale(slam, camera, slam.frames[-1], depths[n - 1], alignment.s)
        print(
            f"frame {n - 1:3d} kf={int(slam.frames[-1].keyframe)} keyframes {len(slam.keyframes)} "
            f"drift {100 * drift:6.2f} cm  ATE so far {100 * m.ate_rmse_m:6.2f} cm  "
            f"loss {slam.last_loss:.4f} {scale}",
            flush=True,
        )


def _run_whole(args, at_truth: bool):
    """The whole system over `--frames` of the sequence. Returns its settings, camera, frames,
    true depths, the `Slam`, the Sim(3) of its initialization onto the ground truth (None
    when it never initialized) and how many frames it took; `at_truth`: every frame after
    the initialization at its true pose (`_track_at_ground_truth`)."""
    cfg, camera, frames = load(args)
    depths = gt_depths(Path(args.seq), frames, camera)
    slam = Slam(cfg, camera, torch.device("cpu"))
    alignment, fed = None, 0
    for fed in _feed(slam, frames):
        if alignment is None:
            gt = _ground_truth(frames[:fed])
            alignment = evaluate_trajectory(slam.trajectory(), gt).alignment
            if at_truth:
                _track_at_ground_truth(slam, frames, alignment.inverse())
    return cfg, camera, frames, depths, slam, alignment, fed


def _track_at_ground_truth(slam: Slam, frames, to_map) -> None:
    """From now on every tracked frame gets its true pose (`to_map`: ground truth into the
    map's frame and scale) and mapping rounds move no pose; the tracker still decides
    keyframes and losses. The map is then learned from true poses only (after the
    initialization's): what is left of its error is the mapper's. It needs an
    initialization whose alignment to the ground truth is well determined: on room0 the
    true poses do not fit the initial map and the tracker is lost from frame 14 on, never
    relocalized (read the drift column first)."""
    mapper = slam.back.mapper
    mapper.cfg = dataclasses.replace(mapper.cfg, pose_lr=0.0)
    track = slam.front.track

    def tracked(field, index, timestamp, rgb):
        state = track(field, index, timestamp, rgb)
        if state is not None:
            T = to_map.apply_poses(frames[index].T_wc[None].astype(np.float64))[0]
            state.T_wc = torch.from_numpy(T).to(state.T_wc)
        return state

    slam.front.track = tracked


BASIN_SCALES = (0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0, 1.1, 1.25, 1.5)
"""Multiples of the true depth at which `basin` evaluates the warping cost."""


def cmd_basin(args) -> None:
    """Is a surface mapped too near from true poses a minimum of the objective, or one the
    mapper has not reached? `run --gt-poses` over `--frames`; then, at the newest frame, the
    textured pixels (the tracker's strongest tenth of the gradient) whose rendered depth is
    below 0.8 of the view's median scale, and for comparison those within 10 % of it: the
    warping cost of their patches (sizes of the preset, against the last mapping round's
    frames and the six keyframes before the newest) with the depth set to the true depth
    times each of `BASIN_SCALES`, and at the rendered depth. Then `--rounds` more mapping
    rounds of the newest frames at their true poses, with `--then` overrides, and the map's
    scale over the view, its textured pixels and those farther than 0.7 of the view's
    farthest true depth after every second round."""
    cfg, camera, frames, depths, slam, alignment, fed = _run_whole(args, at_truth=True)
    if alignment is None or fed < len(frames):
        raise SystemExit("basin: the run stopped before its last frame")
    back, mapper = slam.back, slam.back.mapper
    recent = back.frames[-cfg.mapper.every :]
    newest = recent[-1]
    true = depths[newest.index] / alignment.s  # map units at the initialization's scale
    known = true > 0
    H, W = true.shape
    margin = max(cfg.loss.patch_sizes) // 2 + 1
    inside = np.zeros_like(known)
    inside[margin : H - margin, margin : W - margin] = True
    strong = _textured(_image(frames[newest.index]), known)

    def ratios() -> np.ndarray:
        with torch.no_grad():
            d, _ = render_image(mapper.field, camera, newest.T_wc, cfg.render)
        return np.where(known, d.numpy() / np.maximum(true, 1e-9), np.nan)

    ratio = ratios()
    med = float(np.nanmedian(ratio))
    sources = [f for f in back.keyframes if f.index < newest.index][-6:]
    window = sorted({id(f): f for f in [*sources, *recent]}.values(), key=lambda f: f.index)
    window.remove(newest)
    images = torch.stack([_image(frames[f.index]) for f in [newest, *window]])
    poses = torch.stack([newest.T_wc, *[f.T_wc for f in window]])
    print(
        f"frame {newest.index}: view at {med:.3f} of its true depth; patches warped into "
        f"frames {[f.index for f in window]}"
    )
    groups = {
        "mapped too near (< 0.8 of the view's scale)": strong & inside & (ratio < 0.8 * med),
        "at the view's scale (within 10 %)": strong & inside & (np.abs(ratio / med - 1) < 0.1),
    }
    for name, mask in groups.items():
        v, u = np.nonzero(mask)
        if u.size == 0:
            print(f"  {name}: no pixel")
            continue
        pick = np.random.default_rng(0).choice(u.size, min(400, u.size), replace=False)
        v, u = v[pick], u[pick]
        uv = torch.from_numpy(np.stack([u, v], -1)).float()
        depth = torch.from_numpy(true[v, u]).float()
        at = torch.from_numpy(ratio[v, u]).float()
        row = "  ".join(
            f"x{x:g} {_warp_cost(images, poses, camera, uv, depth * x, cfg.loss):.4f}"
            for x in BASIN_SCALES
        )
        print(f"  {name}: {int(mask.sum())} px, rendered at {float(at.median()):.3f} of true")
        print(f"    cost at the true depth times {row}")
        rendered = _warp_cost(images, poses, camera, uv, depth * at, cfg.loss)
        print(f"    cost at the rendered depth {rendered:.4f}")

    if args.rounds <= 0:
        return
    more = apply_overrides(cfg, dict(args.then))
    mapper.cfg = dataclasses.replace(more.mapper, pose_lr=0.0)
    mapper.loss_cfg, mapper.render_cfg = more.loss, more.render
    far = known & (true > 0.7 * true.max())

    def scales(when: str) -> None:
        r = ratios()
        print(
            f"  {when}: view {np.nanmedian(r):.3f}, textured {np.nanmedian(r[strong]):.3f}, "
            f"far {np.nanmedian(r[far]):.3f} of the true depth",
            flush=True,
        )

    then = " ".join(f"{k}={v}" for k, v in args.then)
    print(
        f"{args.rounds} more mapping rounds of frames {[f.index for f in recent]} "
        f"at their true poses{' with ' + then if then else ''}:"
    )
    for f in recent:  # the tracker released the images of the frames no window holds
        if f.rgb is None:
            f.rgb = _image(frames[f.index])
    scales("before")
    for i in range(1, args.rounds + 1):
        mapper.map(recent, back.keyframes)
        if i % 2 == 0 or i == args.rounds:
            scales(f"after {i}")
    for f in recent:  # the plane sweeps the rounds followed (`mapper.stereo_weight`)
        sweep = mapper.sweeps.get(f.index)
        if sweep is not None:
            ratio = _ratio(sweep.depth.numpy(), depths[f.index], alignment.s)
            print(
                f"  keyframe {f.index}'s plane sweep: {100 * sweep.kept:.0f} % of its pixels "
                f"kept, at {ratio:.3f} of the true depth"
            )


def _warp_cost(images, poses, camera, uv: torch.Tensor, depth: torch.Tensor, loss_cfg) -> float:
    """The warping loss of frame 0's patches at pixels `uv` and depths `depth` against the
    other frames of `images` at `poses`, every pixel counted wherever its patch lands."""
    offsets = losses.patch_offsets(max(loss_cfg.patch_sizes))
    ref = patch_colors(images, torch.zeros(len(uv), dtype=torch.long), uv, offsets)
    warp = losses.warp_patches(uv, depth, poses[0], poses, camera, offsets)
    valid = warp.valid.clone()
    valid[0] = False  # not against itself
    everywhere = torch.ones(len(uv), dtype=torch.bool)
    warped = losses.sample_images(images, warp.uv)
    return float(losses.warping_loss(ref, warped, valid, everywhere, loss_cfg.patch_sizes).value)


def _image(frame) -> torch.Tensor:
    """A dataset frame's colour image as the system holds it: `(H, W, 3)` float in [0, 1]."""
    return image_tensor(frame.rgb)


def _textured(rgb: torch.Tensor, known: np.ndarray) -> np.ndarray:
    """The strongest tenth of the image gradient among the `known` pixels (where the tracker
    draws its points)."""
    grey = cv2.cvtColor((rgb.cpu().numpy() * 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)
    gradient = np.hypot(cv2.Sobel(grey, cv2.CV_32F, 1, 0), cv2.Sobel(grey, cv2.CV_32F, 0, 1))
    return known & (gradient >= np.percentile(gradient[known], 90))


def _ratio(depth: np.ndarray, gt: np.ndarray, scale: float) -> float:
    """Median of `scale * depth / gt` where both are known (NaN where nothing is)."""
    if depth.shape != gt.shape:
        gt = cv2.resize(gt, depth.shape[::-1], interpolation=cv2.INTER_NEAREST)
    ok = np.isfinite(depth) & (gt > 0)
    return float(np.median(scale * depth[ok] / gt[ok])) if ok.any() else float("nan")


def cmd_keyframes(args) -> None:
    """The whole system over `--frames`; then, per keyframe, the depth scale (over the true
    depth, times the initialization's alignment scale: 1 is the scale the system started
    with) of what the map renders at its final pose, and of its plane sweep (the mapper's
    multi-view depth, found when the keyframe was new, from the poses of then)."""
    cfg, camera, frames, depths, slam, alignment, _ = _run_whole(args, at_truth=False)
    if alignment is None:
        raise SystemExit("error: the system did not initialize")
    mapper = slam.back.mapper
    print(f"{len(slam.keyframes)} keyframes, {len(mapper.sweeps)} with a plane sweep")
    print("keyframe | true median depth | map scale | sweep scale (kept)")
    for kf in slam.keyframes:
        d, _ = render_image(mapper.field, camera, kf.T_wc, cfg.render)
        gt = depths[kf.index]
        sweep = mapper.sweeps.get(kf.index)
        swept = "-"
        if sweep is not None:
            ratio = _ratio(sweep.depth.numpy(), gt, alignment.s)
            swept = f"{ratio:.3f} ({100 * sweep.kept:.0f} %)"
        print(
            f"{kf.index:8d} | {np.median(gt[gt > 0]):15.2f} m | "
            f"{_ratio(d.numpy(), gt, alignment.s):9.3f} | {swept}",
            flush=True,
        )


def cmd_mesh(args) -> None:
    """The whole system over `--frames`, then meshes, each evaluated as a run's is (the
    trajectory's Sim(3), culled to the true frustums):

    - `mesh_map.ply`, the mapper's (`Mapper.mesh_depths`: with `mapper.mesh_sweeps`, the
      mesh views' plane sweeps and the map's depth where they agree with it);
    - `mesh_map_depth.ply`: the depth the map renders at the mesh views alone, fused;
    - `mesh_map_view_scale.ply`: that depth with each view's scale made the truth's
      (times its median ratio to the true depth in map units, the true depth divided by the
      alignment's scale): what is left of the mapper's error when only the shape of each
      view's depth is the map's;
    - `mesh_true_depth.ply`: the true depth at the keyframes' estimated poses, in map units:
      what a perfect depth would give at these poses, the part of the error that is the
      poses';
    - with `--refit N[,N...]`, `mesh_refit_N.ply`: the mapper's mesh after N more map
      iterations (poses held) over windows about every keyframe in turn, as the end of a run
      refits the map after its bundle adjustment: whether a map fitted longer to the final
      poses meshes better."""
    from dimslam.common.io.trajectory import write_tum

    if args.out is None:
        raise SystemExit("error: mesh needs --out DIR (meshes and trajectory go there)")
    refits = sorted({int(n) for n in args.refit.split(",")}) if args.refit else []
    if any(n <= 0 for n in refits):
        raise SystemExit(f"error: --refit takes positive iteration counts, got {args.refit}")
    cfg, camera, frames = load(args)
    slam = Slam(cfg, camera, torch.device("cpu"))
    for _ in _feed(slam, frames):
        pass
    if not slam.initialized:
        raise SystemExit("error: the system did not initialize")
    slam.finish()
    args.out.mkdir(parents=True, exist_ok=True)
    traj = slam.trajectory()
    write_tum(args.out / "trajectory.txt", traj)
    gt = _ground_truth(frames)
    alignment = evaluate_trajectory(traj, gt).alignment
    mapper = slam.back.mapper
    poses = torch.from_numpy(traj.poses).float()
    far = cfg.render.far
    keyframes = slam.keyframes
    mesh = mapper.mesh_depths(poses, keyframes)
    small, views, picked = mesh.camera, mesh.T_wc, mesh.index
    truth = np.stack(gt_depths(Path(args.seq), [frames[i] for i in picked], small))
    truth = torch.from_numpy(truth) / alignment.s
    swept = mesh.depths.where(mesh.weights == 1, math.nan) if cfg.mapper.mesh_sweeps else None
    print("mesh view | map depth / true depth (median, quartiles) | plane sweep's (kept)")
    rendered = mapper.render_depths(views, small)  # everywhere (the mesh's skips some pixels)
    scaled = rendered.clone()
    for v, (d, t) in enumerate(zip(rendered, truth, strict=True)):
        q1, q2, q3 = _quartiles(d, t)
        sweep = "-"
        if swept is not None:
            s1, s2, s3 = _quartiles(swept[v], t)
            sweep = (
                f"{s2:.3f} ({s1:.3f}-{s3:.3f}, {100 * swept[v].isfinite().float().mean():.0f} %)"
            )
        print(f"{int(picked[v]):9d} | {q2:.3f} ({q1:.3f}-{q3:.3f}) | {sweep}")
        scaled[v] = d / q2
    true_kf = gt_depths(Path(args.seq), [frames[kf.index] for kf in keyframes], small)
    kf_T = torch.stack([kf.T_wc.detach().cpu() for kf in keyframes])
    true_kf = torch.from_numpy(np.stack(true_kf)) / alignment.s

    def alone(depths, T_wc, index) -> MeshDepths:
        return MeshDepths(depths, torch.ones_like(depths), T_wc, small, depths, index)

    kf_index = torch.tensor([kf.index for kf in keyframes])

    meshes = {
        "mesh_map.ply": lambda: mapper.fuse_mesh(mesh, poses, far),
        "mesh_map_depth.ply": lambda: mapper.fuse_mesh(alone(rendered, views, picked), poses, far),
        "mesh_map_view_scale.ply": lambda: mapper.fuse_mesh(
            alone(scaled, views, picked), poses, far
        ),
        "mesh_true_depth.ply": lambda: mapper.fuse_mesh(alone(true_kf, kf_T, kf_index), poses, far),
    }
    for name, make in meshes.items():
        _write_evaluated(make(), args, name)
    done = 0
    for n in refits:
        started = time.perf_counter()
        mapper.post_optimize(keyframes, n - done, anchors=keyframes)
        done = n
        print(f"refit to {n} iterations: {time.perf_counter() - started:.0f} s")
        _write_evaluated(mapper.extract_mesh(poses, far, keyframes), args, f"mesh_refit_{n}.ply")


def _quartiles(depth: torch.Tensor, truth: torch.Tensor) -> tuple[float, float, float]:
    """Quartiles of `depth / truth` where both are known (NaN where nothing is)."""
    ok = (truth > 0) & (depth > 0)  # NaN compares False
    if not ok.any():
        return math.nan, math.nan, math.nan
    ratio = (depth[ok] / truth[ok]).double()
    q1, q2, q3 = ratio.quantile(torch.tensor([0.25, 0.5, 0.75]).double()).tolist()
    return q1, q2, q3


def _write_evaluated(mesh, args, name: str) -> None:
    """Write `mesh` as `args.out / name` and print its evaluation against `args.seq`."""
    from dimslam.common.eval.report import evaluate_files, format_metrics
    from dimslam.common.map.mesh import write_mesh

    write_mesh(mesh, args.out / name)
    metrics = evaluate_files(args.out / "trajectory.txt", args.seq, mesh=args.out / name)
    print(f"{name}:\n{format_metrics(metrics)}", flush=True)


def cmd_mesh_truth(args) -> None:
    """The mesh fused from the true depth at the true poses (`mapper.mesh_views` of them,
    evenly spread, at `mapper.mesh_width` pixels, `mapper.mesh_voxel`), evaluated as a run's
    mesh is: what the fusion and the evaluation protocol allow with nothing estimated."""
    from dimslam.common.io.trajectory import write_tum
    from dimslam.common.map import mesh as meshing

    if args.out is None:
        raise SystemExit("error: mesh-truth needs --out DIR (mesh and trajectory go there)")
    cfg, camera, frames = load(args)
    truth = _ground_truth(frames)
    args.out.mkdir(parents=True, exist_ok=True)
    write_tum(args.out / "trajectory.txt", truth)
    poses = torch.from_numpy(truth.poses).float()
    pick = torch.linspace(0, len(frames) - 1, min(len(frames), cfg.mapper.mesh_views))
    pick = pick.round().long()
    small = camera.resized(min(camera.width, cfg.mapper.mesh_width))
    depths = torch.from_numpy(np.stack(gt_depths(Path(args.seq), [frames[i] for i in pick], small)))
    voxel, far = cfg.mapper.mesh_voxel, cfg.render.far
    occupancy = meshing.fused_occupancy(depths, poses[pick], small, truncation=3 * voxel)
    centres = poses[:, :3, 3]
    bound = torch.stack([centres.min(0).values - far, centres.max(0).values + far])

    def grey(p: torch.Tensor) -> torch.Tensor:
        return torch.full((len(p), 3), 0.5)

    with torch.no_grad():
        mesh = meshing.extract_mesh_in_budget(
            occupancy, grey, bound, voxel, poses, camera, far, unknown_nan=True
        )
    print(f"{len(pick)} views, {small.width} px, voxel {voxel}:")
    _write_evaluated(mesh, args, "mesh_truth.ply")
    _completion_seen(Path(args.seq), mesh, Sim3.identity(), frames, truth.poses, camera)


def cmd_mesh_seen(args) -> None:
    """A run's mesh (`--out RUN`: its `mesh.ply` and `trajectory.txt`) after the trajectory's
    Sim(3), its completion split into the ground truth that some frame sees unoccluded and
    the part none does (`_completion_seen`)."""
    from dimslam.common.eval.mesh_metrics import load_mesh
    from dimslam.common.io.trajectory import read_tum

    if args.out is None:
        raise SystemExit("error: mesh-seen needs --out RUN (a run folder with mesh.ply)")
    _, camera, frames = load(args)
    truth = _ground_truth(frames)
    alignment = evaluate_trajectory(read_tum(args.out / "trajectory.txt"), truth).alignment
    mesh = load_mesh(args.out / "mesh.ply")
    _completion_seen(Path(args.seq), mesh, alignment, frames, truth.poses, camera)


OCCLUSION_TOLERANCE = 0.03
"""A ground-truth point counts as seen by a frame when it lies at most this far (map units,
or 2 % of its depth where that is more) behind the frame's true depth at its pixel."""


def _completion_seen(seq: Path, mesh, alignment, frames, T_wc: np.ndarray, camera) -> None:
    """What the protocol's culling counts that no camera saw: of the ground-truth surface
    inside the frustums (the protocol's sample of 200 000 points), the share that some frame
    sees unoccluded (its true depth at the point's pixel, `OCCLUSION_TOLERANCE`), and the
    completion of `mesh` (mapped into the ground truth's frame by `alignment`) over all of
    it, the seen part and the hidden part (the protocol has no occlusion test: what no frame
    saw counts as missing from every map)."""
    from scipy.spatial import cKDTree

    from dimslam.common.eval.mesh_metrics import load_mesh, sample_visible

    gt_mesh = load_mesh(seq / "mesh.ply")

    def culled(surface, to_world: Sim3, name: str) -> np.ndarray:  # as `evaluate_mesh` does
        rng = np.random.default_rng(0)
        return sample_visible(surface, 200_000, to_world, T_wc, camera, rng, name)[0]

    points = culled(gt_mesh, Sim3.identity(), "ground-truth")
    depths = gt_depths(seq, frames, camera)
    p_w = torch.from_numpy(points).float()
    seen = torch.zeros(len(p_w), dtype=torch.bool)
    T_cw = pose.invert(torch.from_numpy(np.asarray(T_wc)).float())
    for T, depth in zip(T_cw, depths, strict=True):
        uv, z = camera.project(pose.transform_points(T, p_w))
        inside = (z > 1e-3) & camera.inside(uv)
        u = uv[:, 0].round().long().clamp(0, camera.width - 1)
        v = uv[:, 1].round().long().clamp(0, camera.height - 1)
        d = torch.from_numpy(depth)[v, u]
        tolerance = torch.clamp(0.02 * z, min=OCCLUSION_TOLERANCE)
        seen |= inside & (d > 0) & (z <= d + tolerance)
    distance, _ = cKDTree(culled(mesh, alignment, "estimated")).query(points, workers=-1)
    share = float(seen.float().mean())
    visible, hidden = distance[seen.numpy()], distance[~seen.numpy()]
    print(
        f"ground truth in the frustums: {share:.1%} seen unoccluded by some frame (tolerance "
        f"{OCCLUSION_TOLERANCE * 100:.0f} cm or 2 % of the depth)\n"
        "the mesh's completion, cm and share within 5 cm:\n"
        f"  over all of it     {distance.mean() * 100:6.2f}  {(distance < 0.05).mean():6.1%}\n"
        f"  the seen part      {_mean_cm(visible):6.2f}  {(visible < 0.05).mean():6.1%}\n"
        f"  the hidden part    {_mean_cm(hidden):6.2f}  {(hidden < 0.05).mean():6.1%}",
        flush=True,
    )


def _mean_cm(distance: np.ndarray) -> float:
    return float(distance.mean() * 100) if len(distance) else math.nan


COMMANDS = {
    "map-oracle": cmd_map_oracle,
    "single": cmd_single,
    "landscape": cmd_landscape,
    "mapper": cmd_mapper,
    "init": cmd_init,
    "run": cmd_run,
    "keyframes": cmd_keyframes,
    "mesh": cmd_mesh,
    "mesh-truth": cmd_mesh_truth,
    "mesh-seen": cmd_mesh_seen,
    "basin": cmd_basin,
}


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("command", choices=list(COMMANDS))
    parser.add_argument("seq", help="TUM-layout sequence with depth.txt")
    parser.add_argument("--preset", choices=sorted(PRESETS), default="tiny")
    parser.add_argument("--frames", type=int, default=40, help="frames to use (default: 40)")
    parser.add_argument("--stride", type=int, default=1, help="every N-th frame (default: 1)")
    parser.add_argument("--fit-iters", type=int, default=200, help="map fitting iterations")
    parser.add_argument("--frame", type=int, default=19, help="frame of single / landscape")
    parser.add_argument("--iters", type=int, default=40, help="iterations of single")
    parser.add_argument("--shift", type=float, default=-0.018, help="anchor shift of landscape")
    parser.add_argument(
        "--depth-every",
        type=int,
        default=0,
        help="run: every N frames, the map's depth scale at the newest frame (0: never)",
    )
    parser.add_argument(
        "--gt-poses",
        action="store_true",
        help="run: after the initialization, frames take their true poses and mapping rounds "
        "move none (the map learned from true poses: the mapper's own error)",
    )
    parser.add_argument("--rounds", type=int, default=0, help="basin: more mapping rounds")
    parser.add_argument(
        "--then",
        nargs="*",
        action="extend",
        type=setting,
        default=[],
        metavar="SECTION.FIELD=VALUE",
        help="basin: settings of the extra mapping rounds only",
    )
    parser.add_argument(
        "--out",
        type=Path,
        help="mesh, mesh-truth: folder for the meshes and trajectory; mesh-seen: the run's",
    )
    parser.add_argument(
        "--refit",
        help="mesh: also mesh after this many more map iterations at the final poses "
        "(comma-separated, e.g. 200,600)",
    )
    parser.add_argument(
        "--threads",
        type=int,
        default=1,
        help="CPU threads (default 1: as benchmarks/table.py runs `dimslam run`, so that a "
        "whole run here is that run)",
    )
    parser.add_argument("--until", type=int, help="map-oracle: track only frames before this")
    parser.add_argument(
        "--map-cache",
        type=Path,
        help="keep fitted oracle maps in this folder and reuse them (keyed by sequence, "
        "frames, fit iterations and width)",
    )
    parser.add_argument(
        "--set",
        nargs="*",
        action="extend",
        type=setting,
        default=[],
        metavar="SECTION.FIELD=VALUE",
    )
    args = parser.parse_args()
    # An unknown key or a wrong type: refused before anything runs.
    overrides_or_exit(parser, PRESETS[args.preset], {**dict(args.set), **dict(args.then)})
    if args.threads < 1:
        parser.error(f"--threads must be >= 1, got {args.threads}")
    logging.basicConfig(level=logging.WARNING)
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    COMMANDS[args.command](args)


if __name__ == "__main__":
    main()

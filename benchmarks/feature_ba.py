"""Whether sparse features see a run's drift: ORB bundle adjustment over its keyframes.

    python benchmarks/feature_ba.py RUN DATASET [--odometry DEG DIR [--length L] [--linked N]
        [--length-linked L]]
        [--starts run,truth,blind] [--neighbours 8] [--iters 60] [--outlier 3] [--noise PX]
        [--guided] [--flow N [--flow-realign [--realign-window PX]]] [--save POSES.npy]
        [--init-keyframes [FRAMES]] [--fill-gaps FACTOR [--fill-evenly]]
        [--live | --every-frame [--prior-every-step]] [--keyframes-from RUN2]

RUN is a run's output folder (its `keyframes.txt`), DATASET the sequence it ran on, with
ground truth. The keyframes' images get the mapper's feature tracks (`mapper/bundle.py`:
ORB refined to sub-pixel, matched with the `--neighbours` keyframes before, an essential
matrix by RANSAC). For the *run* and *truth* starts, matches the ground truth calls wrong
(reprojection above `--outlier` pixels of their level after triangulation at the true poses)
are dropped, so what remains is what correct feature matches say about the poses; the
adjustment then starts from the run's keyframe poses or from the true ones (brought to the
run's frame by Sim(3)), with two consecutive keyframes held (they fix the gauge and the scale;
`--gauge`: the first two, or the pair sharing the most points):

- *points-only cost*: the points refined with every pose held, the Huber reprojection cost
  (squared pixels of the features' levels): a drifted path that costs no more than the true
  one is one the features cannot tell from it;
- *adjusted*: poses and points refined together, the cost and the keyframe ATE (Sim(3), cm)
  where it ends.

The *blind* start is what the mapper does (`--bundle.enabled true`): from the run, with the
outliers judged at its own poses (`mapper.bundle.adjust_tracks`; with `--guided`, guided
matching between its two passes, as `bundle.guided`). The points and observations on
the first line are those the truth keeps; the blind start's own (the figures of the
mapper's log line) are printed after it.

`--odometry DEG DIR` adds the run's own steps between consecutive keyframes as a prior,
without their lengths (each turn within DEG degrees, each direction within DIR): the
photometric tracker's local motion, which is accurate, with the scale left to the features.
Where two consecutive keyframes share fewer than `--linked` points, their step's length
relative to the step before is held too (within `--length`, log of the ratio), so that a
stretch no feature sees keeps its neighbours' scale (as `bundle.length` and `bundle.linked`
in the mapper; `--linked 0` leaves every length to the features). `--length-linked L`
holds the ratios of the linked steps too, within L (`bundle.length_linked`).

`--flow N` adds N corners followed by optical flow through every frame of the sequence
between the first and the last keyframe, observed at the keyframes (`bundle.flow`,
`mapper.bundle.FlowTracks`), as points of their own beside the ORB tracks.

`--live` does what the mapper does with a run whose rounds were live (`bundle.live`): the
flow is observed at every frame of the run's trajectory.txt (the frames a live mapper
gets), all of them are held, ORB describes the keyframes alone, and the `--odometry` prior
holds only the steps that fewer than `--linked` points link, no length ratio where they do,
nothing weighed (`BundleConfig.live_path`).

`--every-frame` does what the mapper does with `bundle.every_frame`: every frame held, the
flow observed at each (ORB at the keyframes alone), the `--odometry` prior on the steps
between the described frames alone (keyframes and the initialization's frames), the frames
between them placed by the features; `--prior-every-step` holds every step instead.

`--keyframes-from RUN2` adjusts this run's path at another run's keyframes (the frames of
RUN2's keyframes.txt, posed as this run's trajectory.txt has them): which of two runs'
differences is their paths' and which their keyframes' (two trackers on one sequence, say).

`--noise PX` replaces every observation by the projection of its point at the true poses
plus Gaussian noise: the features as an ideal detector would give them, which separates
what the data says from how well the problem is conditioned.

`--fit-camera` asks whether the ground truth is the motion of the camera that took the
images: the points-only cost at the true poses, then with the focal length, then also two
radial distortion terms and one constant turn between the truth's camera and the images'
fitted to lower it (Powell). A truth that is the images' motion costs about what the
features' own optimum does (the truth start's *adjusted* cost without `--odometry`); on a
synthetic room it does, with nothing fitted.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from dimslam.common.eval.evaluation import evaluate_trajectory, umeyama
from dimslam.common.geometry import pose
from dimslam.common.io.datasets import ReaderOptions, open_dataset
from dimslam.common.io.trajectory import Trajectory, read_tum, write_tum
from dimslam.mapper.backend import brought_back
from dimslam.mapper.bundle import (
    FLOW_REALIGN_WINDOW,
    GAUGES,
    SLIDE_GAP,
    SLIDE_INLIERS,
    BundleConfig,
    FeatureTracks,
    FlowTracks,
    Observations,
    adjust_tracks,
    bundle_adjust,
    grey_image,
    held_pair,
    links,
    observed,
    pointing_against,
    prior_at,
    prior_for,
    reprojection,
    slide_checked,
    triangulate,
)


def keyframe_ate(T_wc: np.ndarray, truth: np.ndarray) -> float:
    """Keyframe ATE (cm) after Sim(3), by the evaluator (poses matched one to one)."""
    stamps = np.arange(len(T_wc), dtype=np.float64)
    metrics = evaluate_trajectory(Trajectory(stamps, T_wc), Trajectory(stamps, truth))
    return metrics.ate_rmse_m * 100


def step_errors(T_wc: torch.Tensor, truth: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """How far each step between consecutive poses of `T_wc` turned (degrees) and pointed
    (unit vectors, over the steps of at least half the median length) from the truth's: what
    the odometry prior's `DEG` and `DIR` stand for."""
    est = pose.compose(pose.invert(T_wc[:-1]), T_wc[1:])
    true = pose.compose(pose.invert(truth[:-1]), truth[1:])
    turn = pose.log_so3(true[:, :3, :3].transpose(1, 2) @ est[:, :3, :3]).norm(dim=1)
    length = true[:, :3, 3].norm(dim=1)
    unit_est = est[:, :3, 3] / est[:, :3, 3].norm(dim=1, keepdim=True).clamp_min(1e-12)
    unit_true = true[:, :3, 3] / length[:, None].clamp_min(1e-12)
    long = length >= 0.5 * length.median()
    return torch.rad2deg(turn), (unit_est - unit_true).norm(dim=1)[long]


def carried(frames: Trajectory, keyframes: Trajectory, adjusted: torch.Tensor) -> np.ndarray:
    """Every frame of a run moved as the mapper moves it when its keyframes are adjusted
    (`BackEnd.adjust_keyframes`): each keyframe to its adjusted pose brought back onto the
    old path, each other frame with the keyframe before it, its offset scaled as the path
    about that keyframe grew."""
    T_new, scales = brought_back(torch.from_numpy(keyframes.poses), adjusted)
    ref = np.searchsorted(keyframes.timestamps, frames.timestamps + 1e-6, side="right") - 1
    out = []
    for T, k in zip(frames.poses, ref, strict=True):
        if k < 0:
            out.append(T)
            continue
        rel = np.linalg.inv(keyframes.poses[k]) @ T
        rel[:3, 3] *= float(scales[k])
        out.append(T_new[k].numpy() @ rel)
    return np.stack(out)


def _rows(keyframes: Trajectory, frames: Trajectory, option: str) -> np.ndarray:
    """The rows of `frames` that `keyframes` are.

    Raises:
        ValueError: fewer than two keyframes, or one that is not a frame of `frames`.
    """
    stamps, wanted = np.round(frames.timestamps, 4), np.round(keyframes.timestamps, 4)
    at = np.searchsorted(stamps, wanted)
    if len(at) < 2 or not np.array_equal(stamps[np.minimum(at, len(stamps) - 1)], wanted):
        raise ValueError(f"{option}: needs two keyframes or more, each a frame of trajectory.txt")
    return at


def _joined(keyframes: Trajectory, frames: Trajectory, at: np.ndarray, extra) -> Trajectory:
    """`keyframes` (rows `at` of `frames`) with the `extra` rows of `frames`, in path order."""
    order = np.argsort(np.concatenate([at, extra]), kind="stable")
    return Trajectory(
        np.concatenate([keyframes.timestamps, frames.timestamps[extra]])[order],
        np.concatenate([keyframes.poses, frames.poses[extra]])[order],
    )


def keyframes_at(frames: Trajectory, other: Trajectory) -> Trajectory:
    """The frames of `frames` that `other`'s keyframes are, with `frames`' poses
    (`--keyframes-from`).

    Raises:
        ValueError: a keyframe of `other` that is not a frame of `frames`.
    """
    stamps = np.round(frames.timestamps, 4)
    at = np.searchsorted(stamps, np.round(other.timestamps, 4))
    at = np.minimum(at, len(stamps) - 1)
    missing = stamps[at] != np.round(other.timestamps, 4)
    if missing.any():
        raise ValueError(
            f"--keyframes-from: {int(missing.sum())} keyframes are not frames of this run's "
            f"trajectory.txt (the first at t = {float(other.timestamps[missing][0]):.4f})"
        )
    return Trajectory(frames.timestamps[at], frames.poses[at])


def with_init_keyframes(
    keyframes: Trajectory, frames: Trajectory, chosen: list[int] | None = None
) -> Trajectory:
    """`keyframes` with the frames before the second one (the initialization's) at the run's
    median keyframe spacing, from the second frame on, or the `chosen` ones (rows of
    `frames`, each before the second keyframe): as if the initialization had made them
    keyframes (`--init-keyframes`).

    Raises:
        ValueError: fewer than two keyframes, one that is not a frame of `frames`, or a
            chosen frame that is not between the first two keyframes.
    """
    at = _rows(keyframes, frames, "--init-keyframes")
    if chosen is None:
        gap = max(1, int(np.median(np.diff(at))))
        extra = np.arange(at[0] + gap, at[1] - gap // 2, gap)
    else:
        extra = np.unique(np.asarray(chosen, dtype=int))
        if len(extra) and (extra.min() <= at[0] or extra.max() >= at[1]):
            raise ValueError(
                f"--init-keyframes: frames between the run's first two keyframes (rows "
                f"{at[0]} and {at[1]} of trajectory.txt), got {extra.tolist()}"
            )
    return _joined(keyframes, frames, at, extra)


def with_gap_frames(
    keyframes: Trajectory, frames: Trajectory, factor: float, evenly: bool = False
) -> Trajectory:
    """`keyframes` with frames in every gap between consecutive ones, after the first gap
    (the initialization's, left to `with_init_keyframes`), of at least `factor` times the
    run's median keyframe spacing, at that spacing (`--fill-gaps`): the frames a long gap
    carries rigidly from the keyframe before it, held by the adjustment instead. `evenly`
    (`--fill-evenly`): in every gap longer than `factor` spacings, the fewest frames that
    leave no piece of it longer, evenly spaced.

    Raises:
        ValueError: fewer than two keyframes, or one that is not a frame of `frames`.
    """
    at = _rows(keyframes, frames, "--fill-gaps")
    gap = max(1, int(np.median(np.diff(at))))
    pairs = list(zip(at[1:-1], at[2:], strict=True))
    if evenly:
        pieces = [(a, b, int(np.ceil((b - a) / (factor * gap)))) for a, b in pairs]
        extra = [a + round((b - a) * j / n) for a, b, n in pieces for j in range(1, n)]
    else:
        extra = [
            i for a, b in pairs if b - a >= factor * gap for i in range(a + gap, b - gap // 2, gap)
        ]
    return _joined(keyframes, frames, at, np.asarray(extra, dtype=int))


def in_front(obs: Observations, starts: dict[str, torch.Tensor], K: torch.Tensor) -> Observations:
    """The observations of the points that triangulate in front of every camera that sees
    them, at each start's poses."""
    for T_wc in starts.values():
        T_cw = pose.invert(T_wc)
        _, c = reprojection(T_cw, triangulate(T_cw, K, obs), K, obs)
        obs = obs.select(c[:, 2] > 0)
    return obs


def main() -> None:
    defaults = BundleConfig()
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run", type=Path, help="a run's output folder (keyframes.txt)")
    p.add_argument("dataset", help="the sequence it ran on, with ground truth")
    p.add_argument(
        "--neighbours",
        type=int,
        default=defaults.neighbours,
        help="keyframes before each that it is matched with",
    )
    p.add_argument("--iters", type=int, default=defaults.iters, help="adjustment iterations")
    p.add_argument(
        "--outlier",
        type=float,
        default=defaults.outlier,
        help="reprojection error (pixels of the level) of an outlier",
    )
    p.add_argument(
        "--noise", type=float, default=None, help="px: ideal observations with this noise"
    )
    p.add_argument(
        "--odometry",
        type=float,
        nargs=2,
        metavar=("DEG", "DIR"),
        help="also hold the run's steps between keyframes: turns within DEG degrees, "
        f"directions within DIR (bundle.turn_deg {defaults.turn_deg}, bundle.direction "
        f"{defaults.direction} in the mapper)",
    )
    p.add_argument(
        "--starts",
        default="run,truth",
        help="comma-separated: run, truth, blind (what the mapper does: from the run, "
        "outliers judged at its own poses)",
    )
    p.add_argument(
        "--views",
        type=int,
        default=defaults.views,
        help="the least keyframes a track is used from",
    )
    p.add_argument(
        "--gauge",
        choices=GAUGES,
        default=defaults.gauge,
        help="the held pair of every start: the first two keyframes, or the consecutive "
        "pair sharing the most points (bundle.gauge)",
    )
    p.add_argument(
        "--length",
        type=float,
        default=defaults.length,
        help="with --odometry: each step's length relative to the step before held within "
        "this (log of the ratio) where --linked features do not link its keyframes",
    )
    p.add_argument(
        "--length-linked",
        type=float,
        default=defaults.length_linked,
        help="with --odometry: the same hold where features link the keyframes (0: none; "
        "bundle.length_linked)",
    )
    p.add_argument(
        "--linked",
        type=int,
        default=defaults.linked,
        help="with --odometry: points two consecutive keyframes share from which their "
        "step's length is left to the features (0: lengths free everywhere but for "
        "--length-linked)",
    )
    p.add_argument("--width", type=int, default=320, help="image width (the cpu preset's)")
    p.add_argument(
        "--guided",
        action=argparse.BooleanOptionalAction,
        default=defaults.guided,
        help="blind start: guided matching between the adjustment's two passes "
        "(`bundle.guided`; default: the mapper's default)",
    )
    p.add_argument(
        "--flow",
        type=int,
        default=defaults.flow,
        help="also corners followed by optical flow through every frame, this many "
        "(`bundle.flow`; 0: ORB alone)",
    )
    p.add_argument(
        "--flow-near",
        type=int,
        default=defaults.flow_near,
        help="the flow's observations only within this many keyframes of a step fewer than "
        "--linked ORB points link (`bundle.flow_near`; -1: everywhere)",
    )
    p.add_argument(
        "--flow-realign",
        action=argparse.BooleanOptionalAction,
        default=defaults.flow_realign,
        help="align the flow's corners again with their first keyframe at each keyframe "
        "(`bundle.flow_realign`)",
    )
    p.add_argument(
        "--realign-window",
        type=int,
        default=FLOW_REALIGN_WINDOW,
        help="pixels: Lucas-Kanade's window for that alignment (the mapper's "
        "FLOW_REALIGN_WINDOW; 21 before session 62)",
    )
    p.add_argument(
        "--save", type=Path, help="blind start: write the adjusted keyframe poses here (.npy)"
    )
    p.add_argument(
        "--fit-camera",
        action="store_true",
        help="the points-only cost at the true poses with the focal length, distortion and a "
        "constant turn fitted (is the truth the images' camera motion?)",
    )
    p.add_argument(
        "--save-trajectory",
        type=Path,
        help="blind start: write every frame as the mapper carries it here (TUM)",
    )
    p.add_argument(
        "--slides",
        action="store_true",
        help="stretches where the features contradict the tracked motion: the blind start "
        "takes them from the motion before them, and every start's prior leaves their steps "
        "free (`bundle.slides`)",
    )
    p.add_argument(
        "--weigh",
        type=int,
        default=defaults.weigh,
        help="rounds of variance component estimation of the prior's turns against the "
        "reprojection errors, each re-solving the second pass (`bundle.weigh`)",
    )
    p.add_argument(
        "--weigh-steps",
        action="store_true",
        help="with --weigh: the directions weighed with the turns, one variance component "
        "(`bundle.weigh_steps`)",
    )
    p.add_argument(
        "--init-keyframes",
        nargs="?",
        const="spacing",
        metavar="FRAMES",
        help="also adjust frames before the run's second keyframe (the initialization's), "
        "carrying the frames between from them, the run unchanged: alone, at the run's "
        "median keyframe spacing; with FRAMES (e.g. 4,8,12: rows of trajectory.txt, the frame "
        "numbers of a stride-1 run), those: the mapper's log line 'the initialization's frames "
        "the tracker's rule marks' names them (bundle.init_frames)",
    )
    p.add_argument(
        "--fill-gaps",
        type=float,
        metavar="FACTOR",
        help="also adjust frames in every gap between keyframes after the run's second one, of "
        "at least FACTOR times the run's median keyframe spacing, at that spacing, carrying "
        "the frames between from them (the run unchanged)",
    )
    p.add_argument(
        "--fill-evenly",
        action="store_true",
        help="with --fill-gaps: in every gap longer than FACTOR spacings, the fewest frames "
        "that leave no piece of it longer, evenly spaced (a gap of 15 at spacing 2 and FACTOR "
        "3: 2 frames, not 7)",
    )
    p.add_argument(
        "--keyframes-from",
        type=Path,
        metavar="RUN2",
        help="adjust at another run's keyframes: the frames of RUN2/keyframes.txt, posed as "
        "this run's trajectory.txt has them (before --init-keyframes and --fill-gaps)",
    )
    p.add_argument(
        "--live",
        action="store_true",
        help="what the mapper does with a live run (bundle.live): with --flow, every frame "
        "of trajectory.txt held, the flow observed at each (ORB at the keyframes alone), the "
        "tracked steps held only where features do not link them (with --odometry), no "
        "length ratio held, nothing weighed",
    )
    p.add_argument(
        "--every-frame",
        action="store_true",
        help="what the mapper does with bundle.every_frame: with --flow, every frame of "
        "trajectory.txt held and the flow observed at each (ORB at the keyframes alone), the "
        "odometry prior on the steps between described frames (keyframes, initialization "
        "frames) alone",
    )
    p.add_argument(
        "--prior-every-step",
        action="store_true",
        help="with --every-frame: the odometry prior on every step from one frame to the "
        "next instead",
    )
    args = p.parse_args()
    if args.neighbours < 1 or args.iters < 0 or args.linked < 0 or args.length <= 0:
        p.error("--neighbours must be >= 1, --iters and --linked >= 0, --length > 0")
    if args.length_linked < 0:
        p.error("--length-linked must be >= 0")
    if args.realign_window < 3:
        p.error("--realign-window must be >= 3 pixels")
    if not set(args.starts.split(",")) <= {"run", "truth", "blind"}:
        p.error(f"--starts: run, truth and/or blind, got {args.starts!r}")
    if args.fill_evenly and args.fill_gaps is None:
        p.error("--fill-evenly needs --fill-gaps FACTOR")
    if args.every_frame and args.flow <= 0:
        p.error("--every-frame needs --flow N")
    if args.every_frame and args.live:
        p.error("--every-frame or --live, not both")
    if args.prior_every_step and not args.every_frame:
        p.error("--prior-every-step needs --every-frame")
    keyframes = read_tum(args.run / "keyframes.txt")
    every = (args.live or args.every_frame) and args.flow > 0
    if args.fill_gaps is not None or args.init_keyframes or every or args.keyframes_from:
        every_frame = read_tum(args.run / "trajectory.txt")
    if args.keyframes_from is not None:
        try:
            keyframes = keyframes_at(every_frame, read_tum(args.keyframes_from / "keyframes.txt"))
        except (OSError, ValueError) as error:
            p.error(str(error))
        print(f"keyframes of {args.keyframes_from}: {len(keyframes)}")
    if args.fill_gaps is not None:
        if args.fill_gaps <= 1:
            p.error("--fill-gaps must be > 1")
        try:
            keyframes = with_gap_frames(keyframes, every_frame, args.fill_gaps, args.fill_evenly)
        except ValueError as error:
            p.error(str(error))
        print(f"keyframes with the long gaps' frames: {len(keyframes)}")
    if args.init_keyframes:
        try:
            chosen = None
            if args.init_keyframes != "spacing":
                if not all(k.strip().isdigit() for k in args.init_keyframes.split(",")):
                    raise ValueError(
                        f"--init-keyframes: frame numbers separated by commas, got "
                        f"{args.init_keyframes!r}"
                    )
                chosen = [int(k) for k in args.init_keyframes.split(",")]
            keyframes = with_init_keyframes(keyframes, every_frame, chosen)
        except ValueError as error:
            p.error(str(error))
        print(f"keyframes with the initialization's frames: {len(keyframes)}")
    described = {round(float(t), 4) for t in keyframes.timestamps}  # ORB features
    if every:  # the flow observes every frame (a live mapper's, or with bundle.every_frame)
        keyframes = every_frame
        print(f"every frame held: {len(keyframes)}, {len(described)} of them described")
    reader = open_dataset(args.dataset, options=ReaderOptions(width=args.width))
    K = torch.from_numpy(reader.camera.K)
    wanted = {round(float(t), 4): k for k, t in enumerate(keyframes.timestamps)}
    images, truth, every_truth, at = {}, {}, {}, {}
    flow = FlowTracks(args.flow, args.flow_realign, args.realign_window) if args.flow > 0 else None
    for i, frame in enumerate(reader):
        every_truth[round(frame.timestamp, 4)] = frame.T_wc
        k = wanted.get(round(frame.timestamp, 4))
        if k is not None:
            images[k] = grey_image(frame.rgb)
            truth[k], at[k] = frame.T_wc, i
        if flow is not None and every and k is not None:
            flow.add(i, images[k], round(frame.timestamp, 4) in described, observe=True)
        elif flow is not None and at and not every:
            flow.add(i, images[k] if k is not None else grey_image(frame.rgb), k is not None)
    if len(images) != len(wanted) or any(t is None for t in truth.values()):
        p.error(f"{args.dataset}: {len(images)} of {len(wanted)} keyframes found with ground truth")
    n = len(images)
    tracks = FeatureTracks(K.numpy(), defaults.features, args.neighbours)
    indices = [at[k] for k in range(n)]  # keyframe k is frame indices[k] of the sequence
    for k in range(n):
        if round(float(keyframes.timestamps[k]), 4) in described:
            tracks.add(indices[k], images[k])
    turn_deg, direction = args.odometry or (defaults.turn_deg, defaults.direction)
    config = BundleConfig(
        turn_deg=turn_deg,
        direction=direction,
        views=args.views,
        outlier=args.outlier,
        iters=args.iters,
        guided=args.guided,
        length=args.length,
        linked=args.linked,
        length_linked=args.length_linked,
        flow_near=args.flow_near,
        gauge=args.gauge,
        weigh=args.weigh,
        weigh_steps=args.weigh_steps,
    )
    if args.live:
        config = config.live_path()
    unjudged = observed(tracks, flow, indices, config)
    gt = np.stack([truth[k] for k in range(n)])
    run = torch.from_numpy(keyframes.poses)
    starts = {
        "run": run,
        "truth": torch.from_numpy(umeyama(gt[:, :3, 3], run[:, :3, 3].numpy()).apply_poses(gt)),
    }
    # Matches the truth calls wrong are dropped; both starts then see the same observations:
    # those in front of their cameras from both.
    T_true = pose.invert(starts["truth"])
    r, c = reprojection(T_true, triangulate(T_true, K, unjudged), K, unjudged)
    obs = in_front(unjudged.select((r.norm(dim=1) < args.outlier) & (c[:, 2] > 0)), starts, K)
    if args.noise is not None:
        r, _ = reprojection(T_true, triangulate(T_true, K, obs), K, obs)
        noise = torch.randn(
            obs.uv.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64
        )
        obs.uv = obs.uv + r * obs.sigma[:, None] + args.noise * noise
        # The noise can triangulate a point of a narrow track behind a camera, where the
        # adjustment's cost is infinite: such points are left out, as above.
        obs = in_front(obs, starts, K)
    seen_by = torch.bincount(torch.bincount(obs.p), minlength=5)
    two, three, more = int(seen_by[2]), int(seen_by[3]), int(seen_by[4:].sum())
    print(
        f"{n} keyframes, {obs.points} points, {len(obs.k)} observations; points seen by "
        f"2 / 3 / 4+ keyframes: {two} / {three} / {more}"
    )
    turn, heading = step_errors(run, torch.from_numpy(gt))
    print(
        f"the run's steps between keyframes against the truth: turn error {turn.median():.3f} "
        f"deg median, {turn.quantile(0.9):.3f} p90; direction error (steps of at least half "
        f"the median length) {heading.median():.3f} median, {heading.quantile(0.9):.3f} p90"
    )
    shared = links(unjudged, n)
    print(
        f"points two consecutive keyframes share: median {int(shared.median())}, "
        f"{int((shared < args.linked).sum())} of {n - 1} steps under --linked {args.linked}"
    )
    blind_start, free = run, None
    if args.slides:
        check = slide_checked(run, K, tracks, flow, indices, config)
        blind_start, free = check.start, check.free
        against = pointing_against(check.cosine, check.inliers)
        print(
            f"essential matrices against the tracked motion from {SLIDE_GAP} keyframes before "
            f"({SLIDE_INLIERS}+ inliers; keyframe: cosine / inliers): "
            + " ".join(
                f"{k}: {check.cosine[k]:+.2f} / {check.inliers[k]}" for k in np.flatnonzero(against)
            )
        )
        print(
            "slides the features see (keyframes): "
            + (", ".join(f"{a}-{b}" for a, b in check.stretches) or "none")
        )
    prior = None
    if args.odometry is not None and args.every_frame and not args.prior_every_step:
        mine = [k for k in range(n) if indices[k] in tracks]  # as the mapper picks them
        prior = prior_at(blind_start, unjudged, config, torch.tensor(mine), free)
        print(f"the odometry prior on the {len(mine)} described frames alone")
    elif args.odometry is not None:
        prior = prior_for(blind_start, unjudged, config, free)
    print("start   ATE cm   points-only cost   adjusted: cost   ATE cm")
    blind = None
    for name in args.starts.split(","):
        T_wc = blind_start if name == "blind" else starts[name]
        T_cw = pose.invert(T_wc)
        if name == "blind":
            result = adjust_tracks(tracks, indices, blind_start, K, config, prior, flow, free)
            T_ba, cost, held = result.T_wc, result.cost, "-"
            blind, kept = T_ba, f"{result.points} points, {result.observations} observations"
            kept += f"; held frames {at[result.held]} and {at[result.held + 1]}"
            if args.guided:
                kept += f" ({result.guided} by guided matching)"
            if result.factors:
                turns, degrees = result.turns(turn_deg)
                kept += (
                    f"; the prior's {config.weighed} weighed x {turns:.2f} ({degrees:.2f} "
                    f"degrees for reprojection errors of {result.reprojection:.2f} px)"
                )
        else:
            _, X, points_only = bundle_adjust(T_cw, triangulate(T_cw, K, obs), K, obs, n, 20)
            gauge = held_pair(obs, n, args.gauge, free)
            T_cw, _, cost = bundle_adjust(T_cw, X, K, obs, gauge, args.iters, prior=prior)
            T_ba, held = pose.invert(T_cw), f"{points_only:.1f}"
        before, after = keyframe_ate(T_wc.numpy(), gt), keyframe_ate(T_ba.numpy(), gt)
        print(f"{name:6s}  {before:6.2f}   {held:>16s}   {cost:14.1f}   {after:6.2f}")
    if args.fit_camera:
        fit_camera(starts["truth"], K, obs)
    if blind is not None and args.save is not None:
        np.save(args.save, blind.numpy())
    if blind is not None:
        # The figures of the mapper's log line: the points above are those the truth keeps.
        print(f"blind: the adjustment kept {kept} (outliers judged at the run's poses)")
    path = args.run / "trajectory.txt"
    if blind is not None and path.exists():
        frames = read_tum(path)
        moved = carried(frames, keyframes, blind)
        gt_all = [every_truth.get(round(float(t), 4)) for t in frames.timestamps]
        if any(T is None for T in gt_all):
            p.error(f"{path}: frames without ground truth in {args.dataset}")
        stamps, truth_all = frames.timestamps, Trajectory(frames.timestamps, np.stack(gt_all))
        before = evaluate_trajectory(frames, truth_all).ate_rmse_m * 100
        after = evaluate_trajectory(Trajectory(stamps, moved), truth_all).ate_rmse_m * 100
        if args.save_trajectory is not None:
            write_tum(args.save_trajectory, Trajectory(stamps, moved))
        print(
            f"every frame (trajectory.txt, as the mapper carries them): {before:.2f} -> {after:.2f}"
        )


def fit_camera(T_wc: torch.Tensor, K: torch.Tensor, obs: Observations) -> None:
    """Print the points-only cost at poses `T_wc` as they are, then with the focal length
    scaled, then also with radial distortion (k1, k2) taken out of the observations and one
    constant turn applied to every camera, each fitted to the least cost."""
    from scipy.optimize import minimize
    from scipy.spatial.transform import Rotation

    centre = K[:2, 2]

    def cost(x: np.ndarray) -> float:  # turn (rotation vector), log focal scale, k1, k2
        turn = torch.eye(4, dtype=T_wc.dtype)
        turn[:3, :3] = torch.from_numpy(Rotation.from_rotvec(x[:3]).as_matrix())
        T_cw = pose.invert(T_wc @ turn)
        Kx = K.clone()
        Kx[:2, :2] *= float(np.exp(x[3]))
        seen = (obs.uv - centre) / Kx[0, 0]
        flat = seen.clone()
        for _ in range(8):  # undistorted = distorted / (1 + k1 r^2 + k2 r^4), r undistorted
            r2 = (flat * flat).sum(1, keepdim=True)
            flat = seen / (1 + x[4] * r2 + x[5] * r2 * r2)
        o = Observations(obs.k, obs.p, flat * Kx[0, 0] + centre, obs.sigma)
        return bundle_adjust(T_cw, triangulate(T_cw, Kx, o), Kx, o, len(T_wc), 10)[2]

    print(f"fit camera: the truth as it is, points-only cost {cost(np.zeros(6)):.1f}")
    for name, free in [("focal length", [3]), ("focal, k1, k2, a turn", [0, 1, 2, 3, 4, 5])]:

        def of(y: np.ndarray, free=free) -> float:
            x = np.zeros(6)
            x[free] = y
            return cost(x)

        fit = minimize(of, np.zeros(len(free)), method="Powell", options={"maxfev": 400})
        x = np.zeros(6)
        x[free] = fit.x
        print(
            f"fit camera: {name}: cost {fit.fun:.1f} (focal x{np.exp(x[3]):.3f}, "
            f"k1 {x[4]:.3f}, k2 {x[5]:.3f}, turn {np.degrees(np.linalg.norm(x[:3])):.2f} deg)"
        )


if __name__ == "__main__":
    main()

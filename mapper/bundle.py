"""Feature bundle adjustment of the keyframes: the scale the photometric map lets drift.

The photometric tracker and mapper follow each 30-frame stretch of a path to 0.2-2 cm, but
the map's scale drifts between stretches (a turn towards far walls that start too near,
docs/results.md "Where the scale goes"), and what they optimize cannot see it. Sparse
features can: a point seen from keyframes far apart ties their distances together. Here:

1. every keyframe gets ORB features (refined to sub-pixel: a FAST corner sits on a whole
   pixel of its pyramid level), matched with the `neighbours` keyframes before it (ratio
   test, then an essential matrix by RANSAC); the matches chain into tracks;
2. `adjust` refines all keyframe poses and the tracks' points together: the Huber
   reprojection error of every observation (in pixels of its pyramid level), plus an
   odometry prior that holds each step between consecutive keyframes to its turn and its
   direction as tracked, but not its length. The first two keyframes are held: they fix the
   map's gauge and scale. Outliers are judged at the poses themselves, loosely first and
   tightly after a first adjustment.

Levenberg-Marquardt with the points eliminated (Schur complement); poses are world to
camera and updated on the left. `benchmarks/feature_ba.py` measures what it does to a run's
keyframes against the ground truth.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
import torch

from dimslam.common.geometry import pose
from dimslam.common.options import option

log = logging.getLogger(__name__)

RATIO = 0.8
GAUGES = ("first", "linked")
"""The pairs an adjustment may hold (`BundleConfig.gauge`)."""
"""Lowe's ratio test: a match is kept when its distance is under this share of the second's."""
SCALE = 1.2
"""ORB's pyramid scale factor: a feature's pixel error grows with its level."""
STEP = 1e-6
"""The increment of the prior's central differences (radians and map units, float64)."""
GUIDE_RADIUS = 1.5
"""Guided matching: how far (pixels of the feature's level) from a point's projection a
feature may lie to be its observation."""
GUIDE_HAMMING = 50
"""Guided matching: the most bits a feature's descriptor may differ from the nearest of the
track's (ORB-SLAM's strict threshold)."""
SLIDE_GAP = 3
"""The slide check (`slides`) compares the tracked motion from keyframe k - 3 to k with the
essential matrix of their shared observations: consecutive keyframes are too near for its
direction."""
SLIDE_INLIERS = 100
"""An essential matrix points against the tracked motion only from this many inliers (with
fewer its direction is noise)."""
SLIDE_CONFIRMED = 0.5
"""A slide reaches over the keyframes next to it whose matrix does not clearly confirm the
tracked direction (cosine under this)."""
SLIDE_WINDOW, SLIDE_LEAST = 7, 5
"""A slide: at least 5 of 7 consecutive keyframes whose matrix points against the tracked
motion. Single ones do on every sequence (session 57's runs: room0 seed 1 three keyframes
of 6-10, room3 and 7-Scenes one to four apart, with 107-295 inliers), where the matrix is
wrong; 5 of 7 only in room5's last turn on seeds 0 and 1 (docs/results.md, session 59)."""


@dataclass(frozen=True)
class BundleConfig:
    """Feature bundle adjustment of the keyframes (mapper process)."""

    enabled: bool = option(
        False,
        "At the end of a run, refine every keyframe pose by its ORB features' reprojection "
        "error with the tracked steps' turns and directions as a prior (their lengths where "
        "features do not link the keyframes, and loosely everywhere with `length_linked`), "
        "and move the other frames and the map with them (on in the cpu preset).",
    )
    features: int = option(1500, "ORB features per keyframe.")
    neighbours: int = option(8, "Keyframes before each new one that it is matched with.")
    views: int = option(
        3,
        "The least keyframes a track is used from: a track seen twice fits any two poses "
        "that its epipolar line allows, so a wrong match cannot be told by its reprojection "
        "(with 2, room0 seed 1's keyframes went from 2.89 to 6.09 cm, with 3 to 2.50; "
        "docs/results.md).",
    )
    outlier: float = option(
        3.0, "Reprojection error (pixels of the feature's pyramid level) of an outlier."
    )
    turn_deg: float = option(
        0.1,
        "The odometry prior's standard error on each step's turn (degrees): the tracked "
        "steps between keyframes turn 0.09-0.2 degrees from the truth's (median over the "
        "rooms' runs, `benchmarks/feature_ba.py`).",
    )
    direction: float = option(
        0.03,
        "The odometry prior's standard error on each step's direction (a unit vector), for "
        "a step of the median length; shorter steps' directions are held less, in "
        "proportion. The tracked steps point 0.04-0.07 from the truth's (median norm over "
        "the rooms' runs; 0.03 per component).",
    )
    length: float = option(
        0.05,
        "The odometry prior's standard error on the log of a step's length relative to the "
        "step before, where features do not link the step's keyframes (`linked`). The "
        "tracked steps' ratios are off by 0.04-0.05 (median over the rooms' runs).",
    )
    length_linked: float = option(
        0.0,
        "The odometry prior's standard error on the log of a step's length relative to the "
        "step before where features do link the step's keyframes (0: left to the features "
        "there). The features' tracks are short (3-4 keyframes), so their scale wanders "
        "along the path; a loose hold on the tracked ratios keeps it near the tracker's. "
        "0.2 (the cpu preset's): with ORB and the flow about unlinked steps, room0, room5 "
        "and 7-Scenes gain, room3 loses 0.04 cm (session 60); with the flow everywhere, "
        "realigned, room0 2.19 -> 2.08 and 7-Scenes 4.73 -> 4.49 (docs/results.md).",
    )
    steps_linked: bool = option(
        True,
        "Hold the tracked turns and directions of the steps that features link (`linked` "
        "points or more) too; false: only where they do not (`live_path`).",
    )
    linked: int = option(
        10,
        "Points two consecutive keyframes must share for their step's length to be left to "
        "the features alone; with fewer it is held as well, in full where they share none. "
        "Without it, a stretch no feature sees (room5's textureless wall) leaves the scale "
        "of the path after it free, and the adjustment puts it anywhere; held wherever fewer "
        "than 50 points link the keyframes, it holds room3's drift too (docs/results.md). "
        "0: lengths free everywhere but for `length_linked`.",
    )
    min_described: float = option(
        0.5,
        "The adjustment runs only where the features describe at least this share of the "
        "keyframes: a live camera's short rounds describe none (`mapper.live_iters`), and "
        "from the few that a mapper behind a live camera once described the adjustment "
        "moved room0's live path by 11-37 cm at the median and doubled its error; from all "
        "of them described at the end, 11.4 -> 12.2 and 12.0 -> 10.2 cm (docs/results.md, "
        "sessions 52-53).",
    )
    every: int = option(
        0,
        "Also adjust during the run, each time this many new keyframes have features, so "
        "that the map and the tracker go on from the corrected poses (0: only at the end). "
        "20 took room3 seed 0 from 4.30 to 7.51 cm (docs/results.md).",
    )
    init_frames: bool = option(
        False,
        "Also adjust the initialization's frames that the tracker's rule marks on the new map "
        "(`keyframe_due`, as `mapper.init_keyframes` would make them keyframes), with the "
        "frames after each carried from it: the initialization leaves frame 0 its only "
        "keyframe, so the adjustment would hold the path's first 13 frames (23-29 cm on the "
        "rooms) at two poses. They are not keyframes: the tracker and the mapping rounds do "
        "not use them, and the run is the same until its end. AMD, 3 seeds: room0 0.86 -> "
        "0.77 cm, room3 1.46 -> 1.03, room5 1.55 -> 1.48, 7-Scenes the same (the rule marks "
        "none there) (on in the cpu preset; docs/results.md, session 66).",
    )
    iters: int = option(60, "Levenberg-Marquardt iterations (two passes of half).")
    gauge: Literal["first", "linked"] = option(
        "first",
        "The two keyframes the adjustment holds (its gauge and scale): the first two, or "
        "the consecutive pair that shares the most points (the mapper brings the adjusted "
        "path back onto the tracked one either way). Held, the first two keep any gap "
        "between them. Linked (the cpu preset's), AMD seeds 1 / 2: 7-Scenes 11.42 / 8.13 -> "
        "9.65 / 7.44 cm, room3 13.48 / 4.85 -> 8.87 / 4.82; Intel, 3 seeds: room0 2.34 -> "
        "2.23, room3 3.68 -> 3.66, room5 9.53 -> 9.38 (docs/results.md, 'The "
        "adjustment's gauge over the table').",
    )
    guided: bool = option(
        False,
        "Between the adjustment's two passes, carry each track to every keyframe where its "
        "point projects onto a feature like it (guided matching, `FeatureTracks.guide`): "
        "matching by descriptor links a keyframe with its `neighbours` before it only. "
        "Room3 4.30 -> 3.48 cm (seed 0), room0 1.73 -> 2.68; the adjustment's end swings by "
        "a centimetre with the observations it is given (docs/results.md, session 37).",
    )
    flow: int = option(
        0,
        "Also follow this many corners by optical flow (pyramidal Lucas-Kanade) through "
        "every frame, observed at the keyframes (`FlowTracks`): a stretch that ORB finds no "
        "corner in (room5's wall of smooth blobs) still links its keyframes. 0: ORB alone. "
        "300, means over 3 seeds: room3 3.70 -> 1.78 cm, room5 9.60 -> 7.40, but room0 1.51 "
        "-> 1.65 and 7-Scenes 3.84 -> 5.54 (docs/results.md, session 38).",
    )
    flow_near: int = option(
        -1,
        "Use the flow's observations only at the keyframes within this many of a step that "
        "fewer than `linked` ORB points link (room5's wall; room0 and 7-Scenes have no such "
        "step): -1, everywhere (the cpu preset's since session 61).",
    )
    flow_realign: bool = option(
        False,
        "At each keyframe, align every corner the flow follows again with its patch in the "
        "keyframe it started at (the frame-to-frame flow's drift does not add up: on "
        "7-Scenes its tracks reproject 1.5 px from the true poses at the median instead of "
        "2.8). With the flow everywhere, 7-Scenes 6.34 -> 4.73 cm, room3 2.50 -> 2.16, room0 "
        "and room5 give back part of the flow's gain (on in the cpu preset; docs/results.md, "
        "session 61). Those figures had the alignment in the flow's 21-pixel window; in "
        "`FLOW_REALIGN_WINDOW`'s 7 since session 62: room0 0.94, room3 1.81, room5 4.86, "
        "7-Scenes 4.47 cm.",
    )
    slides: bool = option(
        False,
        "Before adjusting, look for stretches where the features' epipolar geometry "
        "contradicts the tracked direction of motion over many keyframes (`slides`: the "
        "tracker slid into a wrong turn the images hardly tell from a sideways move, room5's "
        "last turn), and adjust them from the motion before them with no prior on their "
        "steps (`slid_start`; on in the cpu preset). Room5 9.38 -> 7.20 cm over 3 seeds, "
        "no stretch found on room0, room3 or 7-Scenes (docs/results.md, session 59).",
    )
    weigh: int = option(
        0,
        "Rounds of variance component estimation (`variance_factors`): after the "
        "adjustment, the prior's turns are weighed again by how far their residuals are, "
        "for their redundancy, from the reprojection errors', and the second pass solved "
        "again (0: `turn_deg` as configured; `WEIGHED` says why the turns, and "
        "`weigh_steps` the directions with them).",
    )
    weigh_steps: bool = option(
        False,
        "With `weigh`: each step's direction weighed with its turn, as one variance "
        "component (the tracked step's: one solve gives both), rather than held as "
        "configured (`direction`; on in the cpu preset). AMD, 3 seeds: room0 1.51 -> 0.86 "
        "cm, room3 2.12 -> 1.46, room5 3.97 -> 1.55, 7-Scenes 4.49 -> 4.39 "
        "(docs/results.md, session 64).",
    )
    refit_iters: int = option(
        60, "Map iterations, poses fixed, after the keyframes moved (windows of 20)."
    )
    live: bool = option(
        False,
        "A run whose rounds are live (`mapper.live_iters`: they describe no ORB features) "
        "still follows the flow (`flow`) through every frame they map, observed at each; "
        "at its end the mapper describes the keyframes (ORB) and adjusts every frame the "
        "flow observed, as `live_path` says: the tracked steps held only where features "
        "do not link them, no length ratio held, nothing weighed. A live path is tracked "
        "against a map of a twentieth of an offline run's iterations (room0 at 10 FPS: "
        "turns 0.37 degrees from the truth's at the median, 0.08 offline), and a prior on "
        "such steps, weighed or not, holds their error: room0 seed 0's live path 13.96 cm "
        "-> 5.01 with the offline prior, 1.12 with this one on the keyframes, 0.71 on every "
        "frame (docs/results.md, session 67). Off: a live run keeps its tracked poses.",
    )

    every_frame: bool = option(
        False,
        "Hold every frame in the end-of-run adjustment, not the keyframes alone: the flow's "
        "corners (`flow`) observed at each (ORB still at the keyframes and the "
        "initialization's frames), the odometry prior on the steps from one of those to the "
        "next alone, so that the frames between them are placed by the features (a live "
        "run's are `live`'s). AMD, 3 seeds: room0 0.77 -> 0.73 cm, room3 1.03 -> 0.75, "
        "room5 1.48 -> 1.81, 7-Scenes 4.39 -> 4.90 (docs/results.md, session 69): off.",
    )

    def live_path(self) -> BundleConfig:
        """The adjustment of a live path (`live`): the tracked steps held only where the
        features do not link their keyframes (`linked`), their lengths there alone, and no
        variance component weighed (with most steps free there is little to weigh)."""
        return dataclasses.replace(self, steps_linked=False, length_linked=0.0, weigh=0)

    @property
    def weighed(self) -> str:
        """What `weigh` weighs, for the logs: the turns, and the directions with them."""
        return "turns and directions" if self.weigh_steps else "turns"

    def __post_init__(self) -> None:
        if (
            self.features < 8
            or self.neighbours < 1
            or min(self.iters, self.refit_iters, self.weigh) < 0
        ):
            raise ValueError(
                "bundle: features >= 8, neighbours >= 1, iters, refit_iters and weigh >= 0 needed"
            )
        if self.linked < 0 or self.every < 0 or self.flow < 0:
            raise ValueError("bundle: linked, every and flow must be at least 0")
        if self.gauge not in GAUGES:
            raise ValueError(f"bundle.gauge must be first or linked, got {self.gauge!r}")
        if self.flow_near < -1:
            raise ValueError(
                f"bundle.flow_near must be -1 (everywhere) or more, got {self.flow_near}"
            )
        if self.views < 2:
            raise ValueError(f"bundle.views must be at least 2, got {self.views}")
        if min(self.outlier, self.turn_deg, self.direction, self.length) <= 0:
            raise ValueError("bundle: outlier, turn_deg, direction and length must be positive")
        if self.length_linked < 0:
            raise ValueError(
                f"bundle.length_linked must be 0 (off) or positive, got {self.length_linked}"
            )


@dataclass
class Observations:
    """Feature observations: pose `k[i]` sees point `p[i]` at pixel `uv[i]`."""

    k: torch.Tensor
    p: torch.Tensor
    uv: torch.Tensor
    sigma: torch.Tensor
    """`(n,)` the pixel's standard error: the scale of the pyramid level it was found on."""

    @property
    def points(self) -> int:
        return int(self.p.max()) + 1 if len(self.p) else 0

    def cat(self, other: Observations) -> Observations:
        """These observations and `other`'s, its points numbered after these."""
        return Observations(
            torch.cat([self.k, other.k]),
            torch.cat([self.p, other.p + self.points]),
            torch.cat([self.uv, other.uv]),
            torch.cat([self.sigma, other.sigma.to(self.sigma.dtype)]),
        )

    def kept_rows(self, keep: torch.Tensor) -> torch.Tensor:
        """Which observations `select(keep)` keeps: those of the points all of whose
        observations are in `keep`."""
        bad = torch.zeros(self.points, dtype=torch.bool)
        bad[self.p[~keep]] = True
        return ~bad[self.p]

    def rows(self, keep: torch.Tensor) -> Observations:
        """The observations `keep`, the points that keep any numbered again from 0."""
        _, p = torch.unique(self.p[keep], return_inverse=True)
        return Observations(self.k[keep], p, self.uv[keep], self.sigma[keep])

    def select(self, keep: torch.Tensor) -> Observations:
        """The observations `keep` of the points all of whose observations are kept, with
        the points numbered again from 0."""
        return self.rows(self.kept_rows(keep))


def grey_image(rgb: torch.Tensor | np.ndarray) -> np.ndarray:
    """8-bit grey of an `(H, W, 3)` RGB image, float in [0, 1] (tensor) or uint8."""
    if isinstance(rgb, torch.Tensor):
        rgb = (rgb.detach().cpu().numpy() * 255).round().astype(np.uint8)
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)


@dataclass
class Features:
    """A keyframe's ORB features."""

    points: np.ndarray
    """`(n, 2)` float64 sub-pixel positions."""
    sigma: np.ndarray
    """`(n,)` float64 pixel standard errors (`SCALE` to the pyramid level)."""
    descriptors: np.ndarray | None


def describe(grey: np.ndarray, features: int) -> Features:
    """ORB features of an 8-bit grey image, refined to sub-pixel."""
    orb = cv2.ORB_create(features, nlevels=4, edgeThreshold=19, patchSize=19, fastThreshold=10)
    keypoints, descriptors = orb.detectAndCompute(grey, None)
    points = np.array([k.pt for k in keypoints], np.float64).reshape(-1, 2)
    if len(points):
        criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 20, 0.01)
        refined = cv2.cornerSubPix(
            grey, points.astype(np.float32).reshape(-1, 1, 2), (2, 2), (-1, -1), criteria
        ).reshape(-1, 2)
        near = np.linalg.norm(refined - points, axis=1) < 1.0  # a corner it did not lose
        points[near] = refined[near]
    sigma = SCALE ** np.array([k.octave for k in keypoints], np.float64)
    return Features(points, sigma, descriptors)


def root(parent: np.ndarray, a: int) -> int:
    """The root of `a` in the union-find forest `parent` (paths halved on the way)."""
    while parent[a] != a:
        parent[a] = parent[parent[a]]
        a = int(parent[a])
    return a


class FeatureTracks:
    """Keyframes' features, added in path order, and the tracks their matches make."""

    def __init__(self, K: np.ndarray, features: int, neighbours: int) -> None:
        self.K = K
        self.features = features
        self.neighbours = neighbours
        self.keyframes: dict[int, Features] = {}  # frame index -> features, in path order
        self.offset: dict[int, int] = {}  # frame index -> its first feature's id
        self.parent = np.zeros(0, dtype=np.int64)  # union-find over feature ids
        self.matcher = cv2.BFMatcher(cv2.NORM_HAMMING)

    def __contains__(self, index: int) -> bool:
        return index in self.keyframes

    def _root(self, a: int) -> int:
        return root(self.parent, a)

    def add(self, index: int, grey: np.ndarray) -> None:
        """Describe keyframe `index` (newer than every one added) and link its features to
        the matching ones of the `neighbours` keyframes before it."""
        new = describe(grey, self.features)
        before = list(self.keyframes)[-self.neighbours :]
        self.insert(index, new)
        for j in before:
            old = self.keyframes[j]
            if new.descriptors is None or old.descriptors is None or len(old.descriptors) < 2:
                continue
            pairs = self.matcher.knnMatch(new.descriptors, old.descriptors, k=2)
            good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < RATIO * p[1].distance]
            if len(good) < 8:
                continue
            a = np.array([m.queryIdx for m in good])
            b = np.array([m.trainIdx for m in good])
            _, mask = cv2.findEssentialMat(
                new.points[a], old.points[b], self.K, cv2.RANSAC, 0.999, 1.0
            )
            if mask is None:
                continue
            inlier = mask.ravel() > 0
            for x, y in zip(a[inlier], b[inlier], strict=True):
                self.join(index, int(x), j, int(y))

    def insert(self, index: int, features: Features) -> None:
        """Keyframe `index`'s features (newer than every one held), each a track of its own."""
        start = len(self.parent)
        self.offset[index] = start
        self.parent = np.concatenate([self.parent, np.arange(start, start + len(features.points))])
        self.keyframes[index] = features

    def join(self, a: int, i: int, b: int, j: int) -> None:
        """One track for feature `i` of keyframe `a` and feature `j` of keyframe `b`."""
        self.parent[self._root(self.offset[a] + i)] = self._root(self.offset[b] + j)

    def _tracked(self, indices: list[int], views: int) -> tuple[Observations, np.ndarray]:
        """`observations`, and each observation's feature id; a frame of `indices` never
        described (one the flow alone observes, `FlowTracks.add`) has none."""
        kf, ids, uv, sigma = [], [], [], []
        for k, index in enumerate(indices):
            f = self.keyframes.get(index)
            if f is None:
                continue
            kf.append(np.full(len(f.points), k))
            ids.append(self.offset[index] + np.arange(len(f.points)))
            uv.append(f.points)
            sigma.append(f.sigma)
        kf, ids = np.concatenate(kf), np.concatenate(ids)
        roots = np.array([self._root(int(a)) for a in ids], dtype=np.int64)
        _, track, size = np.unique(roots, return_inverse=True, return_counts=True)
        twice = np.zeros(len(size), bool)
        values, counts = np.unique(track * len(indices) + kf, return_counts=True)
        twice[values[counts > 1] // len(indices)] = True
        keep = (size[track] >= views) & ~twice[track]
        _, p = np.unique(track[keep], return_inverse=True)
        obs = Observations(
            torch.from_numpy(kf[keep]),
            torch.from_numpy(p),
            torch.from_numpy(np.concatenate(uv)[keep]),
            torch.from_numpy(np.concatenate(sigma)[keep]),
        )
        return obs, ids[keep]

    def observations(self, indices: list[int], views: int = 2) -> Observations:
        """The tracks seen by at least `views` of keyframes `indices` (all added; pose `k` is
        `indices[k]`), without the tracks that see one keyframe twice (a wrong link)."""
        return self._tracked(indices, views)[0]

    def guide(self, indices: list[int], T_cw: torch.Tensor, views: int, outlier: float) -> int:
        """Guided matching: link to the tracks seen by `views` of keyframes `indices` the
        features of the other keyframes where their points project (`T_cw`, pose `k` of
        `indices[k]`): within `GUIDE_RADIUS` of the projection, the descriptor within
        `GUIDE_HAMMING` of the track's descriptor from the keyframe nearest in the path, and
        clearly nearer (`RATIO`) than any other feature there. Matching by descriptor links
        a keyframe with its `neighbours` before it only; here a point reaches every keyframe
        that sees it at these poses. Only points whose every observation reprojects within
        `outlier` are projected. Returns the links made."""
        obs, ids = self._tracked(indices, views)
        if obs.points == 0:
            return 0
        K = torch.from_numpy(self.K).to(T_cw.dtype)
        good = inliers(T_cw, K, obs, outlier)
        rows = obs.kept_rows(good).numpy()
        kept = obs.select(good)
        if kept.points == 0:
            return 0
        X = triangulate(T_cw, K, kept).numpy()
        p, k_of, fid = kept.p.numpy(), kept.k.numpy(), ids[rows]
        seen = np.zeros((kept.points, len(indices)), bool)
        seen[p, k_of] = True
        firsts = np.array([self.offset.get(i, 0) for i in indices])  # 0: not described
        local = fid - firsts[k_of]
        desc = np.stack(
            [self.keyframes[indices[k]].descriptors[j] for k, j in zip(k_of, local, strict=True)]
        )
        point_of = dict(zip(fid.tolist(), p.tolist(), strict=True))  # for merges
        feature_of = np.zeros(kept.points, np.int64)  # a feature id of each point
        feature_of[p] = fid
        # Points merged here share a representative and the keyframes that see them.
        rep = np.arange(kept.points)
        # Features of no track may join one; those of other tracks only as their point.
        every_root = np.array([self._root(a) for a in range(len(self.parent))], np.int64)
        alone = np.bincount(every_root, minlength=len(self.parent))[every_root] == 1

        def find(q: int) -> int:
            return root(rep, q)

        links = 0
        T = T_cw.numpy()
        for kk, index in enumerate(indices):
            f = self.keyframes.get(index)
            if f is None or f.descriptors is None or len(f.points) == 0:
                continue
            c = X @ T[kk, :3, :3].T + T[kk, :3, 3]
            z = np.maximum(c[:, 2], 1e-9)
            uv = c[:, :2] / z[:, None] * self.K.diagonal()[:2] + self.K[:2, 2]
            # Within reach of the keyframe's features (its image, as far as features go).
            reach = GUIDE_RADIUS * f.sigma.max()
            low, high = f.points.min(0) - reach, f.points.max(0) + reach
            inside = (c[:, 2] > 1e-3) & (uv > low).all(1) & (uv < high).all(1)
            roots = np.array([find(q) for q in range(kept.points)])
            candidates = np.flatnonzero(inside & ~seen[roots, kk])
            if len(candidates) == 0:
                continue
            # The track's descriptor from its observation nearest in the path.
            nearest = np.lexsort((np.abs(k_of - kk), p))
            first = nearest[np.r_[0, np.flatnonzero(np.diff(p[nearest])) + 1]]
            described = desc[first]  # (points, 32), point q's at row q
            gap = np.linalg.norm(uv[candidates, None, :] - f.points[None, :, :], axis=2)
            i, j = np.nonzero(gap < GUIDE_RADIUS * f.sigma[None, :])
            if len(i) == 0:
                continue
            q = candidates[i]
            bits = np.unpackbits(described[q] ^ f.descriptors[j], axis=1).sum(1)
            best: dict[int, tuple[int, int]] = {}  # point -> (bits, feature)
            second: dict[int, int] = {}
            for qq, jj, b in zip(q.tolist(), j.tolist(), bits.tolist(), strict=True):
                old = best.get(qq)
                if old is None or b < old[0]:
                    if old is not None:
                        second[qq] = old[0]
                    best[qq] = (b, jj)
                elif b < second.get(qq, 1 << 30):
                    second[qq] = b
            claimed: dict[int, tuple[int, int]] = {}  # feature -> (bits, point)
            for qq, (b, jj) in best.items():
                if b > GUIDE_HAMMING or b >= RATIO * second.get(qq, 1 << 30):
                    continue
                if jj not in claimed or b < claimed[jj][0]:
                    claimed[jj] = (b, qq)
            start = self.offset[index]
            for jj, (_, qq) in sorted(claimed.items(), key=lambda item: item[1]):
                a = find(qq)
                if seen[a, kk]:
                    continue  # a point merged with it in this keyframe already sees it
                other = point_of.get(start + jj)
                if other is None and not alone[start + jj]:
                    continue  # a feature of a track left out (too short, or an outlier)
                if other is not None:
                    b = find(other)
                    if (seen[a] & seen[b]).any():
                        continue  # two tracks that share a keyframe: not one point
                    rep[b] = a
                    seen[a] |= seen[b]
                seen[a, kk] = True
                self.parent[self._root(start + jj)] = self._root(int(feature_of[qq]))
                links += 1
        return links


FLOW_WINDOW = 21
"""Lucas-Kanade's window (pixels) and pyramid levels above the image."""
FLOW_LEVELS = 3
FLOW_CHECK = 0.3
"""Pixels a corner followed forward and back again may land from where it started."""
FLOW_REALIGN = 1.0
"""Pixels a corner's alignment with its first keyframe (`BundleConfig.flow_realign`) may
move it from where the flow put it before its track ends."""
FLOW_REALIGN_WINDOW = 7
"""Lucas-Kanade's window (pixels) for that alignment. Across keyframes the patch about a
corner changes shape with the viewpoint, and a wide window's best shift follows the patch
as a whole, not the corner: aligned in 21 pixels (the flow's window) the tracks hold the
features-only adjustment from the true poses 6.23 cm off on room5 seed 0 and 3.58 on
room0, in 7 pixels 1.25 and 0.84 (`benchmarks/feature_ba.py --starts truth`;
docs/results.md, session 62)."""
FLOW_SPACING = 8
"""The least pixels between two corners followed."""
FLOW_QUALITY = 0.001
"""A new corner's least eigenvalue, as a share of the image's strongest (Shi-Tomasi)."""


class FlowTracks:
    """Corners followed by pyramidal Lucas-Kanade from frame to frame, observed at keyframes.

    ORB needs corners a FAST test sees; a wall of smooth colour blobs has none (room5: 0 of
    1500 for 25 keyframes), so no ORB track links the keyframes that look at it, and the
    adjustment cannot hold the path's scale across it. Lucas-Kanade follows any patch with
    gradient in two directions, and between consecutive frames the motion is small enough
    to follow without a descriptor. New corners start at keyframes, away from those
    followed; a corner is dropped where the flow back does not return it within
    `FLOW_CHECK` pixels or it leaves the image. With `realign`, each corner is aligned
    again at every keyframe with its patch in the keyframe it started at, in a window
    `window` pixels wide (`FLOW_REALIGN_WINDOW`)."""

    def __init__(
        self, corners: int, realign: bool = False, window: int = FLOW_REALIGN_WINDOW
    ) -> None:
        self.corners, self.realign, self.window = corners, realign, window
        self.previous: np.ndarray | None = None
        self.last = -1
        self.points = np.zeros((0, 2), np.float32)  # the corners followed, in the last frame
        self.ids = np.zeros(0, np.int64)  # their tracks
        self.anchor = np.zeros(0, np.int64)  # the keyframe each started at
        self.start = np.zeros((0, 2), np.float32)  # and where
        self.images: dict[int, np.ndarray] = {}  # keyframes that followed corners started at
        self.tracks = 0
        self.seen: list[tuple[int, np.ndarray, np.ndarray]] = []  # keyframe, tracks, pixels
        self.frames: set[int] = set()  # the frames of `seen`

    def __contains__(self, index: int) -> bool:
        """Whether frame `index` was observed (a keyframe or an `observe`d frame)."""
        return index in self.frames

    def add(self, index: int, grey: np.ndarray, keyframe: bool, observe: bool = False) -> None:
        """Frame `index` (8-bit grey, newer than every one added): the corners followed
        into it, and at a keyframe observed there with new ones started. With `observe`, a
        frame that is not a keyframe but is held by the adjustment (a live run's,
        `BundleConfig.live`): its corners are aligned again (with `realign`) and observed
        there, none started."""
        if index <= self.last:
            return
        if self.previous is not None and len(self.points):
            self._follow(grey)
        if keyframe or observe:
            if self.realign:
                self._realign(grey)
            if keyframe:
                self._start(grey, index)
            self._observe(index)
        self.previous, self.last = grey, index

    def _observe(self, index: int) -> None:
        self.seen.append((index, self.ids.copy(), self.points.astype(np.float64)))
        self.frames.add(index)

    def _realign(self, grey: np.ndarray) -> None:
        """Each corner followed, aligned again with its patch in the keyframe it started at
        (from where the flow put it), so that the frame-to-frame flow's drift does not add
        up over a track. Where the two disagree by `FLOW_REALIGN` pixels or more, the track
        ends."""
        keep = np.ones(len(self.points), bool)
        window = (self.window, self.window)
        for a in np.unique(self.anchor):
            rows = np.flatnonzero(self.anchor == a)
            guess = self.points[rows].reshape(-1, 1, 2).copy()
            aligned, ok, _ = cv2.calcOpticalFlowPyrLK(
                self.images[a],
                grey,
                self.start[rows].reshape(-1, 1, 2),
                guess,
                winSize=window,
                maxLevel=1,
                flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
            )
            aligned = aligned.reshape(-1, 2)
            near = np.linalg.norm(aligned - self.points[rows], axis=1) < FLOW_REALIGN
            keep[rows] = (ok.ravel() == 1) & near
            self.points[rows] = aligned
        self._keep(keep)

    def _follow(self, grey: np.ndarray) -> None:
        window, before = (FLOW_WINDOW, FLOW_WINDOW), self.points.reshape(-1, 1, 2)
        after, ok, _ = cv2.calcOpticalFlowPyrLK(
            self.previous, grey, before, None, winSize=window, maxLevel=FLOW_LEVELS
        )
        back, ok_back, _ = cv2.calcOpticalFlowPyrLK(
            grey, self.previous, after, None, winSize=window, maxLevel=FLOW_LEVELS
        )
        after = after.reshape(-1, 2)
        height, width = grey.shape
        keep = (
            (ok.ravel() == 1)
            & (ok_back.ravel() == 1)
            & (np.linalg.norm((back - before).reshape(-1, 2), axis=1) < FLOW_CHECK)
            & (after >= 0).all(1)
            & (after[:, 0] <= width - 1)
            & (after[:, 1] <= height - 1)
        )
        self.points = after
        self._keep(keep)

    def _keep(self, keep: np.ndarray) -> None:
        self.points, self.ids = self.points[keep], self.ids[keep]
        self.anchor, self.start = self.anchor[keep], self.start[keep]
        self.images = {a: image for a, image in self.images.items() if a in self.anchor}

    def _start(self, grey: np.ndarray, index: int) -> None:
        wanted = self.corners - len(self.points)
        if wanted <= 0:
            return
        free = np.full(grey.shape, 255, np.uint8)
        for x, y in self.points:
            cv2.circle(free, (int(round(x)), int(round(y))), FLOW_SPACING, 0, -1)
        found = cv2.goodFeaturesToTrack(grey, wanted, FLOW_QUALITY, FLOW_SPACING, mask=free)
        if found is None:
            return
        found = found.reshape(-1, 2).astype(np.float32)
        self.points = np.concatenate([self.points, found])
        self.ids = np.concatenate([self.ids, self.tracks + np.arange(len(found))])
        self.anchor = np.concatenate([self.anchor, np.full(len(found), index)])
        self.start = np.concatenate([self.start, found])
        if self.realign:
            self.images[index] = grey
        self.tracks += len(found)

    def observations(self, indices: list[int], views: int) -> Observations:
        """The tracks seen by at least `views` of keyframes `indices` (pose `k` is
        `indices[k]`), each observation's standard error one pixel."""
        pose_of = {index: k for k, index in enumerate(indices)}
        rows = [(pose_of[i], ids, uv) for i, ids, uv in self.seen if i in pose_of]
        if not rows:
            empty = torch.zeros(0, dtype=torch.long)
            return Observations(
                empty, empty, torch.zeros(0, 2, dtype=torch.float64), empty.double()
            )
        k = np.concatenate([np.full(len(ids), kk) for kk, ids, _ in rows])
        track = np.concatenate([ids for _, ids, _ in rows])
        uv = np.concatenate([pixels for _, _, pixels in rows])
        _, inverse, size = np.unique(track, return_inverse=True, return_counts=True)
        keep = size[inverse] >= views
        _, p = np.unique(inverse[keep], return_inverse=True)
        return Observations(
            torch.from_numpy(k[keep]),
            torch.from_numpy(p),
            torch.from_numpy(uv[keep]),
            torch.ones(int(keep.sum()), dtype=torch.float64),
        )


def triangulate(T_cw: torch.Tensor, K: torch.Tensor, obs: Observations) -> torch.Tensor:
    """Each point by linear triangulation (DLT) from all its observations: `(points, 3)`."""
    P = K @ T_cw[:, :3, :]
    rows = torch.cat(
        [obs.uv[:, :1] * P[obs.k, 2] - P[obs.k, 0], obs.uv[:, 1:] * P[obs.k, 2] - P[obs.k, 1]]
    )
    A = torch.zeros(obs.points, 4, 4, dtype=T_cw.dtype)
    A.index_add_(0, obs.p.repeat(2), rows[:, :, None] * rows[:, None, :])
    _, vectors = torch.linalg.eigh(A)
    X = vectors[:, :, 0]
    return X[:, :3] / X[:, 3:]


def reprojection(
    T_cw: torch.Tensor, X: torch.Tensor, K: torch.Tensor, obs: Observations
) -> tuple[torch.Tensor, torch.Tensor]:
    """Residuals `(n, 2)` in pixels of each observation's level, and the camera-frame points
    `(n, 3)`."""
    c = (T_cw[obs.k, :3, :3] @ X[obs.p, :, None])[:, :, 0] + T_cw[obs.k, :3, 3]
    uv = c[:, :2] / c[:, 2:] * K.diagonal()[:2] + K[:2, 2]
    return (uv - obs.uv) / obs.sigma[:, None], c


def _huber(r: torch.Tensor, c: torch.Tensor, delta: float) -> float:
    if bool((c[:, 2] <= 1e-6).any()):
        return math.inf  # a step that puts a point behind a camera is not taken
    n = r.norm(dim=1)
    return float(torch.where(n <= delta, n**2, 2 * delta * n - delta**2).sum())


def _schur_pairs(obs: Observations, free: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Every pair of observations of one point, both on free poses, each unordered pair once
    (the first before the second in the observations' order) and each observation with
    itself: `_reduced` gets the pairs' mirror images by symmetry."""
    index = torch.nonzero(free)[:, 0]
    index = index[torch.argsort(obs.p[index], stable=True)]
    bounds = torch.searchsorted(obs.p[index], torch.arange(obs.points + 1)).tolist()
    first, second = [torch.zeros(0, dtype=torch.long)], [torch.zeros(0, dtype=torch.long)]
    upper: dict[int, torch.Tensor] = {}
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        if b > a:
            if b - a not in upper:
                upper[b - a] = torch.triu_indices(b - a, b - a)
            pairs = index[a:b][upper[b - a]]
            first.append(pairs[0])
            second.append(pairs[1])
    return torch.cat(first), torch.cat(second)


def _normal_equations(
    T_cw: torch.Tensor,
    K: torch.Tensor,
    obs: Observations,
    r: torch.Tensor,
    c: torch.Tensor,
    free: torch.Tensor,
    col: torch.Tensor,
    m: int,
    delta: float,
) -> tuple[torch.Tensor, ...]:
    """The Huber-weighted (IRLS) normal equations of the reprojection residuals `r` (camera
    points `c`) over the points and the `m` moving poses (`free` observations, each in its
    pose's block `col`): point blocks `H_pp` `(points, 3, 3)` and gradient `g_p`, each
    observation's pose-point block `H_cp` `(n, 6, 3)`, pose blocks `H_cc` `(m, m, 6, 6)` and
    gradient `g_c` `(m, 6)`."""
    norm = r.norm(dim=1)
    w = torch.where(norm <= delta, torch.ones_like(norm), delta / norm.clamp_min(1e-12))
    x, y, z = c.unbind(1)
    zero = torch.zeros_like(z)
    fx, fy = float(K[0, 0]), float(K[1, 1])
    dproj = (
        torch.stack(
            [
                torch.stack([fx / z, zero, -fx * x / z**2], 1),
                torch.stack([zero, fy / z, -fy * y / z**2], 1),
            ],
            1,
        )
        / obs.sigma[:, None, None]
    )
    J_pose = torch.cat([dproj, -dproj @ pose.hat(c)], 2)  # (n, 2, 6): left (v, w)
    J_point = dproj @ T_cw[obs.k, :3, :3]  # (n, 2, 3)
    wJ_point = w[:, None, None] * J_point
    H_pp = torch.zeros(obs.points, 3, 3, dtype=r.dtype).index_add_(
        0, obs.p, J_point.transpose(1, 2) @ wJ_point
    )
    g_p = torch.zeros(obs.points, 3, dtype=r.dtype).index_add_(
        0, obs.p, -(wJ_point.transpose(1, 2) @ r[:, :, None])[:, :, 0]
    )
    H_cp = J_pose.transpose(1, 2) @ wJ_point  # (n, 6, 3)
    H_cc = torch.zeros(m, m, 6, 6, dtype=r.dtype)
    H_cc.index_put_(
        (col[free], col[free]),
        (J_pose.transpose(1, 2) @ (w[:, None, None] * J_pose))[free],
        accumulate=True,
    )
    g_c = torch.zeros(m, 6, dtype=r.dtype).index_add_(
        0, col[free], -((w[:, None, None] * J_pose).transpose(1, 2) @ r[:, :, None])[free, :, 0]
    )
    return H_pp, g_p, H_cp, H_cc, g_c


def _reduced(
    H_cc: torch.Tensor,
    H_cp: torch.Tensor,
    H_pp_inv: torch.Tensor,
    p: torch.Tensor,
    col: torch.Tensor,
    ii: torch.Tensor,
    jj: torch.Tensor,
) -> torch.Tensor:
    """The reduced camera system `(6 m, 6 m)`: the pose blocks `H_cc` with the points
    eliminated (inverse point blocks `H_pp_inv`; `ii`, `jj` from `_schur_pairs`, each
    unordered pair once: the block of pair (j, i) is that of (i, j) transposed, so the
    products are computed once and the sum added to its transpose, an observation's pair
    with itself halved)."""
    m = len(H_cc)
    W = H_cp @ H_pp_inv[p]  # per observation, not per pair (a live run's pairs: millions)
    products = W[ii] @ H_cp[jj].transpose(1, 2)
    products[ii == jj] *= 0.5
    eliminated = torch.zeros_like(H_cc)
    eliminated.view(m * m, 6, 6).index_add_(0, col[ii] * m + col[jj], products)
    S = H_cc - eliminated - eliminated.permute(1, 0, 3, 2)
    return S.transpose(1, 2).reshape(6 * m, 6 * m)


def bundle_adjust(
    T_cw: torch.Tensor,
    X: torch.Tensor,
    K: torch.Tensor,
    obs: Observations,
    fixed: int | torch.Tensor,
    iters: int,
    delta: float = 1.5,
    prior: Prior | None = None,
) -> tuple[torch.Tensor, torch.Tensor, float]:
    """Huber reprojection cost over every pose but the held ones (`fixed`: the first that
    many, or a mask of the poses) and every point. `prior(T_cw)`, if given, adds whitened
    residuals on the poses alone. Returns the poses, the points and the final cost."""
    moves, column = moving(len(T_cw), fixed)
    m = int(moves.sum())
    free = moves[obs.k]
    col = column[obs.k]
    ii, jj = _schur_pairs(obs, free)
    use_prior = prior is not None and m > 0

    def cost_of(T, X):
        r, c = reprojection(T, X, K, obs)
        extra = float((prior(T) ** 2).sum()) if use_prior else 0.0
        return r, c, _huber(r, c, delta) + extra

    r, c, cost = cost_of(T_cw, X)
    lam = 1e-3
    for _ in range(iters):
        if use_prior:
            r_prior, J_prior = prior.jacobian(T_cw, ~moves)
        H_pp, g_p, H_cp, H_cc, g_c = _normal_equations(T_cw, K, obs, r, c, free, col, m, delta)
        diagonal = H_cc.diagonal(0, 2, 3).diagonal(0, 0, 1).T.reshape(-1)
        if use_prior:
            diagonal = diagonal + (J_prior**2).sum(0)
        while True:
            H_pp_inv = torch.linalg.inv(
                H_pp + lam * H_pp.diagonal(0, 1, 2).diag_embed() + 1e-9 * torch.eye(3)
            )
            S = _reduced(H_cc, H_cp, H_pp_inv, obs.p, col, ii, jj)
            g = g_c.index_add(
                0,
                col[free],
                -(H_cp[free] @ (H_pp_inv[obs.p[free]] @ g_p[obs.p[free], :, None]))[:, :, 0],
            ).reshape(-1)
            if use_prior:
                S = S + J_prior.T @ J_prior
                g = g - J_prior.T @ r_prior
            # Marquardt's damping on the whole diagonal (a pose no feature sees has only the
            # prior's), with a floor for a pose nothing holds.
            S = S + torch.diag(lam * diagonal + 1e-9 * (1 + lam))
            step_c = torch.linalg.solve(S, g).reshape(m, 6) if m else g.reshape(0, 6)
            per_obs = torch.zeros(len(obs.k), 6, dtype=X.dtype)
            per_obs[free] = step_c[col[free]]
            rhs = g_p.index_add(0, obs.p, -(H_cp.transpose(1, 2) @ per_obs[:, :, None])[:, :, 0])
            T_new = T_cw.clone()
            T_new[moves] = pose.exp_se3(step_c) @ T_cw[moves]
            X_new = X + (H_pp_inv @ rhs[:, :, None])[:, :, 0]
            r_new, c_new, new = cost_of(T_new, X_new)
            if new < cost:
                T_cw, X, r, c, cost = T_new, X_new, r_new, c_new, new
                lam = max(lam / 3, 1e-7)
                break
            lam *= 5
            if lam > 1e8:
                return T_cw, X, cost
    return T_cw, X, cost


def moving(n: int, fixed: int | torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Which of `n` poses an adjustment moves, `(n,)` bool, when it holds `fixed` (the first
    that many, or a mask), and each moving pose's block in its system, `(n,)` (-1 before
    the first)."""
    held = fixed.to(torch.bool) if isinstance(fixed, torch.Tensor) else torch.arange(n) < fixed
    moves = ~held
    return moves, torch.cumsum(moves.long(), 0) - 1


def links(obs: Observations, n: int) -> torch.Tensor:
    """`(n - 1,)` how many points each pair of consecutive poses of `n` both see."""
    order = torch.argsort(obs.p * n + obs.k)
    p, k = obs.p[order], obs.k[order]
    both = (p[1:] == p[:-1]) & (k[1:] == k[:-1] + 1)
    return torch.bincount(k[:-1][both], minlength=n - 1)[: n - 1]


@dataclass(frozen=True)
class Prior:
    """Whitened residuals on world-to-camera poses alone, each depending on at most
    `reach` consecutive poses, the first of them `first[i]` for residual `i`: what lets
    its Jacobian be taken in `6 reach` forward passes instead of one per residual."""

    residuals: Callable[[torch.Tensor], torch.Tensor]
    first: torch.Tensor
    reach: int
    group: torch.Tensor | None = None
    """Each residual's kind (`odometry_prior`'s: 0 turns, 1 directions, 2 lengths; -1 none),
    the variance components `variance_factors` estimates."""
    at: torch.Tensor | None = None
    """The poses (path order) it reads of a larger set, `residuals` and `first` being over
    them alone (`on`); None: every pose."""

    def __call__(self, T_cw: torch.Tensor) -> torch.Tensor:
        return self.residuals(T_cw if self.at is None else T_cw[self.at])

    def on(self, at: torch.Tensor) -> Prior:
        """This prior, made on poses `at` (increasing indices) of a larger set, over that
        set: the odometry of the keyframes alone where every frame is adjusted."""
        return dataclasses.replace(self, at=at)

    def weighed(self, factors: torch.Tensor) -> Prior:
        """The same prior with each group's variance multiplied by its `factors[group]`
        (its residuals divided by the root; group -1 as it is)."""
        scale = torch.cat([factors, factors.new_ones(1)])[self.group].rsqrt()
        base = self.residuals
        return dataclasses.replace(self, residuals=lambda T_cw: base(T_cw) * scale)

    def jacobian(
        self, T_cw: torch.Tensor, fixed: int | torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The residuals at `T_cw` and their Jacobian with respect to left increments
        (v, w) of the poses not held (`fixed`, as `bundle_adjust`'s): poses `reach` apart
        share no residual, so one central difference per colour (index mod `reach`) and
        coordinate gives every pose of that colour's columns at once (float64: within 1e-6
        of the exact Jacobian, as `tests/mapper/test_bundle.py` checks against autograd's)."""
        if self.at is not None:  # over the poses it reads, their columns in the whole system
            moves, column = moving(len(T_cw), fixed)
            mine = moves[self.at]
            r, J_at = dataclasses.replace(self, at=None).jacobian(T_cw[self.at], ~mine)
            J = torch.zeros(len(r), 6 * int(moves.sum()), dtype=T_cw.dtype)
            blocks = column[self.at][mine]
            J[:, (blocks[:, None] * 6 + torch.arange(6)).ravel()] = J_at
            return r, J
        n = len(T_cw)
        index = torch.arange(n)
        moves, column = moving(n, fixed)
        r = self(T_cw)
        J = torch.zeros(len(r), 6 * int(moves.sum()), dtype=T_cw.dtype)
        for colour in range(self.reach):
            owner = self.first + (colour - self.first) % self.reach  # the row's pose of it
            valid = (owner < n) & moves[owner.clamp(max=n - 1)]
            for d in range(6):
                direction = torch.zeros(n, 6, dtype=T_cw.dtype)
                direction[(index % self.reach == colour) & moves, d] = 1
                ahead = self(pose.exp_se3(STEP * direction) @ T_cw)
                behind = self(pose.exp_se3(-STEP * direction) @ T_cw)
                out = (ahead - behind) / (2 * STEP)
                J[valid, column[owner[valid]] * 6 + d] = out[valid]
        return r, J


def odometry_prior(
    T_wc: torch.Tensor,
    turn_deg: float,
    direction: float,
    length: float | None = None,
    linked: torch.Tensor | None = None,
    full: int = 1,
    free: torch.Tensor | None = None,
    length_linked: float = 0.0,
    pooled: bool = False,
    unlinked_only: bool = False,
) -> Prior:
    """Whitened residuals (of world-to-camera poses) that keep each step between
    consecutive poses of `T_wc` turning as it did (within `turn_deg`) and moving in its
    direction (unit vectors within `direction` for a step of the median length, in
    proportion to the length for the others: a short step's direction says little): a
    tracker's local motion without its scale.

    With `length`, a step's length relative to the step before is held as well (log of the
    ratio within `length`; lengths softened by a quarter of the median so that turns in
    place count little), as far as features do not link its poses: in full where its two
    poses share no point (`linked`, from `links`), not at all from `full` shared points
    on. Steps that no feature sees then keep their neighbours' scale instead of any. With
    `length_linked` (with or without `length`), every ratio is held at least that loosely,
    the linked ones too.

    Steps `free` (`(n - 1,)` bool, from `slid_start`) are not held at all: the tracked
    motion there is what the adjustment is to undo.

    With `pooled`, the directions are of the turns' variance component (`Prior.group` 0):
    what `adjust`'s `weigh` weighs again, the step as one measurement. With
    `unlinked_only`, turns and directions are held as the lengths are, as far as features
    do not link the step (none with `linked` None)."""
    rel = pose.compose(pose.invert(T_wc[:-1]), T_wc[1:])
    size = rel[:, :3, 3].norm(dim=1, keepdim=True)
    median = size.median().clamp_min(1e-12)
    heading = rel[:, :3, 3] / size.clamp_min(1e-12)
    # The difference of unit vectors in the tracked direction's own axes: its two
    # components across it (the direction's two degrees of freedom) and the one along it,
    # of second order but for a step turned about (which it holds; `Prior.group` -1: not a
    # variance component of its own).
    least = torch.nn.functional.one_hot(heading.abs().argmin(1), 3).to(T_wc.dtype)
    across = torch.nn.functional.normalize(torch.linalg.cross(heading, least), dim=1)
    axes = torch.stack([across, torch.linalg.cross(heading, across), heading], 1)
    weight = size / median / direction
    soft = 0.25 * median

    def log_ratios(step_length: torch.Tensor) -> torch.Tensor:
        log = torch.log(step_length + soft)
        return log[1:] - log[:-1]

    ratios = log_ratios(size.ravel())
    lengths = length is not None or length_linked > 0
    held = torch.ones(len(size), dtype=T_wc.dtype)
    if linked is not None:
        held = (1 - linked.to(T_wc.dtype) / full).clamp_min(0)
    # A ratio joins two steps: held as much as the worse linked of them, so that a stretch
    # no feature sees takes its scale from the steps on either side.
    ratio_weight = torch.maximum(held[1:], held[:-1]) / (length or math.inf)
    if length_linked > 0:
        ratio_weight = ratio_weight.clamp_min(1 / length_linked)
    step_weight = torch.ones(len(size), dtype=T_wc.dtype)
    if free is not None:
        step_weight = (~free).to(T_wc.dtype)
        ratio_weight = ratio_weight * step_weight[1:] * step_weight[:-1]
    if unlinked_only:
        step_weight = step_weight * (held if linked is not None else 0)
    weight = weight * step_weight[:, None]

    def residuals(T_cw: torch.Tensor) -> torch.Tensor:
        step = pose.compose(T_cw[:-1], pose.invert(T_cw[1:]))
        turn = pose.log_so3(rel[:, :3, :3].transpose(1, 2) @ step[:, :3, :3])
        moved = step[:, :3, 3].norm(dim=1, keepdim=True)
        t = step[:, :3, 3] / moved.clamp_min(1e-12)
        turn = turn / math.radians(turn_deg) * step_weight[:, None]
        direction = (axes @ (t - heading)[:, :, None])[:, :, 0] * weight
        parts = [turn.ravel(), direction[:, :2].ravel(), direction[:, 2]]
        if lengths:
            parts.append((log_ratios(moved.ravel()) - ratios) * ratio_weight)
        return torch.cat(parts)

    steps = torch.arange(len(size))
    first = torch.cat([steps.repeat_interleave(3), steps.repeat_interleave(2), steps])
    group = torch.cat(
        [
            torch.zeros(3 * len(size)),
            torch.full((2 * len(size),), 0 if pooled else 1),
            -torch.ones(len(size)),
        ]
    ).long()
    if lengths:
        first = torch.cat([first, steps[:-1]])
        group = torch.cat([group, torch.full((len(size) - 1,), 2)])
    return Prior(residuals, first, 3 if lengths else 2, group)


def prior_for(
    T_wc: torch.Tensor, obs: Observations, cfg: BundleConfig, free: torch.Tensor | None = None
) -> Prior:
    """The odometry prior of `cfg` on the tracked keyframe poses `T_wc` seen by `obs`, none
    on the steps `free`."""
    held = cfg.linked > 0  # 0: every length left to the features
    return odometry_prior(
        T_wc,
        cfg.turn_deg,
        cfg.direction,
        cfg.length if held else None,
        links(obs, len(T_wc)) if held else None,
        cfg.linked if held else 1,
        free=free,
        length_linked=cfg.length_linked,
        pooled=cfg.weigh_steps,
        unlinked_only=not cfg.steps_linked,
    )


def prior_at(
    T_wc: torch.Tensor,
    obs: Observations,
    cfg: BundleConfig,
    at: torch.Tensor,
    free: torch.Tensor | None = None,
) -> Prior:
    """`prior_for` the poses `at` (increasing) of `T_wc` alone, over them all (`Prior.on`):
    the steps from one of them to the next, linked by the points both see; a step is free
    where any step of `free` between them is."""
    where = torch.full((len(T_wc),), -1, dtype=torch.long)
    where[at] = torch.arange(len(at))
    mine = where[obs.k] >= 0
    seen = Observations(where[obs.k[mine]], obs.p[mine], obs.uv[mine], obs.sigma[mine])
    if free is not None:
        free = torch.stack([free[a:b].any() for a, b in zip(at[:-1], at[1:], strict=True)])
    return prior_for(T_wc[at], seen, cfg, free).on(at)


def feature_directions(
    T_wc: torch.Tensor, K: torch.Tensor, obs: Observations, gap: int = SLIDE_GAP
) -> tuple[np.ndarray, np.ndarray]:
    """For each keyframe `k` (poses `T_wc`, path order) from `gap` on: the cosine between
    its tracked direction of motion from keyframe `k - gap` and the direction the essential
    matrix of their shared observations gives (RANSAC, 1 px), and that matrix's inliers;
    `(n,)` each, nan and 0 where there is none (under 30 shared points, or before `gap`)."""
    n = len(T_wc)
    cosine, inliers = np.full(n, np.nan), np.zeros(n, np.int64)
    k_of, p_of, uv = obs.k.numpy(), obs.p.numpy(), obs.uv.numpy()
    Kn = K.numpy()
    for k in range(gap, n):
        a = k - gap
        _, at_a, at_k = np.intersect1d(
            p_of[k_of == a], p_of[k_of == k], assume_unique=True, return_indices=True
        )
        if len(at_a) < 30:
            continue
        x_a, x_k = uv[k_of == a][at_a], uv[k_of == k][at_k]
        E, mask = cv2.findEssentialMat(x_a, x_k, Kn, cv2.RANSAC, 0.999, 1.0)
        if E is None or E.shape != (3, 3):
            continue
        inliers[k], R, t, _ = cv2.recoverPose(E, x_a, x_k, Kn, mask=mask)
        seen = -R.T @ t.ravel()  # keyframe k's centre in keyframe a's camera
        moved = (pose.invert(T_wc[a]) @ T_wc[k])[:3, 3].numpy()
        norms = np.linalg.norm(seen) * np.linalg.norm(moved)
        if norms > 0:
            cosine[k] = float(seen @ moved) / norms
    return cosine, inliers


def pointing_against(cosine: np.ndarray, inliers: np.ndarray) -> np.ndarray:
    """`(n,)` bool: the keyframes whose essential matrix (`feature_directions`, of
    `SLIDE_INLIERS` inliers or more) points against the tracked motion."""
    return (inliers >= SLIDE_INLIERS) & (np.nan_to_num(cosine, nan=1.0) < 0)


def slides(cosine: np.ndarray, inliers: np.ndarray) -> list[tuple[int, int]]:
    """The stretches `(first, last)` of keyframes where the features contradict the tracked
    motion (`feature_directions`): at least `SLIDE_LEAST` of `SLIDE_WINDOW` consecutive
    keyframes whose essential matrix of `SLIDE_INLIERS` inliers or more points against it
    (negative cosine), reaching over the keyframes next to them whose matrix does not
    clearly confirm the tracked motion (`SLIDE_CONFIRMED`; room5 seed 0: keyframes 84-92
    about the five of 93-98), and to the path's end where fewer than `SLIDE_WINDOW`
    keyframes are left after it (too few to show that the slide ended)."""
    against = pointing_against(cosine, inliers)
    marked = np.zeros(len(against), bool)
    for start in range(max(len(against) - SLIDE_WINDOW + 1, 0)):
        window = against[start : start + SLIDE_WINDOW]
        if window.sum() >= SLIDE_LEAST:
            first, last = np.flatnonzero(window)[[0, -1]]
            marked[start + first : start + last + 1] = True
    # A slide reaches as far as the features do not clearly confirm the tracked motion,
    # and to the path's end where too few keyframes are left to show that it ended.
    doubtful = np.nan_to_num(cosine, nan=0.0) < SLIDE_CONFIRMED
    edges = np.flatnonzero(np.diff(np.concatenate([[0], marked.astype(np.int8), [0]])))
    stretches = []
    for first, end in zip(edges[::2], edges[1::2], strict=True):
        last = end - 1
        while first > 0 and doubtful[first - 1]:
            first -= 1
        while last + 1 < len(cosine) and doubtful[last + 1]:
            last += 1
        if len(cosine) - 1 - last < SLIDE_WINDOW:
            last = len(cosine) - 1
        if stretches and first <= stretches[-1][1] + 1:
            first, before = stretches.pop()
            last = max(last, before)
        stretches.append((int(first), int(last)))
    return stretches


def slid_start(
    T_wc: torch.Tensor, frames: list[int], stretches: list[tuple[int, int]], gap: int = SLIDE_GAP
) -> tuple[torch.Tensor, torch.Tensor]:
    """An adjustment's start with each slid stretch `(first, last)` (`slides`) followed
    from the motion before it, and the steps the prior is to leave free.

    The features say a stretch has slid from keyframe `first - gap` on (their matrices
    compare keyframes `gap` apart), so from there on its keyframes continue the motion of
    the two steps before, per frame (`frames`: each keyframe's frame index), and the
    keyframes after it follow its last rigidly. The slid motion lies in another minimum of
    the reprojection cost than the true one, which the adjustment does not cross from the
    tracked poses even with no prior on the slid steps; from the motion before the slide
    it reaches the true one (docs/results.md, session 59). Returns the start
    `(n, 4, 4)` and `(n - 1,)` bool, the steps about the slid stretches (a stretch whose
    motion before is unknown, too near the path's start, is left as it is)."""
    start = T_wc.clone()
    free = torch.zeros(len(T_wc) - 1, dtype=torch.bool)
    for first, last in stretches:
        trusted = first - gap
        if trusted < 2:
            continue
        before = trusted - 2
        twist = pose.log_se3(pose.invert(start[before]) @ start[trusted])
        twist = twist / (frames[trusted] - frames[before])
        for k in range(trusted + 1, last + 1):
            start[k] = start[trusted] @ pose.exp_se3(twist * (frames[k] - frames[trusted]))
        follow = start[last] @ pose.invert(T_wc[last])
        start[last + 1 :] = follow @ T_wc[last + 1 :]
        free[trusted:last] = True
    return start, free


@dataclass(frozen=True)
class SlideCheck:
    """What `slide_checked` found."""

    start: torch.Tensor
    """`(n, 4, 4)` the adjustment's start: the tracked poses, slid stretches followed from
    the motion before them (`slid_start`)."""
    free: torch.Tensor | None
    """`(n - 1,)` bool, the steps the prior leaves free; None where no stretch is."""
    stretches: list[tuple[int, int]]
    cosine: np.ndarray
    inliers: np.ndarray
    """`feature_directions`' figures."""


def slide_checked(
    T_wc: torch.Tensor,
    K: torch.Tensor,
    tracks: FeatureTracks,
    flow: FlowTracks | None,
    frames: list[int],
    cfg: BundleConfig,
) -> SlideCheck:
    """Keyframes `frames` (poses `T_wc`) checked for slides (`slides`) and the
    adjustment's start and free steps about them. The check reads the flow's tracks at
    every keyframe, whatever `cfg.flow_near`: where ORB finds few corners (room5's last
    turn) the flow's corners are most of what sees the motion."""
    obs = observed(tracks, flow, frames, dataclasses.replace(cfg, flow_near=-1))
    cosine, inliers = feature_directions(T_wc, K, obs)
    stretches = slides(cosine, inliers)
    if not stretches:
        return SlideCheck(T_wc, None, [], cosine, inliers)
    start, free = slid_start(T_wc, frames, stretches)
    return SlideCheck(start, free, stretches, cosine, inliers)


def inliers(T_cw: torch.Tensor, K: torch.Tensor, obs: Observations, limit: float) -> torch.Tensor:
    """Which observations reproject within `limit` (pixels of their level) in front of their
    camera, their points triangulated at `T_cw`, and not at infinity."""
    X = triangulate(T_cw, K, obs)
    r, c = reprojection(T_cw, X, K, obs)
    # Points at infinity (the rays parallel) place nothing.
    far = (X.norm(dim=1) > 1e3 * X.norm(dim=1).median())[obs.p]
    return (r.norm(dim=1) < limit) & (c[:, 2] > 1e-3) & ~far


def judged(T_cw: torch.Tensor, K: torch.Tensor, obs: Observations, limit: float) -> Observations:
    """The observations of the points whose every observation reprojects within `limit`
    (pixels of its level) in front of its camera, triangulated at `T_cw`."""
    return obs.select(inliers(T_cw, K, obs, limit))


@dataclass(frozen=True)
class Adjusted:
    """What `adjust` did."""

    T_wc: torch.Tensor
    """`(n, 4, 4)` float64 the adjusted poses, camera to world."""
    points: int
    observations: int
    cost: float
    """The final cost (px^2 of the observations' levels, Huber, plus the prior's)."""
    guided: int = 0
    """Observations that guided matching added (`adjust_tracks`)."""
    held: int = 0
    """The first of the two consecutive poses held (`adjust`'s `gauge`), in path order."""
    factors: tuple[float, ...] = ()
    """With `adjust`'s `weigh`: each prior group's variance factor over all rounds (what
    its standard errors were multiplied by, squared; 1 for the groups not `WEIGHED`)."""
    reprojection: float = 0.0
    """With `weigh`: the reprojection errors' standard error at the last round (pixels of
    their levels, per coordinate), what the factors are relative to."""

    def turns(self, turn_deg: float) -> tuple[float, float]:
        """With `weigh`: what the turns' standard error was multiplied by, and the turn
        error (degrees per axis) that it allows for these reprojection errors, from the
        configured `turn_deg`."""
        root = math.sqrt(self.factors[0])
        return root, turn_deg * root * self.reprojection


PRIOR_GROUPS = ("turns", "directions", "lengths")
"""`odometry_prior`'s groups of residuals, by their `Prior.group`."""
WEIGHED = ("turns",)
"""The prior's groups (`PRIOR_GROUPS`) that `adjust`'s `weigh` weighs again: the turns.
Weighed as well, the directions (x 9-19 on their standard error) take room3 from 1.81 to
1.26 cm and room5 from 4.86 to 1.57, but room0 from 0.94 to 1.05 and 7-Scenes from 4.47 to
4.70; the turns alone gain on all four (Intel, 3 seeds; docs/results.md, session 63). The
factors are relative to the features, not the truth's: on room0 the weighed turns allow
0.10-0.15 degrees per axis, about twice the turn errors the tracked steps make against the
truth (median angle 0.09-0.11 degrees); the features' errors are not independent, so
their reprojection errors understate them. With `BundleConfig.weigh_steps` the directions
are of the turns' group (`odometry_prior`'s `pooled`): one factor for the step, whose mean
gains on all four on the AMD machine (session 64; a factor of their own, on the Intel one,
cost room0 and 7-Scenes, session 63: not a paired comparison)."""


def variance_factors(
    T_cw: torch.Tensor,
    X: torch.Tensor,
    K: torch.Tensor,
    obs: Observations,
    fixed: int | torch.Tensor,
    prior: Prior,
    delta: float = 1.5,
) -> tuple[torch.Tensor, float]:
    """Variance component estimation (Foerstner's) at an adjustment's end: by how much each
    of the prior's groups (`Prior.group`) is held too tightly, relative to the reprojection
    errors, as the factor on its variance; and the reprojection errors' variance (px^2 of
    their levels, per coordinate). Each group's whitened square sum over its redundancy (its
    rows less their share in fixing the poses, from the reduced camera system) against the
    observations' Huber-weighted square sum over theirs (their rows less the unknowns the
    prior does not fix). Rows that no moving pose enters are left out; a group with none
    gets 1."""
    moves, column = moving(len(T_cw), fixed)
    m = int(moves.sum())
    free, col = moves[obs.k], column[obs.k]
    ii, jj = _schur_pairs(obs, free)
    r, c = reprojection(T_cw, X, K, obs)
    H_pp, _, H_cp, H_cc, _ = _normal_equations(T_cw, K, obs, r, c, free, col, m, delta)
    H_pp_inv = torch.linalg.inv(H_pp + 1e-9 * torch.eye(3))
    r_prior, J_prior = prior.jacobian(T_cw, ~moves)
    S = _reduced(H_cc, H_cp, H_pp_inv, obs.p, col, ii, jj) + J_prior.T @ J_prior
    share = (J_prior * torch.linalg.solve(S, J_prior.T).T).sum(1)
    norm = r.norm(dim=1)
    huber = torch.where(norm <= delta, norm**2, delta * norm)
    redundancy = 2 * len(obs.k) - 6 * m - 3 * obs.points + float(share.sum())
    observed = float(huber.sum()) / max(redundancy, 1.0)
    group = prior.group if prior.group is not None else torch.zeros(len(r_prior), dtype=torch.long)
    used = (J_prior.abs().sum(1) > 0) & (group >= 0)
    factors = torch.ones(int(group.max()) + 1, dtype=T_cw.dtype)
    for g in range(len(factors)):
        rows = used & (group == g)
        if bool(rows.any()):
            own = float((r_prior[rows] ** 2).sum()) / float((1 - share[rows]).sum().clamp_min(1e-9))
            factors[g] = own / observed
    return factors, observed


def adjust(
    T_wc: torch.Tensor,
    K: torch.Tensor,
    obs: Observations,
    outlier: float,
    iters: int,
    prior: Prior | None,
    more: Callable[[torch.Tensor], Observations] | None = None,
    gauge: Literal["first", "linked"] = "first",
    free: torch.Tensor | None = None,
    weigh: int = 0,
) -> Adjusted:
    """Poses `T_wc` (float64, path order) adjusted on `obs`, two consecutive poses held
    (`gauge`: the first two, or the pair sharing the most points, not across a step `free`
    of the prior: a guess): outliers judged at the
    poses themselves, loosely first (3 `outlier`) and at `outlier` after a first pass of
    half the iterations. `more(T_cw)`, if given, replaces `obs` for the second pass with
    observations found at the first pass's poses (guided matching)."""
    T_cw = pose.invert(T_wc)
    loose = judged(T_cw, K, obs, 3 * outlier)
    held = held_pair(loose, len(T_wc), gauge, free)
    X = triangulate(T_cw, K, loose)
    _, X, _ = bundle_adjust(T_cw, X, K, loose, len(T_cw), 20)
    T_first, _, _ = bundle_adjust(T_cw, X, K, loose, held, iters // 2, prior=prior)
    if more is not None:
        obs = more(T_first)
    tight = judged(T_first, K, obs, outlier)
    X_first = triangulate(T_first, K, tight)
    T_ba, X, cost = bundle_adjust(T_first, X_first, K, tight, held, iters - iters // 2, prior=prior)
    total, observed = None, 0.0
    for _ in range(weigh if prior is not None and prior.group is not None else 0):
        factors, observed = variance_factors(T_ba, X, K, tight, held, prior)
        kept = [name not in WEIGHED for name in PRIOR_GROUPS[: len(factors)]]
        factors[torch.tensor(kept)] = 1  # their standard errors as configured
        total = factors if total is None else total * factors
        prior = prior.weighed(factors)
        T_ba, X, cost = bundle_adjust(
            T_first, X_first, K, tight, held, iters - iters // 2, prior=prior
        )
    first = int(torch.nonzero(held)[0])
    return Adjusted(
        pose.invert(T_ba),
        tight.points,
        len(tight.k),
        cost,
        held=first,
        factors=() if total is None else tuple(total.tolist()),
        reprojection=math.sqrt(observed),
    )


def held_pair(
    obs: Observations,
    n: int,
    gauge: Literal["first", "linked"],
    free: torch.Tensor | None = None,
) -> torch.Tensor:
    """`(n,)` bool: the two consecutive poses an adjustment holds (`adjust`'s `gauge`), the
    best-linked pair not across a step `free` (`(n - 1,)` bool)."""
    first = 0
    if gauge == "linked" and n > 2:
        shared = links(obs, n)
        if free is not None:
            shared = shared.masked_fill(free, -1)
        first = int(torch.argmax(shared))
    elif gauge not in GAUGES:
        raise ValueError(f"bundle.gauge must be first or linked, got {gauge!r}")
    held = torch.zeros(n, dtype=torch.bool)
    held[first : first + 2] = True
    return held


def observed(
    tracks: FeatureTracks,
    flow: FlowTracks | None,
    indices: list[int],
    cfg: BundleConfig,
) -> Observations:
    """The ORB tracks and the flow's (`flow`, if any) seen by `cfg.views` of keyframes
    `indices`, one set of points (`with_flow`)."""
    return with_flow(tracks.observations(indices, cfg.views), flow, indices, cfg)


def with_flow(
    obs: Observations, flow: FlowTracks | None, indices: list[int], cfg: BundleConfig
) -> Observations:
    """The ORB tracks `obs` of keyframes `indices` and the flow's (`flow`, if any) seen by
    `cfg.views` of them, numbered after them; with `cfg.flow_near`, the flow's observations
    only at the keyframes within that many of a step that fewer than `cfg.linked` ORB
    points link."""
    if flow is None:
        return obs
    followed = flow.observations(indices, cfg.views)
    if cfg.flow_near < 0:
        return obs.cat(followed)
    near = torch.zeros(len(indices), dtype=torch.bool)
    for step in torch.nonzero(links(obs, len(indices)) < cfg.linked)[:, 0].tolist():
        near[max(0, step - cfg.flow_near) : step + 2 + cfg.flow_near] = True
    keep = near[followed.k]
    seen = torch.bincount(followed.p[keep], minlength=followed.points)
    keep &= (seen >= cfg.views)[followed.p]
    return obs.cat(followed.rows(keep))


def adjust_tracks(
    tracks: FeatureTracks,
    indices: list[int],
    T_wc: torch.Tensor,
    K: torch.Tensor,
    cfg: BundleConfig,
    prior: Prior | None,
    flow: FlowTracks | None = None,
    free: torch.Tensor | None = None,
) -> Adjusted:
    """Keyframes `indices` (poses `T_wc`, float64, path order) adjusted on their tracks seen
    by `cfg.views` of them (`adjust`; `free`: the steps the prior leaves free, not held
    by the gauge), the flow's too if given; with `cfg.guided`, the second
    pass on the ORB tracks carried at the first pass's poses to every keyframe that sees them
    (`FeatureTracks.guide`). A second adjustment from the first one's end instead lands
    elsewhere (room0 seed 1: 1.25 -> 2.52 cm with no new observation; docs/results.md)."""
    obs = observed(tracks, flow, indices, cfg)
    if not cfg.guided:
        return adjust(
            T_wc, K, obs, cfg.outlier, cfg.iters, prior, gauge=cfg.gauge, free=free, weigh=cfg.weigh
        )
    linked = 0

    def guided(T_cw: torch.Tensor) -> Observations:
        nonlocal linked
        linked = tracks.guide(indices, T_cw, cfg.views, cfg.outlier)
        return observed(tracks, flow, indices, cfg)

    result = adjust(T_wc, K, obs, cfg.outlier, cfg.iters, prior, guided, cfg.gauge, free, cfg.weigh)
    return dataclasses.replace(result, guided=linked)

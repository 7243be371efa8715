"""Loop closure over keyframes: place recognition, geometric check, Sim(3) pose graph.

When the camera comes back to a place it mapped long ago, the keyframe it makes there and an
old keyframe see the same surfaces, but drift (scale most of all, in a monocular system) has
put the two apart. Closing the loop:

1. Place recognition: every keyframe keeps its ORB features (`describe`); a new keyframe's
   descriptors are matched (Hamming, ratio test) against every keyframe at least `min_gap`
   frames older. Brute force is cheap at this scale (a few hundred keyframes of <= 1000
   features: about 1 ms per pair on one core), so no vocabulary has to be trained and shipped.
2. Geometric check, against the map: when a keyframe is described, the map's depth at its
   features is stored with it (the map of its time: a place the camera later comes back to
   with drifted poses gets remapped). PnP with RANSAC places the new keyframe against the old
   one's matched features at that depth (in the old place's scale), its inliers spread over
   `LoopConfig.min_area` of the new image at least; the tracker's direct
   solve then aligns the new image to the old keyframe's features from that pose (the dense
   check: a pose that does not align photometrically is no loop, one that does is refined);
   the new keyframe's stored depth against the depth that pose predicts gives the scale
   between the two places. The result is the measured Sim(3) of the new keyframe in the old
   one's frame, kept only within `MAX_TURN`, `MAX_SCALE` and `MAX_DRIFT` of the poses.
3. Correction: a Sim(3) pose graph over all keyframes (edges between consecutive keyframes
   from their current poses, plus every loop found so far) solved by Levenberg-Marquardt
   (`mapper/posegraph.py`); each keyframe moves by its node's change, the frames anchored to
   it follow (their offsets scaled with it), and the map is refitted to the corrected poses
   (`BackEnd`).

A loop whose measurement already agrees with the current poses (within `LoopConfig.agree`)
changes nothing: returning to a well-mapped place keeps matching. One that does not is closed
only once the next keyframe confirms it (`LoopConfig.confirm`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from dimslam.common.geometry import pose, sim3
from dimslam.common.geometry.camera import Camera
from dimslam.common.map.render import RenderConfig, render_pixels
from dimslam.common.optim.window import FrameState, TrackingLost
from dimslam.common.options import option
from dimslam.mapper.bundle import RATIO, grey_image
from dimslam.mapper.posegraph import Edge, PoseGraphResult, odometry_edges, solve_pose_graph
from dimslam.tracker.direct import DirectTracker
from dimslam.tracker.tracker import TrackerConfig

log = logging.getLogger(__name__)

MIN_OPACITY = 0.5
"""Map depth is trusted where the rendered ray's opacity is at least this."""
MAX_TURN = math.radians(30.0)
MAX_SCALE = 2.5
MAX_DRIFT = 0.5
"""A loop may correct the heading by at most `MAX_TURN` and the scale by a factor of at most
`MAX_SCALE`: drift over a loop turned the heading 5-20 degrees on the built-in scene's loop
(cpu preset), and the scale may drift by 2 (room3's did), while false loops on its tiled
textures (`dimslam synth --path loop`, 160 px) were mostly off by 45-160 degrees; the rest
fail the confirmation. Nor may it move a keyframe by more than `MAX_DRIFT` times the path
from the old keyframe to it (plus 5 % of the gauge depth)."""


DepthFn = Callable[[FrameState, np.ndarray], np.ndarray]
"""`depth(frame, uv)`: `(n,)` float64 depth at `(n, 2)` pixels of a frame, nan where unknown."""


def map_depth(field, camera: Camera, render_cfg: RenderConfig) -> DepthFn:
    """The map's rendered depth, nan where the ray's opacity is under `MIN_OPACITY`."""

    def depth(frame: FrameState, uv: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            out = render_pixels(
                field,
                camera,
                torch.from_numpy(uv).float().to(frame.T_wc.device),
                frame.T_wc,
                render_cfg,
                with_color=False,
            )
        d = out.depth.double().cpu().numpy()
        d[out.opacity.cpu().numpy() < MIN_OPACITY] = np.nan
        return d

    return depth


@dataclass(frozen=True)
class LoopConfig:
    """Loop closure (mapper process, on keyframes)."""

    enabled: bool = option(True, "Detect loops among keyframes and correct poses and map.")
    min_gap: int = option(
        150,
        "Frames between a new keyframe and the keyframes it may close a loop with: a loop is a "
        "return after a long way (at 60, keyframes 60 frames apart on the built-in loop were "
        "closed on poor measurements: 48 cm ATE against 22 at 150, docs/results.md).",
    )
    features: int = option(800, "ORB features per keyframe.")
    candidates: int = option(3, "Old keyframes with the most matches that are checked.")
    min_inliers: int = option(30, "PnP inliers a loop needs.")
    pixel_error: float = option(
        2.0, "PnP inlier threshold in pixels at 320 px width (scaled with the width)."
    )
    min_area: float = option(
        0.06,
        "Least share of the new keyframe's image that the convex hull of its PnP inliers "
        "covers: inliers in a sliver of the image leave the pose ill-posed (room5 seeds 0 "
        "and 1: 0.02-0.05, turns measured 8-22 degrees off the truth; true loops on 7-Scenes "
        "and the built-in loop: 0.067-0.44).",
    )
    confirm: float = option(
        0.05,
        "A loop that moves poses is closed only when the next keyframe finds one that moves "
        "them the same way, within this (units as `agree`).",
    )
    agree: float = option(
        0.05,
        "A loop changes nothing when its measurement is within this of the current poses "
        "(scale and translation as a share of the gauge depth; rotation in radians).",
    )
    max_residual: float = option(
        0.1,
        "The dense check's limit on the robust residual of the new image against the old "
        "keyframe's features (as the tracker's `lost_residual`).",
    )
    min_share: float = option(
        0.3,
        "The dense check's least share of features within the Huber threshold (the "
        "tracker's `min_inliers`).",
    )
    refit_iters: int = option(
        60,
        "Map iterations, poses fixed, after a correction: windows of 20 about the keyframes "
        "that moved most.",
    )


@dataclass
class KeyframeCode:
    """What place recognition keeps of a keyframe."""

    index: int
    points: np.ndarray
    """`(n, 2)` float32 pixel coordinates of the features."""
    descriptors: np.ndarray | None
    """`(n, 32)` uint8 ORB descriptors (None when the image has no features)."""
    depth: np.ndarray
    """`(n,)` float64 the map's depth at the features when the keyframe was described (nan
    where unknown): the map a keyframe was mapped with, not what later rounds made of that
    place (a camera that comes back with drifted poses remaps it)."""


@dataclass(frozen=True)
class Loop:
    """A verified loop: keyframe `new` seen from keyframe `old`."""

    new: int
    old: int
    S_old_new: torch.Tensor
    """`(4, 4)` float64 Sim(3): coordinates in `new`'s camera frame (its map's units) to
    `old`'s camera frame."""
    inliers: int
    matches: int
    error: tuple[float, float, float]
    """How far the measurement was from the poses before correction: (translation / gauge,
    rotation rad, |log scale|)."""
    correction: torch.Tensor
    """`(4, 4)` float64 world Sim(3) that would move `new` where the loop measured it."""


def describe(index: int, rgb: torch.Tensor, features: int) -> KeyframeCode:
    """ORB features of a keyframe's `(H, W, 3)` image in [0, 1] (depth unknown)."""
    grey = grey_image(rgb)
    patch = int(np.clip(grey.shape[1] // 10, 11, 31))
    orb = cv2.ORB_create(
        nfeatures=features, nlevels=4, edgeThreshold=patch, patchSize=patch, fastThreshold=10
    )
    keypoints, descriptors = orb.detectAndCompute(grey, None)
    points = np.array([k.pt for k in keypoints], dtype=np.float32).reshape(-1, 2)
    return KeyframeCode(index, points, descriptors, np.full(len(points), np.nan))


def match(a: KeyframeCode, b: KeyframeCode) -> tuple[np.ndarray, np.ndarray]:
    """Ratio-test matches of `a`'s features in `b`: `(ia, ib)` index arrays."""
    if a.descriptors is None or b.descriptors is None or len(b.descriptors) < 2:
        return np.zeros(0, int), np.zeros(0, int)
    pairs = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(a.descriptors, b.descriptors, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < RATIO * p[1].distance]
    return np.array([m.queryIdx for m in good], int), np.array([m.trainIdx for m in good], int)


def covered(uv: np.ndarray, camera: Camera) -> float:
    """The share of the image inside the convex hull of `(n, 2)` pixels."""
    hull = cv2.convexHull(np.ascontiguousarray(uv, dtype=np.float32))
    return float(cv2.contourArea(hull)) / (camera.width * camera.height)


class LoopCloser:
    """Keyframe codes, loop detection and the pose graph that closes loops."""

    def __init__(
        self,
        cfg: LoopConfig,
        camera: Camera,
        render_cfg: RenderConfig,
        tracker_cfg: TrackerConfig,
        gauge_depth: float,
        device: torch.device,
    ) -> None:
        self.cfg = cfg
        self.camera = camera
        self.gauge = gauge_depth
        # The dense check: the tracker's own solve, the new keyframe against the old one's
        # points (its thresholds decide whether the two images align). Its own random stream:
        # a run in which no loop is found draws the same pixels as one without loop closure.
        generator = torch.Generator(device).manual_seed(0)
        limits = dataclasses.replace(
            tracker_cfg, lost_residual=cfg.max_residual, min_inliers=cfg.min_share
        )
        self.aligner = DirectTracker(limits, render_cfg, camera, generator)
        self.codes: dict[int, KeyframeCode] = {}
        self.loops: list[Loop] = []
        self.last: Loop | None = None  # what the previous keyframe found, to be confirmed

    def add(self, frame: FrameState, depth: DepthFn) -> KeyframeCode | None:
        """Describe a keyframe once, with the map's `depth` at its features (call it when the
        keyframe has just been mapped); its code, or None without an image."""
        code = self.codes.get(frame.index)
        if code is None and frame.rgb is not None:
            code = describe(frame.index, frame.rgb, self.cfg.features)
            if len(code.points):
                code.depth = depth(frame, code.points)
            self.codes[frame.index] = code
        return code

    def detect(self, new: FrameState, keyframes: list[FrameState]) -> Loop | None:
        """The best verified loop from keyframe `new` (described, and the keyframe after the
        one this was last called with) to an old keyframe, or None.

        A loop that would move poses is returned only once confirmed: the previous keyframe
        found one whose correction was the same within `confirm`. One that agrees with the
        poses is returned at once (it moves nothing).
        """
        found = self._find(new, keyframes)
        last, self.last = self.last, found
        if found is None or self.agrees(found):
            return found
        if last is None or max(self._disagreement(last.correction, found.correction)) > (
            self.cfg.confirm
        ):
            log.info(
                "loop %d -> %d: waiting for the next keyframe to confirm", new.index, found.old
            )
            return None
        self.last = None  # the correction changes the poses the next ones are checked on
        return found

    def _find(self, new: FrameState, keyframes: list[FrameState]) -> Loop | None:
        """The verified loop with the most PnP inliers from `new`, or None."""
        code = self.codes.get(new.index)
        if code is None or code.descriptors is None:
            return None
        # Drift is at most the path: a loop may not move `new` farther than the path from
        # the old keyframe to it (as estimated) times `MAX_DRIFT`.
        position = {kf.index: kf.T_wc[:3, 3].double().cpu() for kf in keyframes}
        steps = sorted(position)
        travelled = {steps[0]: 0.0}
        for a, b in zip(steps, steps[1:], strict=False):
            travelled[b] = travelled[a] + float((position[b] - position[a]).norm())
        ranked = []
        for old in keyframes:
            if old.index > new.index - self.cfg.min_gap or old.index not in self.codes:
                continue
            ia, ib = match(code, self.codes[old.index])
            if len(ia) >= self.cfg.min_inliers:
                ranked.append((len(ia), old, ia, ib))
        ranked.sort(key=lambda r: -r[0])
        best = None
        for count, old, ia, ib in ranked[: self.cfg.candidates]:
            loop = self._verify(new, old, code, self.codes[old.index], ia, ib)
            path = travelled.get(new.index, math.inf) - travelled.get(old.index, 0.0)
            if loop is not None and loop.error[0] * self.gauge > MAX_DRIFT * path + 0.05 * (
                self.gauge
            ):
                log.info(
                    "loop %d -> %d: moves %.2f, more than %.0f %% of the %.2f path between",
                    new.index,
                    old.index,
                    loop.error[0] * self.gauge,
                    100 * MAX_DRIFT,
                    path,
                )
                loop = None
            if loop is not None and (best is None or loop.inliers > best.inliers):
                best = dataclasses.replace(loop, matches=count)
        return best

    def _verify(
        self,
        new: FrameState,
        old: FrameState,
        code_new: KeyframeCode,
        code_old: KeyframeCode,
        ia: np.ndarray,
        ib: np.ndarray,
    ) -> Loop | None:
        """PnP of `new`'s matched features against `old`'s lifted by their stored depth, the
        dense check, then the scale."""
        uv_new, uv_old, d_old = code_new.points[ia], code_old.points[ib], code_old.depth[ib]
        ok = np.isfinite(d_old) & (d_old > 0)
        if ok.sum() < self.cfg.min_inliers:
            return None
        K = self.camera.K
        rays = np.c_[uv_old[ok], np.ones(ok.sum())] @ np.linalg.inv(K).T
        X_old = rays * d_old[ok, None]
        threshold = self.cfg.pixel_error * self.camera.width / 320
        found, rvec, tvec, inliers = cv2.solvePnPRansac(
            X_old,
            uv_new[ok].astype(np.float64),
            K,
            None,
            iterationsCount=300,
            reprojectionError=threshold,
            confidence=0.999,
            flags=cv2.SOLVEPNP_EPNP,
        )
        if not found or inliers is None or len(inliers) < self.cfg.min_inliers:
            return None
        inliers = inliers.ravel()
        uv_inliers = uv_new[ok][inliers].astype(np.float64)
        area = covered(uv_inliers, self.camera)
        if area < self.cfg.min_area:
            log.info(
                "loop %d -> %d: PnP inliers cover %.1f %% of the image (under %.1f %%)",
                new.index,
                old.index,
                100 * area,
                100 * self.cfg.min_area,
            )
            return None
        found, rvec, tvec = cv2.solvePnP(
            X_old[inliers],
            uv_inliers,
            K,
            None,
            rvec,
            tvec,
            True,
            cv2.SOLVEPNP_ITERATIVE,
        )
        if not found:
            return None
        T_old_new = np.eye(4)
        T_old_new[:3, :3] = cv2.Rodrigues(rvec)[0].T
        T_old_new[:3, 3] = -T_old_new[:3, :3] @ tvec.ravel()
        T_old_new = self._align(new, old, T_old_new, code_old)
        if T_old_new is None:
            return None
        T_new_old = np.linalg.inv(T_old_new)
        X_new = X_old[inliers] @ T_new_old[:3, :3].T + T_new_old[:3, 3]
        d_map = code_new.depth[ia][ok][inliers]
        ratio = X_new[:, 2] / d_map
        ratio = ratio[np.isfinite(ratio) & (ratio > 0) & (X_new[:, 2] > 0)]
        if len(ratio) < self.cfg.min_inliers // 2:
            return None
        scale = float(np.median(ratio))
        S_old_new = sim3.from_pose(torch.from_numpy(T_old_new), scale)
        S_old = sim3.from_pose(old.T_wc.double().cpu())
        S_new = sim3.from_pose(new.T_wc.double().cpu())
        error = self._disagreement(S_old_new, sim3.invert(S_old) @ S_new)
        log.info(
            "loop candidate: keyframe %d sees keyframe %d (%d PnP inliers, scale %.3f; "
            "off by %.3f gauge, %.2f deg, scale %.3f)",
            new.index,
            old.index,
            len(inliers),
            scale,
            error[0],
            math.degrees(error[1]),
            math.exp(error[2]),
        )
        if error[1] > MAX_TURN or error[2] > math.log(MAX_SCALE):
            return None
        correction = S_old @ S_old_new @ sim3.invert(S_new)
        return Loop(new.index, old.index, S_old_new, len(inliers), 0, error, correction)

    def _align(
        self, new: FrameState, old: FrameState, T_old_new: np.ndarray, code_old: KeyframeCode
    ) -> np.ndarray | None:
        """The dense check: `new`'s image aligned by the direct tracker's solve, from the PnP
        pose, to `old`'s features at their stored depth; the refined `T_old_new`, or None when
        they do not align."""
        T_wo = old.T_wc.double().cpu().numpy()
        guess = torch.from_numpy(T_wo @ T_old_new).to(new.T_wc)
        probe = FrameState(new.index, new.timestamp, new.rgb, guess, keyframe=True)
        ref = self.aligner.reference(
            old,
            torch.from_numpy(code_old.points).to(new.T_wc.device),
            torch.from_numpy(code_old.depth).float().to(new.T_wc.device),
        )
        try:
            solved = self.aligner.solve(probe, [ref], self.aligner.images(probe))
        except TrackingLost as e:
            log.info("loop %d -> %d: PnP pose does not align densely (%s)", new.index, old.index, e)
            return None
        return np.linalg.inv(T_wo) @ solved.T_wc.double().cpu().numpy()

    def _disagreement(self, a: torch.Tensor, b: torch.Tensor) -> tuple[float, float, float]:
        """How far apart two Sim(3)s are: (translation / gauge, rotation rad, |log scale|)."""
        T, s = sim3.to_pose(sim3.invert(a) @ b)
        angle = float(pose.rotation_angle(T[:3, :3]))
        return float(T[:3, 3].norm()) / self.gauge, angle, abs(math.log(float(s)))

    def agrees(self, loop: Loop) -> bool:
        """Whether the loop's measurement already agrees with the poses it was checked on."""
        return max(loop.error) <= self.cfg.agree

    def correct(self, keyframes: list[FrameState], loop: Loop) -> PoseGraphResult:
        """Record the loop and solve the pose graph over `keyframes` (ordered by index).

        Returns:
            The solve; `nodes[k]` is keyframe k's corrected Sim(3) (world from its camera),
            node 0 fixed.
        """
        self.loops.append(loop)
        nodes = sim3.from_pose(torch.stack([kf.T_wc.double().cpu() for kf in keyframes]))
        position = {kf.index: k for k, kf in enumerate(keyframes)}
        edges = odometry_edges(nodes)
        for held in self.loops:
            if held.new in position and held.old in position:
                edges.append(Edge(position[held.old], position[held.new], held.S_old_new))
        result = solve_pose_graph(nodes, edges, fixed=(0,))
        log.info(
            "pose graph over %d keyframes, %d loops: cost %.3g -> %.3g in %d iterations",
            len(keyframes),
            len(edges) - len(keyframes) + 1,
            result.initial_cost,
            result.final_cost,
            result.iterations,
        )
        return result

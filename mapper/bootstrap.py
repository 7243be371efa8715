"""Starting poses for the initialization from tracked corners (two-view geometry), no map needed.

The initialization optimizes the map and the first frames' poses together, starting from a
plane. When the camera moves fast, the frames start far from their views and the pair settles
on a wrong depth with wrong poses that explain the images almost as well (room3 at stride 2:
frame 0's depth 50 cm off; from the true poses, the same optimization lands within 2 cm).
Corners tracked from image to image do not need a depth to relate two views:

1. Corners (Shi-Tomasi) tracked frame to frame by pyramidal Lucas-Kanade, kept only where the
   backward track returns to within `FB_PX`; new corners are detected where tracks thin out.
2. The pair (0, k) with the most parallax among those sharing `MIN_POINTS` tracks gives the
   essential matrix (RANSAC), the relative pose and the first 3D points.
3. Every frame is placed on those points by PnP (RANSAC, then Levenberg-Marquardt); points
   tracked since an earlier placed frame are triangulated as frames are placed, so that a
   camera that turns away from frame 0's view keeps points to stand on.
4. The scale: frame 0's median point depth becomes `depth` (the map's gauge).

Every step is checked (enough tracks, inliers, parallax, points in front); `bootstrap` returns
None with the reason logged when one fails, and the initialization starts as before.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

log = logging.getLogger(__name__)

CORNERS = 1000
"""Corners detected in frame 0 (and the most tracks kept alive)."""
FB_PX = 1.0
"""A track survives a frame when the backward track returns within this, pixels."""
MIN_POINTS = 40
"""Fewest points an essential matrix, a triangulation or a PnP may stand on."""
MIN_PARALLAX_DEG = 1.0
"""Median angle between the rays of the first points; less is too little baseline."""
PARALLAX_DEG = 4.0
"""Parallax enough: the first pair with this much starts the points (later pairs share
fewer, longer tracks, which are more often wrong)."""
MIN_AGREEING = 0.6
"""Least share of a pair's shared tracks that its essential matrix must explain."""
REPROJ_PX = 2.0
"""RANSAC threshold and the largest reprojection error of a kept point, pixels."""


@dataclass(frozen=True)
class Bootstrap:
    """Poses for the initialization's frames and what they stand on.

    Attributes:
        poses: `(N, 4, 4)` camera-to-world, frame 0 at identity, frame 0's median point depth
            equal to the requested depth.
        pair: the two frames whose essential matrix started the points.
        parallax_deg: median angle between the rays of the pair's points.
        points: 3D points triangulated in all.
        inliers: per frame, the points its PnP kept (the pair's two frames: their points).
    """

    poses: np.ndarray
    pair: tuple[int, int]
    parallax_deg: float
    points: int
    inliers: tuple[int, ...]


def _track(greys: list[np.ndarray]) -> np.ndarray:
    """`(N, P, 2)` corner positions per frame, NaN where a corner is not tracked."""
    n = len(greys)
    rows: list[np.ndarray] = []  # one (N, 2) row per track
    alive: list[int] = []
    lk = {"winSize": (21, 21), "maxLevel": 4}
    h, w = greys[0].shape

    def detect(k: int) -> None:
        mask = np.full(greys[k].shape, 255, np.uint8)
        for i in alive:
            x, y = rows[i][k]
            cv2.circle(mask, (int(x), int(y)), 7, 0, -1)
        found = cv2.goodFeaturesToTrack(
            greys[k], CORNERS - len(alive), 1e-3, 7, mask=mask, blockSize=5
        )
        for p in [] if found is None else found.reshape(-1, 2):
            row = np.full((n, 2), np.nan, np.float32)
            row[k] = p
            alive.append(len(rows))
            rows.append(row)

    detect(0)
    for k in range(1, n):
        if alive:
            prev = np.stack([rows[i][k - 1] for i in alive]).reshape(-1, 1, 2)
            nxt, ok, _ = cv2.calcOpticalFlowPyrLK(greys[k - 1], greys[k], prev, None, **lk)
            back, ok2, _ = cv2.calcOpticalFlowPyrLK(greys[k], greys[k - 1], nxt, None, **lk)
            fb = np.linalg.norm((back - prev).reshape(-1, 2), axis=1)
            p = nxt.reshape(-1, 2)
            inside = (p[:, 0] >= 0) & (p[:, 1] >= 0) & (p[:, 0] < w) & (p[:, 1] < h)
            keep = (ok.ravel() == 1) & (ok2.ravel() == 1) & (fb < FB_PX) & inside
            for i, q, good in zip(alive, p, keep, strict=True):
                if good:
                    rows[i][k] = q
            alive = [i for i, good in zip(alive, keep, strict=True) if good]
        if len(alive) < CORNERS // 2:
            detect(k)
    return np.stack(rows, axis=1) if rows else np.zeros((n, 0, 2), np.float32)


def _project(K: np.ndarray, T_cw: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels and depths of world points `X` `(M, 3)` in the camera `T_cw`."""
    p = X @ T_cw[:3, :3].T + T_cw[:3, 3]
    z = p[:, 2]
    uv = (p[:, :2] / np.where(np.abs(z) > 1e-9, z, 1e-9)[:, None]) * [K[0, 0], K[1, 1]]
    return uv + [K[0, 2], K[1, 2]], z


def _triangulate(
    K: np.ndarray, T_a: np.ndarray, T_b: np.ndarray, uv_a: np.ndarray, uv_b: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """World points seen at `uv_a` from `T_a` and `uv_b` from `T_b` (world-to-camera), and
    which of them lie in front of both within `REPROJ_PX`."""
    uv_a, uv_b = uv_a.astype(np.float64), uv_b.astype(np.float64)
    X = cv2.triangulatePoints(K @ T_a[:3], K @ T_b[:3], uv_a.T.copy(), uv_b.T.copy())
    X = (X[:3] / np.where(np.abs(X[3]) > 1e-12, X[3], 1e-12)).T
    good = np.ones(len(X), bool)
    for T, uv in ((T_a, uv_a), (T_b, uv_b)):
        proj, z = _project(K, T, X)
        good &= (z > 0) & (np.linalg.norm(proj - uv, axis=1) < REPROJ_PX)
    return X, good


def _ray_angles(K: np.ndarray, T_a: np.ndarray, T_b: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Degrees between the rays from the two camera centres to each point."""
    rays = []
    for T in (T_a, T_b):
        centre = -T[:3, :3].T @ T[:3, 3]
        d = X - centre
        rays.append(d / np.linalg.norm(d, axis=1, keepdims=True))
    return np.degrees(np.arccos(np.clip((rays[0] * rays[1]).sum(axis=1), -1.0, 1.0)))


def _pair(K: np.ndarray, tracks: np.ndarray) -> tuple[int, np.ndarray, np.ndarray, float] | None:
    """The frame k that forms the best pair with frame 0: its `T_kw` (frame 0 = world, unit
    baseline), the pair's points `(P, 3)` (NaN where none) and their median parallax."""
    best = None
    for k in range(1, len(tracks)):
        both = np.flatnonzero(~np.isnan(tracks[0, :, 0]) & ~np.isnan(tracks[k, :, 0]))
        if len(both) < MIN_POINTS:
            break  # fewer shared tracks with every later frame
        a, b = tracks[0, both].astype(np.float64), tracks[k, both].astype(np.float64)
        E, mask = cv2.findEssentialMat(a, b, K, cv2.RANSAC, 0.999, REPROJ_PX / 2)
        if (
            E is None
            or E.shape != (3, 3)
            or int(mask.sum()) < max(MIN_POINTS, MIN_AGREEING * len(both))
        ):
            continue
        _, R, t, mask = cv2.recoverPose(E, a, b, K, mask=mask)
        T_kw = np.eye(4)
        T_kw[:3, :3], T_kw[:3, 3] = R, t.ravel()
        X, good = _triangulate(K, np.eye(4), T_kw, a, b)
        good &= mask.ravel() > 0
        if good.sum() < MIN_POINTS:
            continue
        parallax = float(np.median(_ray_angles(K, np.eye(4), T_kw, X[good])))
        if best is None or parallax > best[3]:
            points = np.full((tracks.shape[1], 3), np.nan)
            points[both[good]] = X[good]
            best = (k, T_kw, points, parallax)
        if parallax >= PARALLAX_DEG:
            break
    return best


def bootstrap(rgbs: list[np.ndarray], K: np.ndarray, depth: float) -> Bootstrap | None:
    """Poses for `rgbs` (uint8 `(H, W, 3)`, undistorted, in order) from tracked corners.

    Returns:
        The poses, or None (logged why) when the images do not support them: too few
        corners tracked, too little parallax, a frame without enough points.
    """
    greys = [cv2.cvtColor(np.ascontiguousarray(im), cv2.COLOR_RGB2GRAY) for im in rgbs]
    tracks = _track(greys)
    found = _pair(K, tracks)
    if found is None:
        log.info("no starting poses from corners: no pair with %d points agreeing", MIN_POINTS)
        return None
    k, T_kw, points, parallax = found
    if parallax < MIN_PARALLAX_DEG:
        log.info("no starting poses from corners: %.2f degrees of parallax", parallax)
        return None
    n = len(rgbs)
    T_cw: list[np.ndarray | None] = [None] * n
    T_cw[0], T_cw[k] = np.eye(4), T_kw
    inliers = [0] * n
    inliers[0] = inliers[k] = int(np.isfinite(points[:, 0]).sum())
    for j in sorted(range(1, n), key=lambda j: abs(j - k)):
        if T_cw[j] is not None:
            continue
        seen = np.flatnonzero(np.isfinite(points[:, 0]) & ~np.isnan(tracks[j, :, 0]))
        if len(seen) < MIN_POINTS:
            log.info("no starting poses from corners: frame %d sees %d points", j, len(seen))
            return None
        obj, img = points[seen].astype(np.float64), tracks[j, seen].astype(np.float64)
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            obj, img, K, None, reprojectionError=REPROJ_PX, flags=cv2.SOLVEPNP_EPNP
        )
        if not ok or inl is None or len(inl) < MIN_POINTS:
            log.info("no starting poses from corners: frame %d fits no pose", j)
            return None
        inl = inl.ravel()
        wrong = np.setdiff1d(np.arange(len(seen)), inl)
        tracks[j, seen[wrong]] = np.nan  # slid in this frame: not triangulated from it
        rvec, tvec = cv2.solvePnPRefineLM(obj[inl], img[inl], K, None, rvec, tvec)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
        T_cw[j], inliers[j] = T, len(inl)
        # Tracks this frame shares with a placed frame, without a point yet, become points.
        for i in range(n):
            if T_cw[i] is None or i == j:
                continue
            new = np.isnan(points[:, 0]) & ~np.isnan(tracks[i, :, 0]) & ~np.isnan(tracks[j, :, 0])
            if new.sum() < MIN_POINTS:
                continue
            X, good = _triangulate(K, T_cw[i], T, tracks[i, new], tracks[j, new])
            good &= _ray_angles(K, T_cw[i], T, X) > MIN_PARALLAX_DEG
            points[np.flatnonzero(new)[good]] = X[good]
    in_first = np.isfinite(points[:, 0]) & ~np.isnan(tracks[0, :, 0])
    _, z = _project(K, np.eye(4), points[in_first])
    median = float(np.median(z[z > 0])) if (z > 0).any() else 0.0
    if median <= 0:
        log.info("no starting poses from corners: frame 0 sees no point in front")
        return None
    poses = np.stack([np.linalg.inv(T) for T in T_cw])
    poses[:, :3, 3] *= depth / median
    return Bootstrap(poses, (0, k), parallax, int(np.isfinite(points[:, 0]).sum()), tuple(inliers))

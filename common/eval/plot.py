"""Trajectory plots for people: where did the estimate drift? Drawn with OpenCV only.

One PNG: a top view (the plane of the ground truth's two largest principal directions, equal
aspect) with thin grey segments joining each associated estimate/ground-truth pair, and x, y, z
against time. Never imported by the core modules; matplotlib is deliberately not a dependency.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from dimslam.common.eval.evaluation import associate
from dimslam.common.io.trajectory import Trajectory

log = logging.getLogger(__name__)

WIDTH, HEIGHT = 1600, 900
"""Size of the written image, pixels."""

# BGR. Okabe-Ito blue and vermillion: distinct for the common colour-vision deficiencies.
GT_COLOR = (178, 114, 0)
EST_COLOR = (0, 94, 213)
_ERROR_COLOR = (190, 190, 190)
_GRID_COLOR = (232, 232, 232)
_AXIS_COLOR = (90, 90, 90)
_TEXT_COLOR = (30, 30, 30)
_BACKGROUND = (255, 255, 255)

_FONT = cv2.FONT_HERSHEY_SIMPLEX
_SHIFT = 4  # sub-pixel bits for cv2 drawing: smooth lines for slow, dense trajectories
_MAX_ERROR_SEGMENTS = 300  # beyond this the grey pair segments become a smear


@dataclass(frozen=True)
class _Axes:
    """A plot area: pixels `(x0, y0)-(x1, y1)` showing data `[xmin, xmax] x [ymin, ymax]`."""

    x0: int
    y0: int
    x1: int
    y1: int
    xmin: float
    xmax: float
    ymin: float
    ymax: float

    def to_pixels(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """`(N, 2)` int32 fixed-point pixel coordinates (`_SHIFT` bits) of data points."""
        u = self.x0 + (x - self.xmin) / (self.xmax - self.xmin) * (self.x1 - self.x0)
        v = self.y1 - (y - self.ymin) / (self.ymax - self.ymin) * (self.y1 - self.y0)
        return np.round(np.stack([u, v], -1) * (1 << _SHIFT)).astype(np.int32)


def _nice_ticks(lo: float, hi: float, target: int = 6) -> np.ndarray:
    """Round tick values (1, 2, 5 x 10^k steps) inside `[lo, hi]`."""
    raw = (hi - lo) / max(target, 1)
    magnitude = 10 ** math.floor(math.log10(raw))
    step = next(m * magnitude for m in (1, 2, 5, 10) if m * magnitude >= raw)
    first = math.ceil(lo / step - 1e-9) * step
    ticks = np.arange(first, hi + step * 1e-9, step)
    return np.round(ticks / step) * step  # no -0.0 or 0.30000000000000004


def _format_ticks(ticks: np.ndarray) -> list[str]:
    step = ticks[1] - ticks[0] if len(ticks) > 1 else 1.0
    decimals = max(0, -math.floor(math.log10(step) + 1e-9))
    return [f"{t:.{decimals}f}" for t in ticks]


def _padded_range(values: np.ndarray, pad: float = 0.05, min_span: float = 1e-3) -> tuple:
    lo, hi = float(values.min()), float(values.max())
    span = max(hi - lo, min_span)
    centre = (lo + hi) / 2
    return centre - span * (0.5 + pad), centre + span * (0.5 + pad)


def _text(
    img: np.ndarray,
    text: str,
    org: tuple[int, int],
    scale: float = 0.5,
    anchor: str = "left",
    thickness: int = 1,
) -> None:
    """Text whose baseline starts (`anchor` "left"), is centred on or ends at `org`."""
    (w, _), _ = cv2.getTextSize(text, _FONT, scale, thickness)
    x = org[0] - {"left": 0, "centre": w // 2, "right": w}[anchor]
    cv2.putText(img, text, (x, org[1]), _FONT, scale, _TEXT_COLOR, thickness, cv2.LINE_AA)


def _draw_axes(img: np.ndarray, ax: _Axes, xlabel: str, ylabel: str) -> None:
    """Grid, frame, tick labels and axis labels of one plot area."""
    for t, label in zip(xt := _nice_ticks(ax.xmin, ax.xmax), _format_ticks(xt), strict=True):
        u = int(round(ax.x0 + (t - ax.xmin) / (ax.xmax - ax.xmin) * (ax.x1 - ax.x0)))
        cv2.line(img, (u, ax.y0), (u, ax.y1), _GRID_COLOR, 1)
        cv2.line(img, (u, ax.y1), (u, ax.y1 + 5), _AXIS_COLOR, 1)
        _text(img, label, (u, ax.y1 + 20), 0.45, anchor="centre")
    for t, label in zip(yt := _nice_ticks(ax.ymin, ax.ymax, 5), _format_ticks(yt), strict=True):
        v = int(round(ax.y1 - (t - ax.ymin) / (ax.ymax - ax.ymin) * (ax.y1 - ax.y0)))
        cv2.line(img, (ax.x0, v), (ax.x1, v), _GRID_COLOR, 1)
        cv2.line(img, (ax.x0 - 5, v), (ax.x0, v), _AXIS_COLOR, 1)
        _text(img, label, (ax.x0 - 8, v + 5), 0.45, anchor="right")
    cv2.rectangle(img, (ax.x0, ax.y0), (ax.x1, ax.y1), _AXIS_COLOR, 1)
    if xlabel:
        _text(img, xlabel, ((ax.x0 + ax.x1) // 2, ax.y1 + 42), 0.5, anchor="centre")
    if ylabel:
        # Upright label above the tick labels: rotated Hershey text is hard to read.
        _text(img, ylabel, (ax.x0, ax.y0 - 8), 0.5)


def _polyline(
    img: np.ndarray, ax: _Axes, x: np.ndarray, y: np.ndarray, breaks: np.ndarray, color
) -> None:
    """A line through `(x, y)`, interrupted before each index in `breaks` (gaps in the data)."""
    runs = [run for run in np.split(ax.to_pixels(x, y), breaks) if len(run) > 1]
    if runs:
        cv2.polylines(img, runs, False, color, 2, cv2.LINE_AA, _SHIFT)


def _marker(img: np.ndarray, ax: _Axes, x: float, y: float, color, filled: bool) -> None:
    (u, v) = ax.to_pixels(np.array([x]), np.array([y]))[0]
    radius = 7 << _SHIFT
    cv2.circle(img, (int(u), int(v)), radius, color, -1 if filled else 2, cv2.LINE_AA, _SHIFT)
    if filled:
        cv2.circle(img, (int(u), int(v)), radius, _TEXT_COLOR, 1, cv2.LINE_AA, _SHIFT)


def _top_view_basis(p: np.ndarray) -> np.ndarray:
    """`(2, 3)` rows spanning the plane of `p`'s two largest principal directions.

    Signs are fixed so that each axis' largest component is positive and the view normal
    (u x v) too: a z-up world with a level trajectory is then seen from above, never mirrored.
    """
    if len(p) < 2:
        return np.eye(3)[:2]
    _, _, Vt = np.linalg.svd(p - p.mean(0), full_matrices=True)
    u, n = Vt[0], Vt[2]
    u = u * np.sign(u[np.argmax(np.abs(u))])
    n = n * np.sign(n[np.argmax(np.abs(n))])
    return np.stack([u, np.cross(n, u)])


def _or_zero(values: np.ndarray) -> np.ndarray:
    """`values`, or a single zero row when empty, so that every axis gets a range."""
    return values if len(values) else np.zeros((1, *values.shape[1:]))


def _finite(traj: Trajectory) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Timestamps `(K,)` and positions `(K, 3)` of the finite poses, and where gaps were.

    Returns:
        `(t, p, breaks)`: `breaks` indexes the first pose after each run of non-finite ones,
        so that lines are not drawn across a stretch where tracking was lost.
    """
    ok = np.all(np.isfinite(traj.positions), axis=1) & np.isfinite(traj.timestamps)
    kept = np.flatnonzero(ok)
    breaks = np.flatnonzero(np.diff(kept) > 1) + 1
    return traj.timestamps[ok], traj.positions[ok], breaks


def plot_trajectory(
    path: str | Path, est_aligned: Trajectory, gt: Trajectory, title: str = ""
) -> None:
    """Write a PNG comparing an aligned estimate with the ground truth.

    Left: top view on the plane of the ground truth's two largest principal directions (equal
    aspect; the directions are printed in world coordinates), grey segments joining associated
    poses, filled circle at the ground-truth start, ring at the estimate's start. Right: x, y, z
    against time (seconds since the first timestamp). Non-finite poses are skipped.

    Args:
        path: the PNG to write (parent folders created).
        est_aligned: the estimate already in the ground truth's frame, e.g.
            `metrics.alignment.apply_trajectory(est)`.
        gt: the ground truth.
        title: first line of the image; put the ATE here.

    Raises:
        OSError: if the file cannot be written.
    """
    t_gt, p_gt, breaks_gt = _finite(gt)
    t_est, p_est, breaks_est = _finite(est_aligned)
    img = np.full((HEIGHT, WIDTH, 3), _BACKGROUND, dtype=np.uint8)
    _text(img, title or "trajectory", (30, 38), 0.8, thickness=2)

    # Top view. The panel is square in pixels, so equal aspect means equal data spans.
    basis = _top_view_basis(p_gt if len(p_gt) else p_est)
    q_gt, q_est = p_gt @ basis.T, p_est @ basis.T
    both = _or_zero(np.concatenate([q_gt, q_est]))
    # At least 10 cm across: a camera that barely moves still gets a readable scale.
    (ulo, uhi), (vlo, vhi) = (_padded_range(both[:, i], min_span=0.1) for i in (0, 1))
    half = max(uhi - ulo, vhi - vlo) / 2
    uc, vc = (ulo + uhi) / 2, (vlo + vhi) / 2
    top = _Axes(95, 85, 835, 825, uc - half, uc + half, vc - half, vc + half)
    _draw_axes(img, top, "", "")
    rounded = np.round(basis, 2) + 0.0  # + 0.0 turns -0.0 into 0.0: no "-0.00" on the label
    axis_names = [
        f"{name} = ({b[0]:+.2f}, {b[1]:+.2f}, {b[2]:+.2f})"
        for name, b in zip("uv", rounded, strict=True)
    ]
    _text(
        img, f"top view (m): {axis_names[0]} right, {axis_names[1]} up", (top.x0, top.y1 + 42), 0.5
    )

    if len(t_gt) and len(t_est):
        idx_est, idx_gt = associate(t_est, t_gt)
        keep = np.linspace(0, len(idx_est) - 1, min(len(idx_est), _MAX_ERROR_SEGMENTS)).astype(int)
        for i, j in zip(idx_est[keep], idx_gt[keep], strict=True):
            seg = top.to_pixels(
                np.array([q_est[i, 0], q_gt[j, 0]]), np.array([q_est[i, 1], q_gt[j, 1]])
            )
            cv2.line(img, tuple(seg[0]), tuple(seg[1]), _ERROR_COLOR, 1, cv2.LINE_AA, _SHIFT)
    _polyline(img, top, q_gt[:, 0], q_gt[:, 1], breaks_gt, GT_COLOR)
    _polyline(img, top, q_est[:, 0], q_est[:, 1], breaks_est, EST_COLOR)
    if len(q_gt):
        _marker(img, top, q_gt[0, 0], q_gt[0, 1], GT_COLOR, filled=True)
    if len(q_est):
        _marker(img, top, q_est[0, 0], q_est[0, 1], EST_COLOR, filled=False)
    _legend(img, top.x0 + 12, top.y0 + 12)

    # x, y, z against time, on a shared time axis.
    times = _or_zero(np.concatenate([t_gt, t_est]))
    t0 = float(times.min())
    tlo, thi = 0.0, max(float(times.max()) - t0, 1.0)
    panel_h, gap = 190, 75
    for k, name in enumerate("xyz"):
        y0 = 85 + k * (panel_h + gap)
        values = _or_zero(np.concatenate([p_gt[:, k], p_est[:, k]]))
        ax = _Axes(1000, y0, 1560, y0 + panel_h, tlo, thi, *_padded_range(values, 0.08, 0.02))
        _draw_axes(img, ax, "time (s)" if name == "z" else "", f"{name} (m)")
        _polyline(img, ax, t_gt - t0, p_gt[:, k], breaks_gt, GT_COLOR)
        _polyline(img, ax, t_est - t0, p_est[:, k], breaks_est, EST_COLOR)

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), img):
        raise OSError(f"{path}: cannot write the plot")
    log.info("trajectory plot written to %s", path)


def _legend(img: np.ndarray, x: int, y: int) -> None:
    """The key, in a white box at `(x, y)` (top-left), so it stays readable over the lines."""
    rows = [
        ("line", GT_COLOR, 2, "ground truth"),
        ("line", EST_COLOR, 2, "estimate (aligned)"),
        ("line", _ERROR_COLOR, 1, "error (associated poses)"),
        ("dot", GT_COLOR, -1, "start (ground truth)"),
        ("ring", EST_COLOR, 2, "start (estimate)"),
    ]
    row_h, width = 24, 290
    box = ((x, y), (x + width, y + 12 + row_h * len(rows)))
    cv2.rectangle(img, *box, _BACKGROUND, -1)
    cv2.rectangle(img, *box, _AXIS_COLOR, 1)
    for r, (kind, color, thickness, label) in enumerate(rows):
        cy = y + 18 + r * row_h
        if kind == "line":
            cv2.line(img, (x + 12, cy), (x + 52, cy), color, thickness, cv2.LINE_AA)
        else:
            cv2.circle(img, (x + 32, cy), 7, color, thickness, cv2.LINE_AA)
        if kind == "dot":
            cv2.circle(img, (x + 32, cy), 7, _TEXT_COLOR, 1, cv2.LINE_AA)
        _text(img, label, (x + 64, cy + 5), 0.5)

"""Trajectory plots: a readable PNG of the right size with both trajectories drawn."""

import cv2
import numpy as np
import torch

from dimslam.common.eval.plot import EST_COLOR, GT_COLOR, HEIGHT, WIDTH, plot_trajectory
from dimslam.common.geometry import pose
from dimslam.common.io.trajectory import Trajectory


def circle_trajectory(n: int = 120, drift: float = 0.0) -> Trajectory:
    angle = np.linspace(0, 2 * np.pi, n)
    t = np.stack([np.cos(angle), np.sin(angle), 0.1 * np.sin(3 * angle)], -1)
    t[:, 0] += drift * np.arange(n) / n
    R = pose.exp_so3(torch.from_numpy(np.stack([0 * angle, 0 * angle, angle], -1)))
    return Trajectory(1.0 + np.arange(n) / 30.0, pose.make_pose(R, torch.from_numpy(t)).numpy())


def color_pixels(img: np.ndarray, bgr: tuple[int, int, int], tol: int = 40) -> int:
    return int((np.abs(img.astype(int) - np.array(bgr)).max(axis=-1) <= tol).sum())


def test_plot_shows_both_trajectories(tmp_path):
    path = tmp_path / "sub" / "plot.png"
    plot_trajectory(path, circle_trajectory(drift=0.3), circle_trajectory(), title="ATE 12.3 cm")
    img = cv2.imread(str(path))
    assert img is not None and img.shape == (HEIGHT, WIDTH, 3)
    assert color_pixels(img, GT_COLOR) > 500
    assert color_pixels(img, EST_COLOR) > 500
    assert (img < 250).any(axis=-1).mean() > 0.02  # axes, text, lines: not a blank canvas
    assert (img[:60] < 128).any()  # the title line has text


def test_plot_survives_degenerate_input(tmp_path):
    gt = circle_trajectory()
    poses = gt.poses.copy()
    poses[10:20] = np.nan  # a tracker that lost track for a while
    plot_trajectory(tmp_path / "nan.png", Trajectory(gt.timestamps, poses), gt)
    assert cv2.imread(str(tmp_path / "nan.png")).shape == (HEIGHT, WIDTH, 3)

    # A straight line (no second principal direction), a single pose, an empty estimate.
    line = Trajectory(np.arange(5.0), np.tile(np.eye(4), (5, 1, 1)))
    line.poses[:, 0, 3] = np.arange(5.0)
    single = Trajectory(np.zeros(1), np.eye(4)[None])
    empty = Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
    for k, (est, ref) in enumerate([(line, line), (single, single), (empty, gt)]):
        plot_trajectory(tmp_path / f"{k}.png", est, ref)
        img = cv2.imread(str(tmp_path / f"{k}.png"))
        assert img.shape == (HEIGHT, WIDTH, 3)
    assert color_pixels(img, GT_COLOR) > 500  # the empty estimate still shows the GT

"""The evaluator against an independent closed form (Horn 1987), known RPE values, association
edge cases and clear errors."""

import ast
import math

import numpy as np
import pytest
import torch

from dimslam.common.errors import EvaluationError
from dimslam.common.eval import evaluation
from dimslam.common.eval.evaluation import (
    Sim3,
    TrajectoryMetrics,
    associate,
    evaluate_trajectory,
    umeyama,
)
from dimslam.common.geometry import pose
from dimslam.common.io.trajectory import Trajectory

# ---------------------------------------------------------------------------------------------
# Independent reference: Horn's closed-form quaternion solution (J. Opt. Soc. Am. A, 1987).
# Written without evaluation.py or pose.py so that a shared mistake cannot hide.


def _quat_wxyz_to_matrix(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z],
        ]
    )


def horn(src: np.ndarray, dst: np.ndarray, with_scale: bool = True):
    """`(s, R, t)` minimizing sum |dst - (s R src + t)|^2: Horn's rotation, Umeyama's scale."""
    mu_x, mu_y = src.mean(0), dst.mean(0)
    x, y = src - mu_x, dst - mu_y
    M = x.T @ y  # M[a, b] = sum_i x_ia y_ib
    (sxx, sxy, sxz), (syx, syy, syz), (szx, szy, szz) = M
    N = np.array(
        [
            [sxx + syy + szz, syz - szy, szx - sxz, sxy - syx],
            [syz - szy, sxx - syy - szz, sxy + syx, szx + sxz],
            [szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy],
            [sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz],
        ]
    )
    _, vectors = np.linalg.eigh(N)  # ascending eigenvalues: the last is the largest
    R = _quat_wxyz_to_matrix(vectors[:, -1])
    s = float(np.sum(y * (x @ R.T)) / np.sum(x * x)) if with_scale else 1.0
    return s, R, mu_y - s * R @ mu_x


def horn_ate(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> float:
    s, R, t = horn(src, dst, with_scale)
    return float(np.sqrt(np.mean(np.sum((s * src @ R.T + t - dst) ** 2, axis=1))))


# ---------------------------------------------------------------------------------------------


def random_trajectory(seed: int, n: int = 60, rate: float = 30.0) -> Trajectory:
    """A smooth-ish 3D camera path (random walk of twists), timestamps at `rate` Hz."""
    g = torch.Generator().manual_seed(seed)
    steps = 0.05 * torch.randn(n, 6, generator=g, dtype=torch.float64)
    T = [pose.exp_se3(steps[0])]
    for k in range(1, n):
        T.append(pose.compose(T[-1], pose.exp_se3(steps[k])))
    return Trajectory(1.0 + np.arange(n) / rate, torch.stack(T).numpy())


def random_sim3(seed: int, with_scale: bool = True) -> Sim3:
    g = torch.Generator().manual_seed(1000 + seed)
    w = 2.0 * torch.randn(3, generator=g, dtype=torch.float64)
    s = math.exp(float(torch.randn(1, generator=g))) if with_scale else 1.0
    t = 3.0 * torch.randn(3, generator=g, dtype=torch.float64)
    return Sim3(s, pose.exp_so3(w).numpy(), t.numpy())


def perturbed(traj: Trajectory, sigma: float, seed: int) -> Trajectory:
    """`traj` with Gaussian noise `sigma` (m, rad) on every pose's translation and rotation."""
    g = torch.Generator().manual_seed(2000 + seed)
    xi = sigma * torch.randn(len(traj), 6, generator=g, dtype=torch.float64)
    T = pose.compose(torch.from_numpy(traj.poses), pose.exp_se3(xi))
    return Trajectory(traj.timestamps.copy(), T.numpy())


def test_horn_reference_recovers_a_known_transform():
    # The reference must itself be right: recover a known Sim(3) from exact correspondences.
    S = random_sim3(0)
    src = np.random.default_rng(0).normal(size=(30, 3))
    s, R, t = horn(src, S.apply_points(src))
    assert np.isclose(s, S.s) and np.allclose(R, S.R) and np.allclose(t, S.t)


@pytest.mark.parametrize("seed", range(5))
def test_exact_sim3_copy_is_undone(seed):
    gt = random_trajectory(seed)
    S = random_sim3(seed)
    est = S.apply_trajectory(gt)  # the estimate lives in a scaled, rotated, shifted world
    m = evaluate_trajectory(est, gt)

    assert m.ate_rmse_m < 1e-9 and m.ate_max_m < 1e-9
    assert m.matched == len(gt)
    S_inv = S.inverse()
    assert np.isclose(m.alignment.s, S_inv.s, atol=1e-6)
    assert np.allclose(m.alignment.R, S_inv.R, atol=1e-6)
    assert np.allclose(m.alignment.t, S_inv.t, atol=1e-6)
    # Relative errors too: the estimate is exact once scaled.
    assert m.rpe_trans_per_m < 1e-9 and m.rpe_rot_deg_per_frame < 1e-6

    s, R, t = horn(est.positions, gt.positions)
    assert np.isclose(m.alignment.s, s, atol=1e-6)
    assert np.allclose(m.alignment.R, R, atol=1e-6) and np.allclose(m.alignment.t, t, atol=1e-6)


@pytest.mark.parametrize("seed", range(5))
def test_noisy_sim3_copy_agrees_with_horn(seed):
    gt = random_trajectory(seed)
    est = random_sim3(seed).apply_trajectory(perturbed(gt, 0.02, seed))
    m = evaluate_trajectory(est, gt)

    s, R, t = horn(est.positions, gt.positions)
    assert np.isclose(m.alignment.s, s, atol=1e-6)
    assert np.allclose(m.alignment.R, R, atol=1e-6) and np.allclose(m.alignment.t, t, atol=1e-6)
    assert np.isclose(m.ate_rmse_m, horn_ate(est.positions, gt.positions), atol=1e-6)
    assert 0.005 < m.ate_rmse_m < 0.05  # the noise shows, in ground-truth units
    assert m.ate_mean_m <= m.ate_rmse_m <= m.ate_max_m
    assert np.isclose(m.ate_rmse_m, np.sqrt(np.mean(m.errors_m**2)))


@pytest.mark.parametrize("seed", range(3))
def test_se3_alignment_agrees_with_horn_and_keeps_scale(seed):
    gt = random_trajectory(seed)
    est = random_sim3(seed, with_scale=False).apply_trajectory(perturbed(gt, 0.02, seed))
    m = evaluate_trajectory(est, gt, align="se3")
    s, R, t = horn(est.positions, gt.positions, with_scale=False)
    assert m.alignment.s == 1.0 and m.align == "se3"
    assert np.allclose(m.alignment.R, R, atol=1e-6) and np.allclose(m.alignment.t, t, atol=1e-6)
    assert np.isclose(m.ate_rmse_m, horn_ate(est.positions, gt.positions, False), atol=1e-6)

    # A scaled estimate is penalized by SE(3) but not by Sim(3).
    scaled = Sim3(1.5, np.eye(3), np.zeros(3)).apply_trajectory(gt)
    assert evaluate_trajectory(scaled, gt, align="se3").ate_rmse_m > 0.01
    assert evaluate_trajectory(scaled, gt, align="sim3").ate_rmse_m < 1e-9


def test_umeyama_never_returns_a_reflection():
    # Mirror-image points: the best proper rotation is not the reflection that fits exactly.
    src = np.random.default_rng(1).normal(size=(20, 3))
    dst = src * np.array([1.0, 1.0, -1.0])
    S = umeyama(src, dst)
    assert np.isclose(np.linalg.det(S.R), 1.0)
    s, R, t = horn(src, dst)
    assert np.allclose(S.R, R, atol=1e-6) and np.isclose(S.s, s, atol=1e-6)


def test_sim3_apply_poses_moves_centres_like_points():
    S = random_sim3(4)
    T = random_trajectory(4, n=10).poses
    out = S.apply_poses(T)
    assert np.allclose(out[:, :3, 3], S.apply_points(T[:, :3, 3]))
    assert np.allclose(out[:, :3, :3], S.R @ T[:, :3, :3])
    assert np.allclose(out[:, 3], [0, 0, 0, 1])
    assert np.allclose(S.inverse().apply_poses(out), T)
    assert np.allclose(S.matrix @ S.inverse().matrix, np.eye(4))


def test_association_with_jitter_and_missing_frames():
    gt_ts = 1.0 + np.arange(100) / 30.0
    rng = np.random.default_rng(0)
    keep = np.sort(rng.choice(100, size=70, replace=False))
    est_ts = gt_ts[keep] + rng.uniform(-0.008, 0.008, size=70)
    idx_est, idx_gt = associate(est_ts[::-1], gt_ts)  # any input order
    assert len(idx_est) == 70
    assert np.array_equal(idx_gt, keep)  # each estimate found its own frame
    assert np.all(np.diff(est_ts[::-1][idx_est]) > 0)  # ordered by estimate time


def test_association_is_one_to_one():
    # Both estimates are closest to gt 1.000; the farther one falls back to gt 1.033.
    idx_est, idx_gt = associate(np.array([1.010, 1.015]), np.array([1.0, 1.033]), max_dt=0.02)
    assert idx_est.tolist() == [0, 1] and idx_gt.tolist() == [0, 1]
    # With a tighter bound the fallback (18 ms) is too far and stays unmatched.
    idx_est, idx_gt = associate(np.array([1.010, 1.015]), np.array([1.0, 1.033]), max_dt=0.017)
    assert idx_est.tolist() == [0] and idx_gt.tolist() == [0]


def test_association_picks_the_closest_candidate():
    idx_est, idx_gt = associate(np.array([0.995, 1.004, 1.001]), np.array([1.0]), max_dt=0.01)
    assert idx_est.tolist() == [2] and idx_gt.tolist() == [0]
    empty = associate(np.array([0.0, 1.0]), np.array([0.5]), max_dt=0.02)
    assert len(empty[0]) == 0 and len(empty[1]) == 0


def test_mismatched_time_bases_say_so():
    gt = random_trajectory(0)
    est = Trajectory(gt.timestamps + 1.7e9, gt.poses)  # unix time against sequence time
    with pytest.raises(EvaluationError, match=r"only 0 poses associate") as info:
        evaluate_trajectory(est, gt)
    message = str(info.value)
    assert "60 estimated poses" in message and "60 ground-truth poses" in message
    assert "1700000001.000000" in message and "[1.000000, 2.966667] s" in message


def test_too_few_matches_and_non_finite_poses_are_errors():
    gt = random_trajectory(0)
    with pytest.raises(EvaluationError, match="only 2 poses associate"):
        evaluate_trajectory(Trajectory(gt.timestamps[:2], gt.poses[:2]), gt)
    poses = gt.poses.copy()
    poses[7, 0, 3] = np.nan
    with pytest.raises(EvaluationError, match=r"1 non-finite poses.*index 7"):
        evaluate_trajectory(Trajectory(gt.timestamps, poses), gt)
    with pytest.raises(ValueError, match="align"):
        evaluate_trajectory(gt, gt, align="sim2")  # type: ignore[arg-type]


def line_trajectory(n: int, step: np.ndarray, yaw_steps_deg: np.ndarray | None = None):
    """Poses along a line, `step` apart, yawing by `yaw_steps_deg[k]` between k and k + 1."""
    angles = torch.zeros(n, 3, dtype=torch.float64)
    if yaw_steps_deg is not None:
        yaw = np.concatenate([[0.0], np.cumsum(np.radians(yaw_steps_deg))])
        angles[:, 2] = torch.from_numpy(yaw)
    t = torch.from_numpy(np.arange(n)[:, None] * step)
    return Trajectory(np.arange(n) / 30.0, pose.make_pose(pose.exp_so3(angles), t).numpy())


def test_rpe_of_a_constant_step_error():
    # Ground truth: 10 cm steps along x. Estimate: each step also drifts 1 cm along y, i.e. a
    # 1 cm relative-translation error per 10 cm travelled: 0.1 m/m whatever the rigid alignment.
    gt = line_trajectory(50, np.array([0.1, 0.0, 0.0]))
    est = line_trajectory(50, np.array([0.1, 0.01, 0.0]))
    m = evaluate_trajectory(est, gt, align="se3")
    assert m.rpe_trans_per_m == pytest.approx(0.1, rel=1e-9)
    assert m.rpe_rot_deg_per_frame == pytest.approx(0.0, abs=1e-9)


def test_rpe_of_a_known_rotation_error():
    # The estimate turns 1 and 3 degrees in alternate steps where the truth goes straight.
    gt = line_trajectory(51, np.array([0.1, 0.0, 0.0]))
    est = line_trajectory(51, np.array([0.1, 0.0, 0.0]), np.tile([1.0, 3.0], 25))
    m = evaluate_trajectory(est, gt)
    assert m.rpe_rot_deg_per_frame == pytest.approx(2.0, rel=1e-9)


def test_rpe_uses_the_alignment_scale():
    # Half-size estimate: Sim(3) scales it back, so no relative error remains.
    gt = random_trajectory(2)
    half = Sim3(0.5, np.eye(3), np.zeros(3)).apply_trajectory(gt)
    assert evaluate_trajectory(half, gt).rpe_trans_per_m < 1e-9
    assert evaluate_trajectory(half, gt, align="se3").rpe_trans_per_m > 0.1


def test_trajectory_metrics_dict():
    gt = random_trajectory(0)
    m = evaluate_trajectory(perturbed(gt, 0.01, 0), gt)
    assert isinstance(m, TrajectoryMetrics)
    d = m.to_dict()
    assert set(d) == {
        "ate_rmse_m",
        "ate_mean_m",
        "ate_median_m",
        "ate_max_m",
        "rpe_trans_per_m",
        "rpe_rot_deg_per_frame",
        "matched",
        "est_count",
        "gt_count",
        "align",
        "scale",
    }
    assert d["ate_rmse_m"] == m.ate_rmse_m and d["matched"] == 60 and d["align"] == "sim3"


def test_evaluation_does_not_import_plotting():
    tree = ast.parse(open(evaluation.__file__).read())
    imported = {
        node.module if isinstance(node, ast.ImportFrom) else alias.name
        for node in ast.walk(tree)
        if isinstance(node, ast.Import | ast.ImportFrom)
        for alias in node.names
    }
    assert not any("plot" in (name or "") or "cv2" in (name or "") for name in imported)

"""SE(3) identities, small-angle behaviour and quaternion conversions of common/geometry/pose.py."""

import math

import pytest
import torch

from dimslam.common.geometry import pose


def random_twists(n: int, dtype=torch.float64, max_angle: float = 3.0, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    xi = torch.randn(n, 6, generator=g, dtype=dtype)
    axis = xi[:, 3:] / xi[:, 3:].norm(dim=-1, keepdim=True)
    xi[:, 3:] = axis * torch.rand(n, 1, generator=g, dtype=dtype) * max_angle
    return xi


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-10), (torch.float32, 1e-4)])
def test_exp_log_round_trip(dtype, tol):
    xi = random_twists(500, dtype, max_angle=2.5)
    xi[:10, 3:] *= 1e-7  # tiny rotations take the Taylor branch
    xi[10:20, 3:] = 0.0
    assert torch.allclose(pose.log_se3(pose.exp_se3(xi)), xi, atol=tol)


def test_log_near_pi_is_stable():
    axis = torch.tensor([[1.0, 2.0, -0.5]], dtype=torch.float64)
    w = axis / axis.norm() * (math.pi - 1e-6)
    R = pose.exp_so3(w)
    assert torch.allclose(pose.log_so3(R).abs(), w.abs(), atol=1e-6)
    assert pose.rotation_angle(R).item() == pytest.approx(math.pi - 1e-6, abs=1e-6)


def test_the_angle_between_two_poses_is_their_relative_rotation_s_whatever_the_translations():
    a = pose.exp_se3(torch.tensor([0.3, -0.2, 1.0, 0.1, 0.2, -0.3], dtype=torch.float64))
    turn = pose.exp_se3(torch.tensor([2.0, 0.0, -1.0, 0.0, 0.0, 0.25], dtype=torch.float64))
    assert pose.angle_between(a, pose.compose(a, turn)).item() == pytest.approx(0.25, abs=1e-12)
    assert pose.angle_between(a, a).item() == pytest.approx(0.0, abs=1e-6)


def test_exp_is_rigid_and_matches_matrix_exponential():
    xi = random_twists(50, max_angle=3.0)
    T = pose.exp_se3(xi)
    R = T[:, :3, :3]
    eye = torch.eye(3, dtype=torch.float64)
    assert torch.allclose(R @ R.transpose(-1, -2), eye.expand_as(R), atol=1e-12)
    assert torch.allclose(torch.det(R), torch.ones(50, dtype=torch.float64))
    # Independent reference: the matrix exponential of the 4x4 twist matrix.
    X = torch.zeros(50, 4, 4, dtype=torch.float64)
    X[:, :3, :3] = pose.hat(xi[:, 3:])
    X[:, :3, 3] = xi[:, :3]
    assert torch.allclose(T, torch.linalg.matrix_exp(X), atol=1e-10)


def test_invert_compose_and_transform_points():
    T = pose.exp_se3(random_twists(20))
    eye = pose.identity((20,), dtype=torch.float64)
    assert torch.allclose(pose.compose(T, pose.invert(T)), eye, atol=1e-12)
    assert torch.allclose(pose.invert(T), torch.linalg.inv(T), atol=1e-12)
    p = torch.randn(20, 7, 3, dtype=torch.float64)
    back = pose.transform_points(pose.invert(T), pose.transform_points(T, p))
    assert torch.allclose(back, p, atol=1e-12)


def test_retract_is_a_body_frame_increment():
    T = pose.exp_se3(random_twists(5))
    xi = random_twists(5, seed=1) * 1e-2
    assert torch.allclose(pose.retract(T, xi), T @ pose.exp_se3(xi), atol=1e-14)


def test_gradients_finite_at_zero():
    xi = torch.zeros(3, 6, dtype=torch.float64, requires_grad=True)
    pose.log_se3(pose.exp_se3(xi)).sum().backward()
    assert torch.allclose(xi.grad, torch.ones_like(xi))
    x32 = torch.zeros(6, requires_grad=True)
    (pose.exp_se3(x32) ** 2).sum().backward()
    assert torch.isfinite(x32.grad).all()


def test_quaternion_round_trip_and_convention():
    # 90 degrees about z: x -> y.  TUM order (x, y, z, w).
    q = torch.tensor([0.0, 0.0, math.sin(math.pi / 4), math.cos(math.pi / 4)], dtype=torch.float64)
    R = pose.quat_to_matrix(q)
    assert torch.allclose(
        R @ torch.tensor([1.0, 0, 0], dtype=torch.float64),
        torch.tensor([0.0, 1, 0], dtype=torch.float64),
        atol=1e-12,
    )
    Rs = pose.exp_so3(random_twists(300, max_angle=math.pi)[:, 3:])
    q = pose.matrix_to_quat(Rs)
    assert (q[:, 3] >= 0).all()
    assert torch.allclose(q.norm(dim=-1), torch.ones(300, dtype=torch.float64))
    assert torch.allclose(pose.quat_to_matrix(q), Rs, atol=1e-12)
    assert torch.allclose(pose.quat_to_matrix(-q), Rs, atol=1e-12)  # q and -q: same rotation


def test_float32_and_batch_shapes_preserved():
    xi = torch.zeros(2, 3, 6)
    T = pose.exp_se3(xi)
    assert T.shape == (2, 3, 4, 4) and T.dtype == torch.float32
    assert pose.log_se3(T).shape == (2, 3, 6)


def test_shape_errors_are_clear():
    with pytest.raises(ValueError, match=r"T_ab: expected shape \(\.\.\., 4, 4\)"):
        pose.invert(torch.zeros(3, 3))


def test_normalize_keeps_repeated_composition_on_se3():
    # The motion model composes a pose with itself again and again: in float32 without
    # normalization the rotation drifts off SO(3) geometrically (invert assumes R^T = R^-1).
    step = pose.exp_se3(torch.tensor([0.01, 0.0, 0.015, 0.004, 0.006, -0.003]))
    before, previous = torch.eye(4), step
    for _ in range(60):
        motion = pose.compose(pose.invert(before), previous)
        before, previous = previous, pose.normalize(pose.compose(previous, motion))
    R = previous[:3, :3]
    assert torch.allclose(R @ R.T, torch.eye(3), atol=1e-5)
    expected = torch.linalg.matrix_power(step.double(), 61)
    assert torch.allclose(previous.double(), expected, atol=1e-3)


def test_normalize_projects_a_perturbed_rotation():
    R = pose.exp_so3(torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64))
    T = pose.make_pose(R * 1.01 + 0.001, torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64))
    N = pose.normalize(T)
    assert torch.allclose(N[:3, :3] @ N[:3, :3].T, torch.eye(3, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(N[:3, :3], R, atol=2e-3) and torch.equal(N[:3, 3], T[:3, 3])

"""Sim(3) identities of common/geometry/sim3.py: exp/log round trips (also near 0 and pi),
the exact inverse, and the SE(3) conversions."""

import math

import pytest
import torch

from dimslam.common.geometry import pose, sim3

F64 = torch.float64


def random_xi(n: int, max_angle: float = 3.0, seed: int = 0) -> torch.Tensor:
    """Tangent vectors with angles in [0, max_angle) and scales in [0.3, 3]."""
    g = torch.Generator().manual_seed(seed)
    xi = torch.randn(n, 7, generator=g, dtype=F64)
    axis = xi[:, 3:6] / xi[:, 3:6].norm(dim=-1, keepdim=True)
    xi[:, 3:6] = axis * torch.rand(n, 1, generator=g, dtype=F64) * max_angle
    xi[:, 6] = torch.empty(n, dtype=F64).uniform_(math.log(0.3), math.log(3.0), generator=g)
    return xi


def algebra_exp(xi: torch.Tensor) -> torch.Tensor:
    """The reference: the matrix exponential of [[omega^ + sigma I, rho], [0, 0]]."""
    M = torch.zeros(*xi.shape[:-1], 4, 4, dtype=xi.dtype)
    M[..., :3, :3] = pose.hat(xi[..., 3:6]) + xi[..., 6, None, None] * torch.eye(3, dtype=F64)
    M[..., :3, 3] = xi[..., :3]
    return torch.linalg.matrix_exp(M)


def test_exp_log_round_trip_over_angles_and_scales():
    xi = random_xi(600, max_angle=math.pi - 0.1)
    xi[:50, 3:6] *= 1e-7  # tiny rotations: the series of V
    xi[50:100, 3:6] = 0.0
    xi[100:150, 6] *= 1e-8  # tiny log-scales, large rotations
    xi[150:200] *= 1e-4  # everything tiny
    xi[200:250, 3:6] *= (math.pi - 0.1) / xi[200:250, 3:6].norm(dim=-1, keepdim=True)
    assert torch.allclose(sim3.exp_sim3(xi), algebra_exp(xi), atol=1e-11)
    assert torch.allclose(sim3.log_sim3(sim3.exp_sim3(xi)), xi, atol=1e-10)


def test_exp_is_smooth_across_the_series_threshold():
    # Either side of r = 1e-3 the series and the closed form must agree with the reference.
    direction = torch.tensor([0.3, -1.0, 2.0, 0.4, -0.2, 0.7, 0.5], dtype=F64)
    radii = torch.tensor([0.5e-3, 0.99e-3, 1.01e-3, 2e-3], dtype=F64)
    xi = direction / direction[3:].norm() * radii[:, None]
    xi[:, :3] = direction[:3]  # a translation of O(1), so errors in V show
    assert torch.allclose(sim3.exp_sim3(xi), algebra_exp(xi), atol=1e-13)


def test_exp_of_pure_log_scale_is_a_pure_scale():
    sigma = torch.tensor([-1.2, -1e-9, 0.0, 1e-9, 0.7], dtype=F64)
    xi = torch.zeros(5, 7, dtype=F64)
    xi[:, 6] = sigma
    expected = torch.diag_embed(torch.stack([*[sigma.exp()] * 3, torch.ones(5, dtype=F64)], -1))
    assert torch.allclose(sim3.exp_sim3(xi), expected, atol=1e-15)
    assert torch.allclose(sim3.scale_of(sim3.exp_sim3(xi)), sigma.exp(), atol=1e-15)


def test_gradients_are_finite_at_zero():
    xi = torch.zeros(7, dtype=F64, requires_grad=True)
    sim3.log_sim3(sim3.exp_sim3(xi)).sum().backward()
    assert torch.isfinite(xi.grad).all()
    assert torch.allclose(xi.grad, torch.ones(7, dtype=F64), atol=1e-12)


def test_inverse_is_exact():
    S = sim3.exp_sim3(random_xi(200, seed=1))
    eye = torch.eye(4, dtype=F64).expand(200, 4, 4)
    assert torch.allclose(sim3.compose(sim3.invert(S), S), eye, atol=1e-12)
    assert torch.allclose(sim3.compose(S, sim3.invert(S)), eye, atol=1e-12)
    assert torch.allclose(sim3.scale_of(sim3.invert(S)), 1 / sim3.scale_of(S), atol=1e-12)


def test_from_pose_and_to_pose_round_trip():
    g = torch.Generator().manual_seed(2)
    T = pose.exp_se3(torch.randn(30, 6, generator=g, dtype=F64))
    scale = torch.empty(30, dtype=F64).uniform_(0.3, 3.0, generator=g)
    S = sim3.from_pose(T, scale)
    assert torch.allclose(S[:, :3, 3], T[:, :3, 3])  # translation unchanged
    T_back, s_back = sim3.to_pose(S)
    assert torch.allclose(T_back, T, atol=1e-12)
    assert torch.allclose(s_back, scale, atol=1e-12)
    assert torch.equal(sim3.from_pose(T), T)  # scale 1 is the pose itself


@pytest.mark.parametrize("scale", [0.5, 2.0])
def test_invert_matches_the_general_inverse(scale):
    S = sim3.from_pose(
        pose.exp_se3(torch.tensor([1.0, -2.0, 0.5, 0.3, 0.2, -1.0], dtype=F64)), scale
    )
    assert torch.allclose(sim3.invert(S), torch.linalg.inv(S), atol=1e-12)

"""Sim(3) on 4x4 tensors, for loop closure in a monocular map whose scale drifts.

Conventions, the same layout as `pose` (SE(3)):

- A similarity is `S = [[s R, t], [0, 1]]`, a `(..., 4, 4)` tensor with `s > 0`; it maps
  `p -> s R p + t`. `S_wk` is world-from-node k, as `T_wc` is world-from-camera.
- A tangent vector `xi` is `(..., 7)` ordered `(rho, omega, sigma)`: translation part, rotation
  (axis-angle), log-scale; `exp(xi) = [[e^sigma exp(omega^), V rho], [0, 1]]` with
  `V = int_0^1 e^(u sigma) exp(u omega^) du = a0 I + a1 W + a2 W^2`, `W = omega^`.

Every function is batched over leading dimensions and keeps the input's dtype and device.
Near `sigma = theta = 0` the coefficients of V use Taylor series so that values and gradients
stay finite; the rest of the error analysis is in `_v_coefficients`.
"""

from __future__ import annotations

import torch

from dimslam.common.geometry.pose import (
    _small_angle,
    _so3_coefficients,
    hat,
    log_so3,
    make_pose,
)
from dimslam.common.geometry.shapes import check_shape


def from_pose(T: torch.Tensor, scale: float | torch.Tensor = 1.0) -> torch.Tensor:
    """Sim(3) `(..., 4, 4)` from SE(3) poses `(..., 4, 4)` and scales (float or `(...)`)."""
    check_shape("T", T, (..., 4, 4))
    s = torch.as_tensor(scale, dtype=T.dtype, device=T.device)
    return make_pose(s[..., None, None] * T[..., :3, :3], T[..., :3, 3])


def scale_of(S: torch.Tensor) -> torch.Tensor:
    """Scales `(...)` of `(..., 4, 4)` similarities: the cube root of det(s R) = s^3.

    NaN where the determinant is negative (a reflection is no similarity of ours).
    """
    check_shape("S", S, (..., 4, 4))
    c = S[..., :3, :3]  # det = c0 . (c1 x c2), elementwise: no LAPACK call per batch
    det = (c[..., 0] * torch.linalg.cross(c[..., 1], c[..., 2], dim=-1)).sum(-1)
    return det ** (1.0 / 3.0)


def to_pose(S: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Split `(..., 4, 4)` similarities into SE(3) poses (same R and t) and scales `(...)`."""
    s = scale_of(S)
    return make_pose(S[..., :3, :3] / s[..., None, None], S[..., :3, 3]), s


def compose(S_ab: torch.Tensor, S_bc: torch.Tensor) -> torch.Tensor:
    """`S_ac = S_ab @ S_bc`, broadcasting over batch dimensions."""
    check_shape("S_ab", S_ab, (..., 4, 4))
    check_shape("S_bc", S_bc, (..., 4, 4))
    return S_ab @ S_bc


def invert(S_ab: torch.Tensor) -> torch.Tensor:
    """`S_ba` from `S_ab` by the structure: scale 1/s, rotation R^T, translation -R^T t / s."""
    s = scale_of(S_ab)[..., None, None]
    R_t = S_ab[..., :3, :3].transpose(-1, -2) / s  # R^T, since (sR)^T / s = R^T
    return make_pose(R_t / s, -(R_t @ S_ab[..., :3, 3:])[..., 0] / s[..., 0])


def _v_coefficients(sigma: torch.Tensor, theta2: torch.Tensor):
    """a0, a1, a2 of `V = a0 I + a1 W + a2 W^2` for log-scales `sigma` and squared angles.

    a0 = (e^s - 1)/s, a1 = int e^(us) sin(ut)/t du, a2 = int e^(us) (1 - cos ut)/t^2 du.
    The closed forms of a1 and a2 lose ~eps / (s^2 + t^2) to cancellation, so within the
    small-angle radius of `pose` (1e-3 in float64) a Taylor series in (s, t) takes over; its
    truncation error is O(r^4).
    """
    A, B, _ = _so3_coefficients(theta2)  # sin t / t, (1 - cos t) / t^2, safe at t = 0
    eps = _small_angle(sigma.dtype)
    one = torch.ones_like(sigma)
    small_s = sigma.abs() < eps
    safe_s = torch.where(small_s, one, sigma)
    s2 = sigma * sigma
    a0_series = 1 + sigma / 2 + s2 / 6 + s2 * sigma / 24 + s2 * s2 / 120
    a0 = torch.where(small_s, a0_series, torch.expm1(safe_s) / safe_s)
    r2 = s2 + theta2
    small = r2 < eps**2
    safe_r2 = torch.where(small, one, r2)
    es, cos = torch.exp(sigma), 1 - theta2 * B
    a1_series = 0.5 + sigma / 3 + s2 / 8 - theta2 / 24 + sigma * (s2 - theta2) / 30
    a2_series = 1 / 6 + sigma / 8 + s2 / 20 - theta2 / 120 + sigma * (s2 / 72 - theta2 / 144)
    a1 = torch.where(small, a1_series, (es * (sigma * A - cos) + 1) / safe_r2)
    a2 = torch.where(small, a2_series, (a0 - es * A + sigma * es * B) / safe_r2)
    return a0, a1, a2


def exp_sim3(xi: torch.Tensor) -> torch.Tensor:
    """Similarities `(..., 4, 4)` from tangent vectors `(..., 7)` ordered `(rho, omega, sigma)`."""
    check_shape("xi", xi, (..., 7))
    omega, sigma = xi[..., 3:6], xi[..., 6]
    W = hat(omega)
    WW = W @ W
    theta2 = (omega * omega).sum(-1)
    A, B, _ = _so3_coefficients(theta2)
    a0, a1, a2 = (a[..., None, None] for a in _v_coefficients(sigma, theta2))
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device)
    sR = torch.exp(sigma)[..., None, None] * (
        eye + A[..., None, None] * W + B[..., None, None] * WW
    )
    return make_pose(sR, ((a0 * eye + a1 * W + a2 * WW) @ xi[..., :3, None])[..., 0])


def log_sim3(S: torch.Tensor) -> torch.Tensor:
    """Tangent vectors `(..., 7)` ordered `(rho, omega, sigma)` from `(..., 4, 4)`; inverse of
    `exp_sim3` for rotation angles in [0, pi)."""
    check_shape("S", S, (..., 4, 4))
    s = scale_of(S)
    omega = log_so3(S[..., :3, :3] / s[..., None, None])
    sigma = torch.log(s)
    theta2 = (omega * omega).sum(-1)
    a0, a1, a2 = _v_coefficients(sigma, theta2)
    # V^-1 = b0 I + b1 W + b2 W^2 (W^3 = -theta^2 W); det > 0 as V's eigenvalues are
    # a0 and a0 - theta^2 a2 +- i theta a1, nonzero for angles below 2 pi.
    p = a0 - theta2 * a2
    det = p * p + theta2 * a1 * a1
    b0, b1, b2 = (b[..., None, None] for b in (1 / a0, -a1 / det, (a1 * a1 - p * a2) / (a0 * det)))
    W = hat(omega)
    eye = torch.eye(3, dtype=S.dtype, device=S.device)
    rho = ((b0 * eye + b1 * W + b2 * (W @ W)) @ S[..., :3, 3:])[..., 0]
    return torch.cat([rho, omega, sigma[..., None]], dim=-1)

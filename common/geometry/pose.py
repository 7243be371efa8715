"""SE(3) on 4x4 tensors: the one module that composes, inverts and converts poses.

Conventions (design.md section 2), decided here once:

- A pose is `T_wc`, camera-to-world, a `(..., 4, 4)` tensor; OpenCV camera axes (x right,
  y down, z forward). Every transform is named `T_<to><from>`: `T_wc @ p_c = p_w`.
- A twist `xi` in se(3) is `(..., 6)`, translation part first: `xi = (v, w)`, with
  `exp(xi) = [[exp(w^), V(w) v], [0, 1]]`.
- Quaternions exist only in trajectory files, in TUM order `(qx, qy, qz, qw)`; `quat_to_matrix`
  and `matrix_to_quat` are the only converters.

Every function is batched over leading dimensions and keeps the input's dtype and device
(float32 or float64, CPU or CUDA). Small-angle cases use Taylor expansions so that values and
gradients stay finite at zero rotation.
"""

from __future__ import annotations

import torch

from dimslam.common.geometry.shapes import check_shape

# Below this angle (radians) the closed forms lose precision to cancellation (1 - cos t is
# tiny); their Taylor series, exact to ~t^6, take over. float32 cancels much earlier.
_SMALL_ANGLE = {torch.float64: 1e-3}
_SMALL_ANGLE_LOW_PRECISION = 0.1


def _small_angle(dtype: torch.dtype) -> float:
    return _SMALL_ANGLE.get(dtype, _SMALL_ANGLE_LOW_PRECISION)


def identity(batch: tuple[int, ...] = (), dtype=torch.float32, device=None) -> torch.Tensor:
    """Identity poses of shape `(*batch, 4, 4)`."""
    return torch.eye(4, dtype=dtype, device=device).expand(*batch, 4, 4).clone()


def make_pose(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Assemble `(..., 4, 4)` from a rotation `(..., 3, 3)` and a translation `(..., 3)`."""
    check_shape("R", R, (..., 3, 3))
    check_shape("t", t, (..., 3))
    batch = torch.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    T = torch.zeros(*batch, 4, 4, dtype=R.dtype, device=R.device)
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def compose(T_ab: torch.Tensor, T_bc: torch.Tensor) -> torch.Tensor:
    """`T_ac = T_ab @ T_bc`, broadcasting over batch dimensions."""
    check_shape("T_ab", T_ab, (..., 4, 4))
    check_shape("T_bc", T_bc, (..., 4, 4))
    return T_ab @ T_bc


def invert(T_ab: torch.Tensor) -> torch.Tensor:
    """`T_ba` from `T_ab`, using the rigid structure (R^T, -R^T t) rather than a general inverse."""
    check_shape("T_ab", T_ab, (..., 4, 4))
    R_t = T_ab[..., :3, :3].transpose(-1, -2)
    t = T_ab[..., :3, 3:]
    return make_pose(R_t, -(R_t @ t)[..., 0])


def transform_points(T_ab: torch.Tensor, p_b: torch.Tensor) -> torch.Tensor:
    """Points `(..., N, 3)` in frame b mapped to frame a by `T_ab` `(..., 4, 4)`."""
    check_shape("T_ab", T_ab, (..., 4, 4))
    check_shape("p_b", p_b, (..., 3))
    return p_b @ T_ab[..., :3, :3].transpose(-1, -2) + T_ab[..., None, :3, 3]


def hat(w: torch.Tensor) -> torch.Tensor:
    """Skew-symmetric matrices `(..., 3, 3)` from vectors `(..., 3)`: `hat(w) @ x = w x x`."""
    check_shape("w", w, (..., 3))
    zero = torch.zeros_like(w[..., 0])
    x, y, z = w.unbind(-1)
    return torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(*w.shape[:-1], 3, 3)


def _so3_coefficients(theta2: torch.Tensor):
    """A = sin t / t, B = (1 - cos t) / t^2, C = (t - sin t) / t^3 with safe small-angle forms."""
    small = theta2 < _small_angle(theta2.dtype) ** 2
    safe2 = torch.where(small, torch.ones_like(theta2), theta2)
    theta = safe2.sqrt()
    s, c = torch.sin(theta), torch.cos(theta)
    A = torch.where(small, 1 - theta2 / 6 + theta2**2 / 120, s / theta)
    B = torch.where(small, 0.5 - theta2 / 24 + theta2**2 / 720, (1 - c) / safe2)
    C = torch.where(small, 1 / 6 - theta2 / 120 + theta2**2 / 5040, (theta - s) / (safe2 * theta))
    return A, B, C


def exp_so3(w: torch.Tensor) -> torch.Tensor:
    """Rotation matrices `(..., 3, 3)` from axis-angle vectors `(..., 3)` (Rodrigues)."""
    check_shape("w", w, (..., 3))
    W = hat(w)
    A, B, _ = _so3_coefficients((w * w).sum(-1))
    eye = torch.eye(3, dtype=w.dtype, device=w.device)
    return eye + A[..., None, None] * W + B[..., None, None] * (W @ W)


def exp_se3(xi: torch.Tensor) -> torch.Tensor:
    """Poses `(..., 4, 4)` from twists `(..., 6)` ordered `(v, w)`."""
    check_shape("xi", xi, (..., 6))
    v, w = xi[..., :3], xi[..., 3:]
    W = hat(w)
    WW = W @ W
    A, B, C = _so3_coefficients((w * w).sum(-1))
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device)
    R = eye + A[..., None, None] * W + B[..., None, None] * WW
    V = eye + B[..., None, None] * W + C[..., None, None] * WW
    return make_pose(R, (V @ v[..., None])[..., 0])


def log_so3(R: torch.Tensor) -> torch.Tensor:
    """Axis-angle vectors `(..., 3)` (angle in [0, pi]) from rotation matrices `(..., 3, 3)`.

    Goes through the quaternion, which stays well conditioned near both 0 and pi.
    """
    check_shape("R", R, (..., 3, 3))
    q = _matrix_to_quat(R)  # qw >= 0
    qv, qw = q[..., :3], q[..., 3]
    n = qv.norm(dim=-1)
    small = n < 1e-3  # atan2 is well conditioned; only the division by n needs the series
    safe_n = torch.where(small, torch.ones_like(n), n)
    # angle / n, with the series 2/qw * (1 - n^2 / (3 qw^2)) when n -> 0 (then qw -> 1).
    factor = torch.where(
        small,
        2.0 / qw * (1 - n**2 / (3 * qw**2)),
        2.0 * torch.atan2(n, qw) / safe_n,
    )
    return qv * factor[..., None]


def log_se3(T: torch.Tensor) -> torch.Tensor:
    """Twists `(..., 6)` ordered `(v, w)` from poses `(..., 4, 4)`; inverse of `exp_se3`."""
    check_shape("T", T, (..., 4, 4))
    w = log_so3(T[..., :3, :3])
    theta2 = (w * w).sum(-1)
    A, B, _ = _so3_coefficients(theta2)
    small = theta2 < _small_angle(theta2.dtype) ** 2
    safe2 = torch.where(small, torch.ones_like(theta2), theta2)
    # V^-1 = I - W/2 + D W^2, D = (1 - A / (2B)) / theta^2.
    D = torch.where(small, 1 / 12 + theta2 / 720 + theta2**2 / 30240, (1 - A / (2 * B)) / safe2)
    W = hat(w)
    eye = torch.eye(3, dtype=T.dtype, device=T.device)
    V_inv = eye - 0.5 * W + D[..., None, None] * (W @ W)
    v = (V_inv @ T[..., :3, 3:])[..., 0]
    return torch.cat([v, w], dim=-1)


def normalize(T: torch.Tensor) -> torch.Tensor:
    """Project the rotation part of `(..., 4, 4)` poses back onto SO(3) (via the quaternion).

    Products of float32 poses drift off SO(3), and `invert` relies on R^T being the inverse:
    a pose that is composed again and again (the motion model) must be normalized, or the
    error compounds (it tripled every frame and blew up tracking after ~15 frames).
    """
    check_shape("T", T, (..., 4, 4))
    return make_pose(quat_to_matrix(_matrix_to_quat(T[..., :3, :3])), T[..., :3, 3])


def retract(T: torch.Tensor, xi: torch.Tensor) -> torch.Tensor:
    """Apply a body-frame increment: `T @ exp(xi)`. The optimizers' pose update."""
    return compose(T, exp_se3(xi))


def rotation_angle(R: torch.Tensor) -> torch.Tensor:
    """Rotation angle in radians `(...)` of rotation matrices `(..., 3, 3)`."""
    return log_so3(R).norm(dim=-1)


def angle_between(T_a: torch.Tensor, T_b: torch.Tensor) -> torch.Tensor:
    """Rotation angle in radians `(...)` from the orientation of poses `T_a` to that of
    `T_b` (both `(..., 4, 4)`)."""
    return rotation_angle(T_a[..., :3, :3].transpose(-1, -2) @ T_b[..., :3, :3])


def quat_to_matrix(q_xyzw: torch.Tensor) -> torch.Tensor:
    """Rotation matrices `(..., 3, 3)` from quaternions `(..., 4)` in TUM order (x, y, z, w).

    The quaternion is normalized first; a zero quaternion gives NaN (callers validate files).
    """
    check_shape("q_xyzw", q_xyzw, (..., 4))
    q = q_xyzw / q_xyzw.norm(dim=-1, keepdim=True)
    x, y, z, w = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - z * w),
            2 * (x * z + y * w),
            2 * (x * y + z * w),
            1 - 2 * (x * x + z * z),
            2 * (y * z - x * w),
            2 * (x * z - y * w),
            2 * (y * z + x * w),
            1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(*q.shape[:-1], 3, 3)


def _matrix_to_quat(R: torch.Tensor) -> torch.Tensor:
    """Shepperd's method, branch chosen per element by the largest diagonal term; qw >= 0."""
    m00, m01, m02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    m10, m11, m12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    m20, m21, m22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    t = torch.stack(
        [1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22],
        dim=-1,
    )
    r = 0.5 * t.clamp_min(1e-12).sqrt()  # |qw|, |qx|, |qy|, |qz| candidates
    d = 4 * r
    candidates = torch.stack(
        [
            torch.stack([(m21 - m12), (m02 - m20), (m10 - m01), t[..., 0]], -1) / d[..., 0:1],
            torch.stack([t[..., 1], (m01 + m10), (m02 + m20), (m21 - m12)], -1) / d[..., 1:2],
            torch.stack([(m01 + m10), t[..., 2], (m12 + m21), (m02 - m20)], -1) / d[..., 2:3],
            torch.stack([(m02 + m20), (m12 + m21), t[..., 3], (m10 - m01)], -1) / d[..., 3:4],
        ],
        dim=-2,
    )  # (..., 4 branches, xyzw)
    best = t.argmax(dim=-1)
    q = torch.gather(candidates, -2, best[..., None, None].expand(*best.shape, 1, 4))[..., 0, :]
    q = q / q.norm(dim=-1, keepdim=True)
    return torch.where(q[..., 3:4] < 0, -q, q)


def matrix_to_quat(R: torch.Tensor) -> torch.Tensor:
    """Quaternions `(..., 4)` in TUM order (x, y, z, w), with qw >= 0, from `(..., 3, 3)`."""
    check_shape("R", R, (..., 3, 3))
    return _matrix_to_quat(R)

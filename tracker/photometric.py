"""The photometric least squares of one pyramid level, and the images it works on.

`LevelProblem` is what `DirectTracker` minimizes at each level: the residuals between a
frame's grey image and the intensities of reference points projected into it, under a pose and
a per-reference affine brightness, with their analytic Jacobians (the image gradient times the
projection's), Huber weights and Levenberg-Marquardt steps. Written for few operations per
iteration (each torch call costs microseconds on a CPU, whatever its size): the pose and
brightness live in numpy, the per-point work in one pass of float32 tensors.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from dimslam.common.geometry.camera import Camera
from dimslam.tracker.tracker import TrackerConfig

GREY = (0.299, 0.587, 0.114)
BRIGHTNESS_PRIOR = 1e-2
"""Weight of the prior that holds each reference's affine brightness near (1, 0), against
the data's own weights of ~0.01-0.04 for the gain (the intensities' variance about their
mean) and ~1 for the offset: the offset follows an exposure change, the gain stays near 1
(a gain of 0.7 in a unit test came out at 0.97, the pose within 5 mm; with a prior of 1e-3
the pose was 1 cm off)."""
GAIN_RANGE = (0.75, 1 / 0.75)
OFFSET_RANGE = (-0.2, 0.2)
PRIOR_BRIGHTNESS = np.array([1.0, 0.0])
"""Bounds of a reference's brightness against the frame: a few frames apart, exposure changes
less than that. Unbounded, a misaligned solve can lower the gain towards 0, which flattens the
residuals of any pose: on room0's frame 111 (oracle map, prior 1e-4) the gain fell to 0.1 and
the pose slid 40 cm along a textured wall."""
MARGIN = 2.0
"""Points closer than this (level pixels) to the border are out of view: their gradient is
one-sided there."""


def grey(rgb: torch.Tensor) -> torch.Tensor:
    """`(H, W)` grey image of an `(H, W, 3)` one."""
    return rgb @ rgb.new_tensor(GREY)


def channels(rgb: torch.Tensor, colour: bool) -> torch.Tensor:
    """`(H, W, C)`: what a solve compares of an `(H, W, 3)` image: its colours (C = 3) or its
    grey values (C = 1)."""
    return rgb if colour else grey(rgb)[..., None]


def pyramid(image: torch.Tensor, levels: int) -> list[torch.Tensor]:
    """`levels` `(H, W, C)` images, each half the size of the one before (2x2 means)."""
    out = [image]
    for _ in range(levels - 1):
        if min(out[-1].shape[:2]) < 16:
            break
        out.append(F.avg_pool2d(out[-1].permute(2, 0, 1)[None], 2)[0].permute(1, 2, 0))
    return out


def with_gradients(image: torch.Tensor) -> torch.Tensor:
    """`(H, W, 3C)` of an `(H, W, C)` image: its values, then their central differences
    along u, then along v."""
    padded = F.pad(image.permute(2, 0, 1)[None], (1, 1, 1, 1), mode="replicate")[0]
    padded = padded.permute(1, 2, 0)
    gu = 0.5 * (padded[1:-1, 2:] - padded[1:-1, :-2])
    gv = 0.5 * (padded[2:, 1:-1] - padded[:-2, 1:-1])
    return torch.cat([image, gu, gv], dim=-1)


def texture(image: torch.Tensor) -> float:
    """Mean absolute gradient of a `with_gradients` image: how much there is to align."""
    return float(image[..., image.shape[-1] // 3 :].abs().mean())


def level_uv(uv: torch.Tensor, level: int) -> torch.Tensor:
    """Level-0 pixel coordinates at pyramid `level` (pixel centres stay pixel centres)."""
    s = 0.5**level
    return (uv + 0.5) * s - 0.5


@dataclass
class Evaluation:
    """The residuals of one pose and brightness, with what their Jacobian needs."""

    r: torch.Tensor  # (N, C)
    valid: torch.Tensor  # (N,)
    w: torch.Tensor  # (N, C)
    cost: float
    p_c: torch.Tensor
    inv_z: torch.Tensor
    gradient: torch.Tensor  # (2, N, C): the frame's intensity gradient along u and v


class LevelProblem:
    """One pyramid level of a solve: the frame's image and the points' constants.

    The image is a `with_gradients` one of C channels; each point has C intensities (`centred`
    and `mean`, `(N, C)`), each a residual; a reference's brightness is shared by its channels.

    Written for few operations per iteration (each torch call costs microseconds on a CPU,
    whatever its size): the pose and brightness live in numpy, the per-point work in one pass
    of float32 tensors, the affine part of the Jacobian is built once.
    """

    def __init__(
        self,
        image: torch.Tensor,
        camera: Camera,
        p_w: torch.Tensor,
        centred: torch.Tensor,
        mean: torch.Tensor,
        ref_of: torch.Tensor,
        n_refs: int,
        cfg: TrackerConfig,
    ) -> None:
        self.chw = image.permute(2, 0, 1)[None].contiguous()  # (1, 3C, H, W)
        h, w = image.shape[:2]
        self.fx, self.fy, self.cx, self.cy = camera.fx, camera.fy, camera.cx, camera.cy
        self.box = (MARGIN - 0.5, w - 0.5 - MARGIN, MARGIN - 0.5, h - 0.5 - MARGIN)
        self.scale = (2.0 / max(w - 1, 1), 2.0 / max(h - 1, 1))
        self.p_w, self.centred, self.mean, self.ref_of = p_w, centred, mean, ref_of
        self.huber = cfg.huber
        # A step this small moves no point by a tenth of a pixel at this level (at 2 map units
        # of depth): the level has converged.
        self.converged = 0.1 / camera.fx * 2.0
        self.n_refs = n_refs
        self.affine = cfg.affine
        if self.affine:  # columns: the gains of the references, then their offsets
            onehot = F.one_hot(ref_of, n_refs).to(p_w.dtype)[:, None, :]  # (N, 1, R)
            onehot = onehot.expand(-1, centred.shape[1], -1)  # (N, C, R)
            self.A = torch.cat([-centred[..., None] * onehot, -onehot], dim=2).flatten(0, 1)

    def evaluate(self, T_cw: np.ndarray, ab: np.ndarray) -> Evaluation:
        T = torch.from_numpy(T_cw).to(self.p_w.device, self.p_w.dtype)
        R, t = T[:3, :3], T[:3, 3]
        p_c = torch.addmm(t, self.p_w, R.T)
        x, y, z = p_c.unbind(1)
        inv_z = 1.0 / z.clamp_min(1e-3)
        u = self.fx * x * inv_z + self.cx
        v = self.fy * y * inv_z + self.cy
        u0, u1, v0, v1 = self.box
        valid = (z > 1e-3) & (u >= u0) & (u <= u1) & (v >= v0) & (v <= v1)
        sx, sy = self.scale
        grid = torch.stack([u * sx - 1.0, v * sy - 1.0], dim=-1).view(1, 1, -1, 2)
        sample = F.grid_sample(self.chw, grid, mode="bilinear", align_corners=True)[0, :, 0]
        c = self.centred.shape[1]
        brightness = torch.from_numpy(ab).to(self.p_w.device, self.p_w.dtype)[self.ref_of]
        gains, offsets = brightness[:, :1], brightness[:, 1:]  # (N, 1) each
        r = sample[:c].T - (gains * self.centred + self.mean + offsets)  # (N, C)
        k = self.huber
        a = r.abs()
        rho = huber(r, k)
        # Points out of view count as outliers at the threshold, so leaving it earns nothing.
        rho = torch.where(valid[:, None], rho, torch.full_like(rho, 0.5 * k * k))
        w = torch.where(a <= k, torch.ones_like(a), k / a.clamp_min(1e-12)) * valid[:, None]
        drift = (ab - PRIOR_BRIGHTNESS).reshape(-1)
        cost = float(rho.mean()) + 0.5 * BRIGHTNESS_PRIOR * float(drift @ drift) * self.affine
        gradient = sample[c:].view(2, c, -1).transpose(1, 2)
        return Evaluation(r, valid, w, cost, p_c, inv_z, gradient)

    def normal_equations(self, e: Evaluation, ab: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """`H` and `g` of the weighted least squares in (pose increment, gains, offsets)."""
        x, y, z = e.p_c[:, None, :].unbind(2)  # (N, 1) each, against (N, C) gradients
        inv_z = e.inv_z[:, None]
        gu = e.gradient[0] * self.fx * inv_z
        gv = e.gradient[1] * self.fy * inv_z
        gz = -(gu * x + gv * y) * inv_z  # d r / d p_c = (gu, gv, gz)
        # Left increment of T_cw: d p_c / d v = I, d p_c / d w = -[p_c]x.
        J = torch.stack([gu, gv, gz, y * gz - z * gv, z * gu - x * gz, x * gv - y * gu], dim=2)
        J = J.flatten(0, 1)  # (N C, 6)
        if self.affine:
            J = torch.cat([J, self.A], dim=1)
        Jw = J * e.w.reshape(-1, 1)
        n = e.r.numel()
        H = (Jw.T @ J).double().cpu().numpy() / n
        g = (Jw.T @ e.r.reshape(-1)).double().cpu().numpy() / n
        if self.affine:
            H[6:, 6:] += BRIGHTNESS_PRIOR * np.eye(H.shape[0] - 6)
            g[6:] += BRIGHTNESS_PRIOR * (ab - PRIOR_BRIGHTNESS).T.reshape(-1)
        return H, g

    def minimize(
        self,
        T_cw: np.ndarray,
        ab: np.ndarray,
        budget: int,
        hold: float = 0.0,
        anchor: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, int, float]:
        """Levenberg-Marquardt; returns pose, brightness, iterations used and final cost.

        With `hold` > 0 and an `anchor` (a `T_cw`, the motion guess), the cost also holds the
        pose near the anchor: `hold` times the data's own curvature of each of the six pose
        directions at the start, so a direction the data fix firmly moves freely and one
        they leave loose (on a narrow view a turn and a sideways move look alike) stays near
        the guess, as a few small steps from the guess would leave it.
        """
        damping = 1e-3
        current = self.evaluate(T_cw, ab)
        equations = self.normal_equations(current, ab)  # of `current`; a rejected step keeps it
        weight, from_anchor = np.zeros(6), np.eye(4)
        if hold > 0 and anchor is not None:
            weight = hold * np.maximum(np.diag(equations[0])[:6], 0.0)
            from_anchor = np.linalg.inv(anchor)

        def total(e: Evaluation, T: np.ndarray) -> float:
            if not weight.any():
                return e.cost
            d = _deviation(T, from_anchor)
            return e.cost + 0.5 * float(weight @ (d * d))

        cost = total(current, T_cw)
        used = 0
        while used < budget:
            used += 1
            H, g = equations
            if weight.any():
                H, g = H.copy(), g.copy()
                H[:6, :6] += np.diag(weight)
                g[:6] += weight * _deviation(T_cw, from_anchor)
            H_lm = H + damping * np.diag(np.maximum(np.diag(H), 1e-12))
            try:
                step = -np.linalg.solve(H_lm, g)
            except np.linalg.LinAlgError:
                break
            if not np.isfinite(step).all():
                break
            T_new = se3_exp(step[:6]) @ T_cw
            ab_new = ab
            if self.affine:
                ab_new = ab + step[6:].reshape(2, -1).T
                ab_new[:, 0] = ab_new[:, 0].clip(*GAIN_RANGE)
                ab_new[:, 1] = ab_new[:, 1].clip(*OFFSET_RANGE)
            candidate = self.evaluate(T_new, ab_new)
            new_cost = total(candidate, T_new)
            if new_cost <= cost:
                T_cw, ab, current, cost = T_new, ab_new, candidate, new_cost
                damping = max(damping * 0.5, 1e-6)
                if max(np.abs(step[:6])) < self.converged:
                    break
                if used < budget:
                    equations = self.normal_equations(current, ab)
            else:
                damping *= 8.0
                if damping > 1e4:
                    break
        return T_cw, ab, used, current.cost


def _deviation(T_cw: np.ndarray, from_anchor: np.ndarray) -> np.ndarray:
    """The twist (translation, rotation vector; first order) that takes the anchor to `T_cw`
    as a left increment (`from_anchor`: the anchor's inverse)."""
    D = T_cw @ from_anchor
    R = D[:3, :3]
    w = 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return np.concatenate([D[:3, 3], w])


def huber(r: torch.Tensor, k: float) -> torch.Tensor:
    """Huber cost of each residual of `r` at threshold `k`."""
    a = r.abs()
    return torch.where(a <= k, 0.5 * r * r, k * (a - 0.5 * k))


def huber_mean(r: torch.Tensor, k: float) -> float:
    """Mean Huber cost of residuals `r` at threshold `k`."""
    return float(huber(r, k).mean())


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """`(4, 4)` float64 pose of a twist `(v, w)` (numpy; `pose.exp_se3` for tensors)."""
    v, w = xi[:3], xi[3:]
    th2 = float(w @ w)
    W = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if th2 < 1e-10:
        A, B, C = 1.0 - th2 / 6.0, 0.5 - th2 / 24.0, 1.0 / 6.0 - th2 / 120.0
    else:
        th = math.sqrt(th2)
        A, B, C = math.sin(th) / th, (1.0 - math.cos(th)) / th2, (th - math.sin(th)) / (th2 * th)
    WW = W @ W
    T = np.eye(4)
    T[:3, :3] = np.eye(3) + A * W + B * WW
    T[:3, 3] = (np.eye(3) + B * W + C * WW) @ v
    return T

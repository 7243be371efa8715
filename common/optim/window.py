"""Frames, keyframes and the window optimizer that the tracker and the mapper share.

A `FrameState` is one input frame inside the system: its image on the compute device and its
current pose estimate. `minimize` runs Adam on an objective of a window: pose increments
(se(3) twists on the current estimates, design.md section 4) for the frames marked movable,
plus whatever map parameter groups the caller passes (none for the tracker).
`optimize_window` is `minimize` on the window objective with pixels rendered at every
iteration (mapping and initialization); the tracker brings its own objective.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from dimslam.common.errors import DimslamError
from dimslam.common.geometry import pose
from dimslam.common.geometry.camera import Camera
from dimslam.common.map.render import DepthPrior, FieldFn, RenderConfig, render_pixels
from dimslam.common.optim import losses
from dimslam.common.optim.objective import LossConfig, WindowLoss, window_objective


class TrackingLost(DimslamError):
    """A frame could not be placed: the optimization diverged, or its result failed a check.

    Attributes:
        best: where the solve ended when only its checks failed (a high residual, few inliers):
            never published, but the motion model may follow it through a stretch of frames
            where the map is poor, so that the frames after it start near the camera. None when
            the solve locked onto something else, turned non-finite or did not run.
    """

    def __init__(self, message: str, best: torch.Tensor | None = None) -> None:
        super().__init__(message)
        self.best = best


@dataclass(eq=False)
class FrameState:
    """One frame inside the system.

    Attributes:
        index: position in the input stream (0-based, after stride).
        timestamp: seconds.
        rgb: `(H, W, 3)` float32 in [0, 1] on the compute device; None once the frame has left
            every window and is not a keyframe (its memory is released).
        T_wc: `(4, 4)` float32 current pose estimate.
        keyframe: whether it belongs to the global keyframe set.
    """

    index: int
    timestamp: float
    rgb: torch.Tensor | None
    T_wc: torch.Tensor
    keyframe: bool = False


def image_tensor(rgb: np.ndarray, device: torch.device | str = "cpu") -> torch.Tensor:
    """An `(H, W, 3)` uint8 RGB image as `FrameState.rgb` holds it: float32 in [0, 1] on
    `device`."""
    return torch.from_numpy(rgb).to(device).float() / 255.0


@dataclass
class WindowStats:
    """What an optimization step did (for logs and the progress line)."""

    iterations: int = 0
    loss: float = math.nan
    warp: float = math.nan
    render: float = math.nan
    smooth: float = math.nan
    warp_count: int = 0
    history: list[float] = field(default_factory=list)


def adam(groups: list[dict]) -> torch.optim.Adam:
    """Adam over parameter groups, with the fused kernel.

    The dense grids hold ~16M parameters at the paper's voxel sizes; the unfused step makes
    about ten passes over them and measured 106 ms per step on a 2-core CPU, the fused one
    16 ms (a third of a whole mapping iteration saved).
    """
    return torch.optim.Adam(groups, fused=True)


PixelSampler = Callable[[int], tuple[torch.Tensor, torch.Tensor]]
"""Iteration -> `(frame (M,) long, uv (M, 2) float)` pixels of the window to use."""

Objective = Callable[[int, torch.Tensor], tuple[torch.Tensor, WindowLoss]]
"""`(iteration, poses (F, 4, 4))` -> `(total to minimize, its terms for the stats)`."""


def minimize(
    frames: list[FrameState],
    movable: list[bool],
    objective: Objective,
    iterations: int,
    pose_lr: float,
    map_optimizer: torch.optim.Optimizer | None = None,
    max_loss: float = 10.0,
) -> WindowStats:
    """Adam on an objective of the window's poses (and the map); write the poses back.

    Args:
        frames: the window.
        movable: per frame, whether its pose is optimized (as an se(3) increment).
        objective: the loss of the window at the current poses.
        iterations: Adam steps.
        pose_lr: learning rate of the pose twists.
        map_optimizer: the optimizer of the map's parameters (grids, decoder), stepped with
            the poses; None leaves the map fixed. The caller owns it, so its moments may
            outlive one call (`MapperConfig.keep_adam`).
        max_loss: a total loss above this (or non-finite) means the optimization diverged.

    Raises:
        TrackingLost: on divergence; the frames keep their poses from before the step.
    """
    start = torch.stack([f.T_wc for f in frames])
    move = torch.tensor(movable, device=start.device)
    twists = torch.zeros(int(move.sum()), 6, device=start.device, requires_grad=True)
    optimizers = [adam([{"params": [twists], "lr": pose_lr}])]
    if map_optimizer is not None:
        optimizers.append(map_optimizer)
    stats = WindowStats()

    def current() -> torch.Tensor:
        poses = start.clone()
        if twists.shape[0]:
            poses[move] = pose.retract(start[move], twists)
        return poses

    for it in range(iterations):
        total, result = objective(it, current())
        value = total.item()
        if not math.isfinite(value) or value > max_loss:
            raise TrackingLost(f"optimization diverged at iteration {it} (loss {value:.4g})")
        for optimizer in optimizers:
            optimizer.zero_grad(set_to_none=True)
        total.backward()
        for optimizer in optimizers:
            optimizer.step()
        stats.history.append(value)
        stats.iterations = it + 1
        stats.loss, stats.warp, stats.render = value, result.warp, result.render
        stats.smooth, stats.warp_count = result.smooth, result.warp_count
    with torch.no_grad():
        final = pose.normalize(current())
    if not torch.isfinite(final).all():
        raise TrackingLost("poses became non-finite")
    for f, T in zip(frames, final, strict=True):
        f.T_wc = T.detach().clone()
    return stats


def optimize_window(
    field_fn: FieldFn,
    frames: list[FrameState],
    movable: list[bool],
    camera: Camera,
    pixels: PixelSampler,
    iterations: int,
    pose_lr: float,
    loss_cfg: LossConfig,
    render_cfg: RenderConfig,
    map_optimizer: torch.optim.Optimizer | None = None,
    generator: torch.Generator | None = None,
    smooth: bool = False,
    extra_loss: Callable[[WindowLoss, torch.Tensor, torch.Tensor], torch.Tensor] | None = None,
    max_loss: float = 10.0,
    surface: bool = False,
    pose_gate: float = 0.0,
) -> WindowStats:
    """Minimize the window objective; write the optimized poses back into `frames`.

    Args:
        field_fn: the map.
        frames: the window (all need `rgb`).
        movable: per frame, whether its pose is optimized.
        camera: shared intrinsics.
        pixels: which pixels to use at each iteration.
        iterations: Adam steps.
        pose_lr: learning rate of the pose twists.
        loss_cfg, render_cfg: objective and ray sampling.
        map_optimizer: the map's optimizer (see `minimize`) or None.
        generator: randomness for ray sampling.
        smooth: include the smoothness term.
        extra_loss: `(window_loss, frame_of_pixels, uv) -> tensor` added to the total (e.g. the
            scale gauge during initialization).
        max_loss: a total loss above this (or non-finite) means the optimization diverged.
        surface: sample rays around the depth the map renders for the window at the start
            (`RenderConfig.surface_samples`; a map that already holds the window's surfaces).
        pose_gate: rays the map stops less than this move the map only (`window_objective`).

    Raises:
        TrackingLost: on divergence; the frames keep their poses from before the step.
    """
    images = torch.stack([f.rgb for f in frames])
    prior = None
    if surface and render_cfg.surface_samples > 0:
        poses = torch.stack([f.T_wc for f in frames])
        prior = DepthPrior(field_fn, camera, poses, render_cfg)

    def objective(it: int, poses: torch.Tensor) -> tuple[torch.Tensor, WindowLoss]:
        frame, uv = pixels(it)
        result = window_objective(
            field_fn,
            images,
            poses,
            camera,
            frame,
            uv,
            loss_cfg,
            render_cfg,
            generator,
            smooth,
            prior,
            pose_gate,
        )
        total = result.total
        if extra_loss is not None:
            total = total + extra_loss(result, frame, uv)
        return total, result

    return minimize(frames, movable, objective, iterations, pose_lr, map_optimizer, max_loss)


def constant_velocity(previous: torch.Tensor, before: torch.Tensor) -> torch.Tensor:
    """The pose after `previous` if the motion from `before` to `previous` repeats."""
    motion = pose.compose(pose.invert(before), previous)
    return pose.normalize(pose.compose(previous, motion))


def release_images(frames: list[FrameState], keep: int) -> None:
    """Free the images no window will use again: all but the keyframes' and the newest `keep`."""
    for f in frames[:-keep]:
        if not f.keyframe:
            f.rgb = None


def random_pixels(
    n_frames: int, count: int, camera: Camera, margin: int, generator: torch.Generator, device
) -> tuple[torch.Tensor, torch.Tensor]:
    """`count` uniformly random pixels over `n_frames` frames, `margin` px from the border."""
    frame = torch.randint(0, n_frames, (count,), generator=generator, device=device)
    u = torch.randint(margin, camera.width - margin, (count,), generator=generator, device=device)
    v = torch.randint(margin, camera.height - margin, (count,), generator=generator, device=device)
    return frame, torch.stack([u, v], dim=-1).float()


def project_into(
    field_fn: FieldFn,
    source: FrameState,
    targets: list[FrameState],
    camera: Camera,
    count: int,
    render_cfg: RenderConfig,
    generator: torch.Generator,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Render `count` random pixels of `source` and reproject them into `targets`.

    Returns:
        `(uv (count, 2), uv_targets (T, count, 2), valid (T, count))`: the pixels, where they
        land in each target, and whether they land in front of it and inside its image.
    """
    device = source.T_wc.device
    _, uv = random_pixels(1, count, camera, 0, generator, device)
    with torch.no_grad():
        depth = render_pixels(field_fn, camera, uv, source.T_wc, render_cfg).depth
        T_l = torch.stack([t.T_wc for t in targets])
        zero = torch.zeros(1, 2, device=device)
        warp = losses.warp_patches(uv, depth, source.T_wc, T_l, camera, zero)
    return uv, warp.uv[:, :, 0], warp.valid[:, :, 0]


def overlapping_keyframes(
    field_fn: FieldFn,
    frame: FrameState,
    keyframes: list[FrameState],
    camera: Camera,
    limit: int,
    overlap: float,
    count: int,
    render_cfg: RenderConfig,
    generator: torch.Generator,
) -> list[FrameState]:
    """Up to `limit` random keyframes that see more than `overlap` of `frame`'s view.

    Overlap is the share of `count` random pixels of `frame`, placed at their rendered depth,
    that land inside a keyframe (paper section 3.3).
    """
    if not keyframes or limit <= 0:
        return []
    _, _, valid = project_into(field_fn, frame, keyframes, camera, count, render_cfg, generator)
    ratio = valid.float().mean(dim=1).tolist()
    good = [kf for kf, r in zip(keyframes, ratio, strict=True) if r > overlap]
    if len(good) <= limit:
        return good
    pick = torch.randperm(len(good), generator=generator, device=generator.device)[:limit]
    return [good[i] for i in sorted(pick.tolist())]

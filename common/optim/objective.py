"""The window objective shared by tracking, mapping and initialization (paper eq. 8).

For a window of frames with their current poses and a set of sampled pixels, render the
pixels' depth and colour from the map, and combine:

- the photometric warping loss: each pixel's fronto-parallel patch, placed at its rendered
  depth, compared (SSIM, L1 for size 1) with where it lands in every other window frame;
- the render loss: L1 between rendered and observed colour;
- the edge-aware smoothness of rendered depth on small pixel blocks (mapping only).

Which parameters move is the caller's business (the tracker's poses, the mapper's grids): the
objective is differentiable in the map and in every pose it is given.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from dimslam.common.geometry.camera import Camera
from dimslam.common.geometry.shapes import check_shape
from dimslam.common.map.render import DepthPrior, FieldFn, RenderConfig, render_pixels
from dimslam.common.optim import losses
from dimslam.common.options import option


@dataclass(frozen=True)
class LossConfig:
    """Weights and shape of the window objective (design.md section 4)."""

    warp_weight: float = option(0.5, "Weight of the patch warping loss (paper: 0.5).")
    render_weight: float = option(0.1, "Weight of the L1 render loss (paper: 0.1).")
    smooth_weight: float = option(0.01, "Weight of the depth smoothness loss (paper: 0.01).")
    patch_sizes: tuple[int, ...] = option((1, 5, 11), "Patch sizes of the warping loss.")
    min_views: int = option(5, "A pixel counts if it lands inside more than this many frames.")
    smooth_blocks: int = option(128, "Rendered 2x2 pixel blocks per iteration for smoothness.")

    def offsets(self, dtype=torch.float32, device=None) -> torch.Tensor:
        """`(P, 2)` the warping loss's patch layout (`losses.patch_offsets` of the largest
        size)."""
        return losses.patch_offsets(max(self.patch_sizes), dtype=dtype, device=device)

    def margin(self) -> int:
        """Pixels from the border where the largest patch still fits whole."""
        return max(self.patch_sizes) // 2


@dataclass(frozen=True)
class WindowLoss:
    """One evaluation of the objective.

    Attributes:
        total: 0-dim weighted sum, to call `backward()` on.
        warp, render, smooth: the normalized terms (floats, for logs).
        warp_count: number of valid warping terms (0 means the geometry is unconstrained).
        depth: `(M,)` rendered depth of the sampled pixels (with gradients, for extra terms).
    """

    total: torch.Tensor
    warp: float
    render: float
    smooth: float
    warp_count: int
    depth: torch.Tensor


class _GradientMask(torch.autograd.Function):
    """Identity on `(M, ...)` values; their gradient times `mask` `(M,)`, read at backward
    time, so the caller may fill `mask` in place after the forward pass (not through
    `save_for_backward`, which would refuse the change)."""

    @staticmethod
    def forward(ctx, values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        ctx.mask = mask
        return values.view_as(values)

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> tuple[torch.Tensor, None]:
        shape = (-1,) + (1,) * (grad.dim() - 1)
        return grad * ctx.mask.view(shape), None


def pixel_colors(images: torch.Tensor, frame: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Observed colours `(M, 3)` of integer pixels `uv` `(M, 2)` in frames `frame` `(M,)`."""
    u, v = uv[:, 0].long(), uv[:, 1].long()
    return images[frame, v, u]


def patch_colors(
    images: torch.Tensor, frame: torch.Tensor, uv: torch.Tensor, offsets: torch.Tensor
) -> torch.Tensor:
    """Observed colours `(M, P, 3)` of the patches `offsets` `(P, 2)` around integer pixels
    `uv` `(M, 2)` of frames `frame` `(M,)`, all inside their image."""
    u, v = (uv[:, None] + offsets).long().unbind(-1)
    return images[frame[:, None], v, u]


def window_objective(
    field: FieldFn,
    images: torch.Tensor,
    poses: torch.Tensor,
    camera: Camera,
    frame: torch.Tensor,
    uv: torch.Tensor,
    cfg: LossConfig,
    render_cfg: RenderConfig,
    generator: torch.Generator | None = None,
    smooth: bool = False,
    prior: DepthPrior | None = None,
    pose_gate: float = 0.0,
) -> WindowLoss:
    """Evaluate the objective on pixels of a window.

    Args:
        field: the map.
        images: `(F, H, W, 3)` window frames, float in [0, 1].
        poses: `(F, 4, 4)` their `T_wc`, with gradients where the caller optimizes them.
        camera: shared intrinsics.
        frame: `(M,)` long, the window frame of each sampled pixel.
        uv: `(M, 2)` integer-valued pixel coordinates, at least 5 px (half the largest patch)
            from the border.
        cfg: loss weights and shapes.
        render_cfg: ray sampling.
        generator: randomness for ray sampling and smoothness blocks.
        smooth: add the smoothness term (mapping).
        prior: the depths the window's rays are known to end near (`RenderConfig`'s surface
            sampling), or None.
        pose_gate: rays whose opacity is below this are rendered and warped as if the poses
            were fixed: they move the map, not the poses (0: every ray moves both).
    """
    check_shape("poses", poses, (images.shape[0], 4, 4))
    check_shape("uv", uv, (frame.shape[0], 2))
    near = prior(frame, uv) if prior is not None else None
    source = poses[frame]
    gated = pose_gate > 0 and poses.requires_grad
    if gated:  # which rays pass the gate is known once they are rendered, before any backward
        placed = torch.ones(frame.shape, dtype=poses.dtype, device=poses.device)
        source = _GradientMask.apply(source, placed)
    out = render_pixels(field, camera, uv, source, render_cfg, generator, depth_prior=near)
    render_term = losses.render_l1(out.rgb, pixel_colors(images, frame, uv))

    # Every pixel's patch is warped into every window frame in one call, its own frame masked
    # out: one image lookup for the window instead of one per source frame.
    offsets = cfg.offsets(dtype=uv.dtype, device=uv.device)
    n_frames = images.shape[0]
    warp = losses.warp_patches(uv, out.depth, source, poses, camera, offsets)
    if gated:
        placed.copy_(out.opacity.detach() >= pose_gate)
        still = losses.warp_patches(uv, out.depth, source, poses.detach(), camera, offsets)
        chosen = placed.bool()[None, :, None, None]
        warp = losses.WarpResult(torch.where(chosen, warp.uv, still.uv), warp.valid)
    others = frame != torch.arange(n_frames, device=frame.device)[:, None]  # (F, M)
    warp = losses.WarpResult(warp.uv, warp.valid & others[..., None])
    ref = patch_colors(images, frame, uv, offsets)
    warped = losses.sample_images(images, warp.uv)
    visible = losses.visibility_mask(warp, min(cfg.min_views, n_frames - 2))
    term = losses.warping_loss(ref, warped, warp.valid, visible, cfg.patch_sizes)
    warp_value, count = term.value, term.count

    loss = cfg.warp_weight * warp_value + cfg.render_weight * render_term.value
    smooth_value = 0.0
    if smooth and cfg.smooth_weight > 0 and cfg.smooth_blocks > 0:
        term = _smoothness(
            field, images, poses, camera, cfg.smooth_blocks, render_cfg, generator, prior
        )
        loss = loss + cfg.smooth_weight * term.value
        smooth_value = term.value.item()
    return WindowLoss(
        total=loss,
        warp=warp_value.item(),
        render=render_term.value.item(),
        smooth=smooth_value,
        warp_count=int(count),
        depth=out.depth,
    )


def _smoothness(
    field: FieldFn,
    images: torch.Tensor,
    poses: torch.Tensor,
    camera: Camera,
    blocks: int,
    render_cfg: RenderConfig,
    generator: torch.Generator | None,
    prior: DepthPrior | None = None,
) -> losses.LossTerm:
    """Render `blocks` random 2x2 pixel blocks and score their depth smoothness."""
    device = images.device
    frame = torch.randint(0, images.shape[0], (blocks,), generator=generator, device=device)
    u0 = torch.randint(0, camera.width - 1, (blocks,), generator=generator, device=device)
    v0 = torch.randint(0, camera.height - 1, (blocks,), generator=generator, device=device)
    du = torch.tensor([0, 1, 0, 1], device=device)
    dv = torch.tensor([0, 0, 1, 1], device=device)
    u = (u0[:, None] + du).reshape(-1)
    v = (v0[:, None] + dv).reshape(-1)
    f = frame[:, None].expand(blocks, 4).reshape(-1)
    uv = torch.stack([u, v], dim=-1).to(images.dtype)
    near = prior(f, uv) if prior is not None else None
    out = render_pixels(
        field, camera, uv, poses[f], render_cfg, generator, with_color=False, depth_prior=near
    )
    return losses.smoothness_loss(
        out.depth.view(blocks, 2, 2), images[f, v, u].view(blocks, 2, 2, 3)
    )

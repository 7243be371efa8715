"""Volume rendering of the occupancy field along camera rays (paper section 3.1).

Each ray gets `n_stratified` stratified samples in [near, far], then `importance_rounds`
rounds of `n_importance` samples drawn from the weights of the samples so far (32 + 4 x 16 = 96
in the paper). Only the final set is evaluated with gradients: the placement rounds run under
`no_grad` and skip the colour head.

Weights follow UNISURF: `w_i = o_i * prod_{j<i} (1 - o_j)`; depth is `sum w_i z_i`, colour
`sum w_i c_i`. Rays are parameterized by z-depth: a direction has z = 1 in the camera frame,
so the sample parameter *is* the z-depth and rendered depth is z-depth as design.md requires.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from dimslam.common.geometry.camera import Camera
from dimslam.common.geometry.shapes import check_shape
from dimslam.common.map.field import FieldOutput
from dimslam.common.options import option

SEEN = 1e-2
"""Transmittance below which a ray no longer sees: samples beyond it are not `observe`d."""

STOPPED = 0.5
"""Transmittance below which a ray has stopped: where its surface is, for the sparse map's
fine levels (`MapConfig.fine_band`). On a learned map the ray's `SEEN` lies about a map unit
behind it (room0, 60 frames: 0.76 / 0.97 / 1.94 at the 10th / 50th / 90th percentile)."""

FieldFn = Callable[..., FieldOutput]
"""A map: `(N, 3)` points (and `with_color=`) -> `FieldOutput` (e.g. `Field`)."""


@dataclass(frozen=True)
class RenderConfig:
    """Sampling along rays; depths in map units."""

    n_stratified: int = option(32, "Stratified samples per ray (paper: 32).")
    n_importance: int = option(16, "Samples added per importance round (paper: 16).")
    importance_rounds: int = option(4, "Importance rounds (paper: 4, so 96 samples in all).")
    near: float = option(0.1, "Nearest rendered depth.")
    far: float = option(8.0, "Farthest rendered depth.")
    surface_samples: int = option(
        0,
        "Mapping rounds: samples per ray around the depth the map rendered at the round's "
        "start, plus `coarse_samples` over [near, far], all in one pass with gradients, "
        "instead of the stratified and importance rounds (0: the paper's sampling).",
    )
    coarse_samples: int = option(8, "Stratified samples over [near, far] with surface sampling.")
    normalize_depth: bool = option(
        False,
        "Rendered depth is the mean depth of the ray's weights (their sum times depth divided "
        "by the ray's opacity; False: not divided, the paper's, which renders a ray that does "
        "not quite stop nearer than where it stops and so shrinks the map). On, the plane the "
        "map starts from is also made to stop every ray (mapper.prior_stop).",
    )
    normalize_floor: float = option(
        0.01,
        "Normalized depth divides by at least this opacity: a ray through empty space keeps a "
        "bounded depth and gradient; at 1 the depth is not divided at all.",
    )
    median_depth: bool = option(
        False,
        "Rendered depth is where the ray has stopped half of the light it stops (the median "
        "of its weights, interpolated within the sample interval that crosses it) instead of "
        "their mean: a surface whose light partly leaks behind it renders at the surface. "
        "Off: means over 3 seeds (cpu preset, with tracker.window_refine_deg 0.6 / _seen "
        "0.5) room3 18.59 -> 7.60 cm and room5 10.80 -> 6.45, but room0 3.29 -> 3.69 and "
        "7-Scenes 3.60 -> 4.55 (docs/results.md, 'The median depth').",
    )
    surface_band: float = option(
        0.15, "Surface samples cover the rendered depth +- this fraction of it."
    )

    def __post_init__(self) -> None:
        if self.median_depth and self.normalize_depth:
            raise ValueError(
                "render.median_depth and render.normalize_depth exclude each other: set one false"
            )
        if not 0 < self.normalize_floor <= 1:
            floor = self.normalize_floor
            raise ValueError(f"render.normalize_floor must be in (0, 1], got {floor}")


@dataclass(frozen=True)
class RenderOutput:
    """Per-ray results for R rays.

    Attributes:
        depth: `(R,)` expected z-depth.
        rgb: `(R, 3)` expected colour.
        opacity: `(R,)` sum of the weights (1 where the ray hits a surface).
    """

    depth: torch.Tensor
    rgb: torch.Tensor
    opacity: torch.Tensor


def camera_rays(
    camera: Camera, uv: torch.Tensor, T_wc: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """World-frame rays through pixels.

    Args:
        camera: intrinsics of the image the pixels belong to.
        uv: `(R, 2)` pixel coordinates.
        T_wc: `(4, 4)` or `(R, 4, 4)` camera-to-world poses.

    Returns:
        `(origins (R, 3), directions (R, 3))`; a direction has unit z in the camera frame.
    """
    check_shape("uv", uv, (None, 2))
    ones = torch.ones_like(uv[:, 0])
    d_c = camera.unproject(uv, ones)
    R = T_wc[..., :3, :3]
    directions = (R @ d_c[..., None])[..., 0] if T_wc.dim() == 3 else d_c @ R.t()
    origins = T_wc[..., :3, 3].expand_as(directions)
    return origins, directions


def ray_weights(occupancy: torch.Tensor) -> torch.Tensor:
    """Termination weights `(R, S)` from occupancies `(R, S)` ordered along each ray."""
    free = torch.cumprod(1 - occupancy, dim=-1)
    transmittance = torch.cat([torch.ones_like(free[:, :1]), free[:, :-1]], dim=-1)
    return occupancy * transmittance


def sample_pdf(
    t: torch.Tensor, weights: torch.Tensor, count: int, generator: torch.Generator | None
) -> torch.Tensor:
    """Draw `count` depths per ray from the weights of samples `t` (both `(R, S)`, t sorted).

    Each sample owns the interval from the previous sample up to itself: a ray terminates at
    the first occupied sample, so the surface lies *before* it, and that whole gap must be
    refined (midpoint intervals would leave the near half of it unsampled). The density is
    piecewise constant on those intervals (inverse-CDF sampling). Stratified uniforms when a
    generator is given, evenly spaced quantiles otherwise.
    """
    first = t[:, :1] - (t[:, 1:2] - t[:, :1])  # the first sample's interval mirrors the second's
    edges = torch.cat([first, t], dim=-1)  # (R, S + 1)
    pdf = weights + 1e-5  # a flat floor keeps empty rays sampling everywhere
    pdf = pdf / pdf.sum(dim=-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), torch.cumsum(pdf, dim=-1)], dim=-1)
    steps = torch.arange(count, device=t.device, dtype=t.dtype)
    if generator is not None:
        jitter = torch.rand(t.shape[0], count, device=t.device, dtype=t.dtype, generator=generator)
    else:
        jitter = torch.full((t.shape[0], count), 0.5, device=t.device, dtype=t.dtype)
    u = ((steps + jitter) / count).clamp(0, 1 - 1e-6)
    idx = torch.searchsorted(cdf.contiguous(), u.contiguous(), right=True).clamp(1, pdf.shape[1])
    c0, c1 = cdf.gather(1, idx - 1), cdf.gather(1, idx)
    e0, e1 = edges.gather(1, idx - 1), edges.gather(1, idx)
    frac = (u - c0) / (c1 - c0).clamp_min(1e-12)
    return e0 + frac * (e1 - e0)


def sample_depths(
    field: FieldFn,
    origins: torch.Tensor,
    directions: torch.Tensor,
    cfg: RenderConfig,
    generator: torch.Generator | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Sorted sample depths `(R, S)`: stratified plus importance rounds, without gradients;
    how far each ray sees `(R,)`: the depth of the first evaluated sample where the
    transmittance falls below `SEEN` (beyond it nothing the ray renders can change); and
    where it stops `(R,)`: the same for `STOPPED` (`cfg.far` where it does not)."""
    R = origins.shape[0]
    with torch.no_grad():
        t = _stratified(cfg.near, cfg.far - cfg.near, R, cfg.n_stratified, origins, generator)
        occ = _occupancy(field, origins, directions, t)
        seen_t = t
        for round_ in range(cfg.importance_rounds):
            extra = sample_pdf(t, ray_weights(occ), cfg.n_importance, generator)
            t, order = torch.sort(torch.cat([t, extra], dim=-1), dim=-1)
            if round_ + 1 < cfg.importance_rounds:
                # Only the new samples are evaluated: the earlier ones keep their occupancy.
                occ_extra = _occupancy(field, origins, directions, extra)
                occ = torch.cat([occ, occ_extra], dim=-1).gather(1, order)
                seen_t = t
        transmittance = torch.cumprod(1 - occ, dim=-1)
        reach, stop = (_first_below(transmittance, seen_t, x, cfg.far) for x in (SEEN, STOPPED))
    return t, reach, stop


def _first_below(
    transmittance: torch.Tensor, t: torch.Tensor, level: float, far: float
) -> torch.Tensor:
    """`(R,)` depth of each ray's first sample (of `t` `(R, S)`) whose transmittance is below
    `level`; `far` where none is."""
    below = transmittance < level
    first = torch.where(below.any(dim=-1), below.float().argmax(dim=-1), -1)
    depth = t.gather(1, first[:, None].clamp_min(0))[:, 0]
    return torch.where(first >= 0, depth, torch.full_like(depth, far))


def _stratified(
    lo, span, rays: int, count: int, like: torch.Tensor, generator: torch.Generator | None
) -> torch.Tensor:
    """`(rays, count)` depths stratified in [lo, lo + span] (floats, or `(rays, 1)`): jittered
    when a generator is given, interval midpoints otherwise; `like` gives device and dtype."""
    steps = torch.arange(count, device=like.device, dtype=like.dtype)
    shape = (rays, count)
    if generator is not None:
        u = torch.rand(shape, device=like.device, dtype=like.dtype, generator=generator)
    else:
        u = torch.full(shape, 0.5, device=like.device, dtype=like.dtype)
    return lo + span * (steps + u) / count


def surface_depths(
    depth: torch.Tensor, cfg: RenderConfig, generator: torch.Generator | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Sorted sample depths `(R, S)` around known depths `(R,)`: `surface_samples` stratified
    in `depth * (1 +- surface_band)` plus `coarse_samples` stratified over [near, far]; how
    far each ray sees (the end of its band); and where it stops (the known depth)."""
    R = depth.shape[0]

    def stratified(lo: torch.Tensor, hi: torch.Tensor, count: int) -> torch.Tensor:
        return _stratified(lo[:, None], (hi - lo)[:, None], R, count, depth, generator)

    d = depth.clamp(cfg.near, cfg.far)
    lo = (d * (1 - cfg.surface_band)).clamp_min(cfg.near)
    hi = (d * (1 + cfg.surface_band)).clamp_max(cfg.far)
    near = torch.full_like(d, cfg.near)
    far = torch.full_like(d, cfg.far)
    t = torch.cat(
        [stratified(near, far, cfg.coarse_samples), stratified(lo, hi, cfg.surface_samples)], -1
    )
    return torch.sort(t, dim=-1).values, hi, d


def _occupancy(
    field: FieldFn, origins: torch.Tensor, directions: torch.Tensor, t: torch.Tensor
) -> torch.Tensor:
    """Occupancy `(R, S)` at depths `t` `(R, S)` along rays `(R, 3)`."""
    points = origins[:, None] + t[..., None] * directions[:, None]
    return field(points.reshape(-1, 3), with_color=False).occupancy.view(t.shape)


def render_rays(
    field: FieldFn,
    origins: torch.Tensor,
    directions: torch.Tensor,
    cfg: RenderConfig,
    generator: torch.Generator | None = None,
    with_color: bool = True,
    depth_prior: torch.Tensor | None = None,
) -> RenderOutput:
    """Render depth and colour of rays `(R, 3)`; gradients reach the field and the rays.

    Args:
        field: the map.
        origins: `(R, 3)` ray origins (camera centres) in map coordinates.
        directions: `(R, 3)` directions with unit z in their camera's frame.
        cfg: sampling configuration.
        generator: random source for stratified jitter; None renders deterministically.
        with_color: False skips the colour head (depth-only rendering, e.g. for tracking
            geometry); `rgb` is then zeros.
        depth_prior: `(R,)` depths the rays are known to end near: sampled around them
            (`surface_depths`) where `cfg.surface_samples` > 0.
    """
    check_shape("origins", origins, (None, 3))
    check_shape("directions", directions, (origins.shape[0], 3))
    if depth_prior is not None and cfg.surface_samples > 0:
        t, reach, stop = surface_depths(depth_prior, cfg, generator)
    else:
        t, reach, stop = sample_depths(field, origins, directions, cfg, generator)
    R, S = t.shape
    points = origins[:, None] + t[..., None] * directions[:, None]
    observe = getattr(field, "observe", None)
    if observe is not None and torch.is_grad_enabled():
        seen = t <= reach[:, None]
        stops = stop < cfg.far  # the ray's transmittance fell: it ends at a surface
        surface = torch.where(stops[:, None], (t - stop[:, None]).abs(), torch.inf)
        observe(points[seen], surface[seen])
    out = field(points.reshape(-1, 3), with_color=with_color)
    w = ray_weights(out.occupancy.view(R, S))
    depth = median_depth(w, t) if cfg.median_depth else (w * t).sum(dim=-1)
    rgb = (w[..., None] * out.rgb.view(R, S, 3)).sum(dim=1)
    opacity = w.sum(dim=-1)
    if cfg.normalize_depth:
        depth = depth / opacity.clamp_min(cfg.normalize_floor)
    return RenderOutput(depth=depth, rgb=rgb, opacity=opacity)


def median_depth(w: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Depth `(R,)` where each ray's cumulative weight reaches half its sum, from weights and
    sorted sample depths `(R, S)`. Sample i owns the interval from sample i - 1 up to itself
    (`sample_pdf`): the crossing is placed within it by linear interpolation, so the depth is
    differentiable in the weights up to and including the crossing sample and in the ray's
    opacity."""
    cum = torch.cumsum(w, dim=-1)
    half = 0.5 * cum[:, -1:]
    i = torch.searchsorted(cum.detach().contiguous(), half.detach().contiguous())
    i = i.clamp_max(w.shape[1] - 1)
    w_i = w.gather(1, i)
    before = cum.gather(1, i) - w_i
    t_i = t.gather(1, i)
    t_prev = t.gather(1, (i - 1).clamp_min(0))
    share = (half - before) / w_i.clamp_min(1e-8)
    return (t_prev + (t_i - t_prev) * share)[:, 0]


def render_pixels(
    field: FieldFn,
    camera: Camera,
    uv: torch.Tensor,
    T_wc: torch.Tensor,
    cfg: RenderConfig,
    generator: torch.Generator | None = None,
    with_color: bool = True,
    depth_prior: torch.Tensor | None = None,
) -> RenderOutput:
    """`render_rays` for pixels `(R, 2)` of a camera at `T_wc` (`(4, 4)` or `(R, 4, 4)`)."""
    origins, directions = camera_rays(camera, uv, T_wc)
    return render_rays(field, origins, directions, cfg, generator, with_color, depth_prior)


def render_chunked(
    field: FieldFn,
    camera: Camera,
    uv: torch.Tensor,
    T_wc: torch.Tensor,
    cfg: RenderConfig,
    chunk: int = 4096,
    with_color: bool = True,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """`render_pixels` over any number of pixels `(R, 2)`, `chunk` rays at a time (bounds the
    memory), without gradients: depth `(R,)` and colour `(R, 3)` (None without colour)."""
    depths, colours = [], []
    with torch.no_grad():
        for start in range(0, uv.shape[0], chunk):
            out = render_pixels(
                field, camera, uv[start : start + chunk], T_wc, cfg, None, with_color
            )
            depths.append(out.depth)
            colours.append(out.rgb)
    depth = torch.cat(depths) if depths else uv.new_zeros(0)
    return depth, torch.cat(colours) if with_color and colours else None


def render_image(
    field: FieldFn,
    camera: Camera,
    T_wc: torch.Tensor,
    cfg: RenderConfig,
    chunk: int = 4096,
) -> tuple[torch.Tensor, torch.Tensor]:
    """A whole `(H, W)` depth and `(H, W, 3)` colour image, in chunks, without gradients."""
    depth, colour = render_chunked(field, camera, camera.pixels(T_wc.device), T_wc, cfg, chunk)
    shape = (camera.height, camera.width)
    return depth.view(shape), colour.view(*shape, 3)


class DepthPrior:
    """Where each frame's rays end, as the map rendered them once (at `width` px, nearest
    pixel): the depths `surface_depths` samples around, in a mapping round whose map and
    poses move little."""

    def __init__(
        self,
        field: FieldFn,
        camera: Camera,
        poses: torch.Tensor,
        cfg: RenderConfig,
        width: int = 40,
    ) -> None:
        small = camera.resized(min(width, camera.width))
        self.scale = torch.tensor(
            [small.width / camera.width, small.height / camera.height], device=poses.device
        )
        self.size = (small.width, small.height)
        self.depths = torch.stack([render_image(field, small, T, cfg)[0] for T in poses])

    def __call__(self, frame: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
        """`(M,)` depths of pixels `uv` `(M, 2)` of window frames `frame` `(M,)`."""
        small = ((uv + 0.5) * self.scale).long()
        u = small[:, 0].clamp(0, self.size[0] - 1)
        v = small[:, 1].clamp(0, self.size[1] - 1)
        return self.depths[frame, v, u]

"""Multi-view depth of a keyframe by plane sweep: where its pixels are, searched, not guessed.

The map renders, where no frame has looked yet, one depth in every direction, whatever its
first plane taught the decoder to make of empty grids (on room3, one thread, the map behind
frame 0 renders 1.97-2.06 map units: about the gauge depth). The window objective then only
refines that depth by gradient descent on warped patches, whose reach is a few pixels of
disparity: a far wall seen with little parallax may stay near the prior depth. (On room3
the map's scale fell from 0.89 to 0.49 of the start's between frames 20 and 100,
`benchmarks/diagnose.py run --depth-every`; the sweep's target holds the first 60 frames'
scale but not the fall in the turn that follows, and whole runs are not better with it:
docs/results.md, "Where the scale goes".)

A plane sweep looks at every depth: for each pixel of the keyframe and each of `planes`
inverse depths between `near` and `far`, its 5x5 patch is compared with where that depth
lands in each source frame (zero-mean normalized cross-correlation, so exposure changes do not
matter), the better half of the sources' costs is averaged (a pixel occluded in some sources
still matches in the others), and the best depth wins. It is kept only where it is clearly
the best (textured patch, good correlation, no rival depth nearly as good away from it) and
refined between planes by a parabola. The mapper uses the kept depths as a soft target for
the depth it renders (`MapperConfig.stereo_weight`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from dimslam.common.geometry import pose
from dimslam.common.geometry.camera import Camera
from dimslam.tracker.photometric import grey

PATCH = 5
"""Side of the compared patches (pixels at the sweep's resolution)."""
CV_CHANNELS = 512
"""The most channels an OpenCV image may have (`CV_CN_MAX`)."""
PLANES = 64
"""Inverse depths searched, evenly spaced between the nearest and the farthest."""
WIDTH = 160
"""Width of the images the sweep compares (half the cpu preset's frames)."""
MIN_TEXTURE = 0.02
"""A patch whose grey values (in [0, 1]) vary less than this has nothing to match."""
MAX_COST = 0.5
"""Largest kept cost (1 - correlation of the better half of the sources)."""
UNIQUE = 0.8
"""The best cost must be below this share of the best one more than `RIVAL` planes away."""
RIVAL = 3
"""Planes within this distance of the best belong to its minimum, not rivals to it."""
MIN_TRAVEL = 2.0
"""A source counts for a pixel only where the searched depths spread that pixel's match over
at least this many pixels (at the sweep's resolution): with less parallax every depth
matches alike."""


@dataclass(frozen=True)
class SweepDepth:
    """A keyframe's multi-view depth.

    Attributes:
        depth: `(H, W)` z-depth at the sweep's resolution, NaN where not kept.
        camera: the camera of that resolution.
    """

    depth: torch.Tensor
    camera: Camera

    @property
    def kept(self) -> float:
        """Share of the pixels with a depth."""
        return float(torch.isfinite(self.depth).float().mean())


def sample_depths(
    depths: torch.Tensor, small: Camera, frame: torch.Tensor, uv: torch.Tensor, camera: Camera
) -> torch.Tensor:
    """Sweep depths `(F, h, w)` (at `small`'s size) at pixels `(N, 2)` of `camera` (the same
    views at any size) in frames `(N,)`: nearest sweep pixel, NaN where none was kept."""
    sx, sy = small.width / camera.width, small.height / camera.height
    u = ((uv[:, 0] + 0.5) * sx - 0.5).round().long().clamp(0, small.width - 1)
    v = ((uv[:, 1] + 0.5) * sy - 0.5).round().long().clamp(0, small.height - 1)
    return depths[frame, v, u]


def _box(x: torch.Tensor) -> torch.Tensor:
    """Mean over the `PATCH` x `PATCH` neighbourhoods of `(N, H, W)` images (same size;
    at the edges over the pixels inside). On a CPU by OpenCV's running sums, all images at
    once as the channels of one: several times faster than torch's pooling, which sums
    every patch afresh and which a GPU (or a gradient) keeps (docs/benchmarks.md, "Mesh
    extraction")."""
    opencv = x.device.type == "cpu" and x.dtype == torch.float32 and len(x) <= CV_CHANNELS
    if not opencv or x.requires_grad:
        pooled = F.avg_pool2d(
            x[:, None], PATCH, stride=1, padding=PATCH // 2, count_include_pad=False
        )
        return pooled[:, 0]
    window, edge = (PATCH, PATCH), cv2.BORDER_CONSTANT
    channels = x.permute(1, 2, 0).contiguous().numpy()
    sums = cv2.boxFilter(channels, -1, window, normalize=False, borderType=edge)
    inside = cv2.boxFilter(
        np.ones(channels.shape[:2], np.float32), -1, window, normalize=False, borderType=edge
    )
    sums = sums.reshape(channels.shape) / inside[:, :, None]
    return torch.from_numpy(sums).permute(2, 0, 1)


def _small(rgb: torch.Tensor, camera: Camera) -> torch.Tensor:
    """`(H, W)` grey image of `rgb` (`(H0, W0, 3)`, [0, 1]) at `camera`'s size."""
    image = grey(rgb)[None, None]
    if image.shape[-2:] != (camera.height, camera.width):
        image = F.interpolate(image, size=(camera.height, camera.width), mode="area")
    return image[0, 0]


def plane_sweep(
    rgb: torch.Tensor,
    T_wc: torch.Tensor,
    sources: list[tuple[torch.Tensor, torch.Tensor]],
    camera: Camera,
    near: float,
    far: float,
    planes: int = PLANES,
    width: int = WIDTH,
) -> SweepDepth:
    """The depth of the view `rgb` at `T_wc` from `sources` (`(rgb, T_wc)` of other frames).

    Args:
        rgb: `(H, W, 3)` the keyframe's image in [0, 1], `camera`'s size.
        T_wc: its pose.
        sources: the frames it is compared with (their poses fix the depth's scale).
        camera: the full-size camera.
        near, far: the searched depth range (map units).
        planes: inverse depths searched, evenly spaced.
        width: the sweep's image width (pixels; the height keeps the aspect).
    """
    if not sources:
        raise ValueError("a plane sweep needs at least one source frame")
    small = camera.resized(min(width, camera.width))
    H, W = small.height, small.width
    device = rgb.device
    ref = _small(rgb, small)
    mean_r = _box(ref[None])[0]
    var_r = (_box((ref * ref)[None])[0] - mean_r**2).clamp_min(0)
    textured = var_r.sqrt() > MIN_TEXTURE

    rays = small.unproject(small.pixels(device), torch.ones(H * W, device=device))
    inverse = torch.linspace(1 / near, 1 / far, planes, device=device)  # near to far
    costs = []
    for src_rgb, T_src in sources:
        image = _small(src_rgb, small)
        T_sr = pose.compose(pose.invert(T_src), T_wc)
        a = rays @ T_sr[:3, :3].T  # (HW, 3): the ray's direction in the source
        p = a[None] / inverse[:, None, None] + T_sr[:3, 3]  # (P, HW, 3)
        uv, z = small.project(p)
        grid = torch.stack([(uv[..., 0] + 0.5) / W * 2 - 1, (uv[..., 1] + 0.5) / H * 2 - 1], -1)
        seen = (z > 1e-3) & (grid.abs() <= 1).all(-1)
        travel = (uv[0] - uv[-1]).norm(dim=-1).nan_to_num(0.0)  # (HW,) over the whole search
        seen = seen & (travel >= MIN_TRAVEL)
        warped = F.grid_sample(
            image[None, None].expand(planes, 1, H, W),
            grid.view(planes, H, W, 2),
            mode="bilinear",
            padding_mode="border",
            align_corners=False,
        )[:, 0]
        mean_w = _box(warped)
        var_w = (_box(warped * warped) - mean_w**2).clamp_min(0)
        cov = _box(warped * ref[None]) - mean_w * mean_r[None]
        ncc = cov / (var_w * var_r[None] + 1e-8).sqrt()
        whole = _box(seen.view(planes, H, W).float()) > 0.999  # the whole patch in view
        costs.append(torch.where(whole, 1 - ncc, torch.full_like(ncc, math.inf)))
    cost = torch.stack(costs)  # (S, P, H, W)
    keep = max(1, (len(sources) + 1) // 2)
    best_sources = cost.sort(dim=0).values[:keep]
    total = best_sources.mean(dim=0)  # (P, H, W): inf where fewer than `keep` sources see it

    best, index = total.min(dim=0)
    planes_idx = torch.arange(planes, device=device)[:, None, None]
    rivals = total.masked_fill((planes_idx - index[None]).abs() <= RIVAL, math.inf)
    rival = rivals.min(dim=0).values
    inner = (index > 0) & (index < planes - 1)
    good = textured & inner & torch.isfinite(best) & (best < MAX_COST) & (best < UNIQUE * rival)

    # Sub-plane refinement: the parabola through the best plane and its two neighbours.
    i0 = (index - 1).clamp(0, planes - 1)
    i2 = (index + 1).clamp(0, planes - 1)
    c0 = total.gather(0, i0[None])[0]
    c2 = total.gather(0, i2[None])[0]
    curve = c0 - 2 * best + c2
    shift = torch.where(curve > 1e-6, 0.5 * (c0 - c2) / curve, torch.zeros_like(curve))
    shift = shift.clamp(-0.5, 0.5)
    step = inverse[1] - inverse[0]
    inv = inverse[index] + shift * step
    good = good & torch.isfinite(inv) & (inv > 0)
    depth = torch.where(good, 1 / inv.clamp_min(1e-6), torch.full_like(inv, math.nan))
    return SweepDepth(depth, small)


def consistent_depths(
    depths: torch.Tensor,
    T_wc: torch.Tensor,
    camera: Camera,
    tolerance: float = 0.02,
    neighbours: int = 3,
    agree: int = 1,
) -> torch.Tensor:
    """`depths` (`(V, H, W)` z-depth at `camera`'s size, NaN where unknown, views at poses
    `T_wc` `(V, 4, 4)` in path order) kept only where they are multi-view consistent: a
    pixel's point, seen by at least `agree` of the `neighbours` views before and after its own,
    lands where that view's depth is within `tolerance` (relative) of the point's. A plane
    sweep keeps wrong matches that look unique (repeated texture, occlusion edges); two
    sweeps against other sources rarely make the same mistake."""
    V, H, W = depths.shape
    uv = camera.pixels()
    T_cw = pose.invert(T_wc)
    out = torch.full_like(depths, math.nan)
    for a in range(V):
        d = depths[a].reshape(-1)
        known = torch.isfinite(d)
        points = pose.transform_points(T_wc[a], camera.unproject(uv[known], d[known]))
        votes = torch.zeros(len(points))
        for b in range(max(0, a - neighbours), min(V, a + neighbours + 1)):
            if b == a:
                continue
            q, z = camera.project(pose.transform_points(T_cw[b], points))
            col, row = q[:, 0].round(), q[:, 1].round()
            inside = (z > 0) & (col >= 0) & (col < W) & (row >= 0) & (row < H)
            seen = torch.full_like(z, math.nan)
            seen[inside] = depths[b][row[inside].long(), col[inside].long()]
            votes += ((seen - z).abs() < tolerance * z).float()  # NaN compares False
        kept = d[known].clone()
        kept[votes < agree] = math.nan
        out[a].view(-1)[known] = kept
    return out


def _smooth(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """`(N, H, W)` images blurred by a Gaussian of `sigma` pixels (separable, edges repeated)."""
    half = max(1, int(3 * sigma))
    taps = torch.exp(-(torch.arange(-half, half + 1, dtype=torch.float32) ** 2) / (2 * sigma**2))
    taps = taps / taps.sum()
    x = F.pad(x[:, None], (half, half, 0, 0), mode="replicate")
    x = F.conv2d(x, taps.view(1, 1, 1, -1))
    x = F.pad(x, (0, 0, half, half), mode="replicate")
    return F.conv2d(x, taps.view(1, 1, -1, 1))[:, 0]


def agreeing_depths(
    rendered: torch.Tensor, sweeps: torch.Tensor, gate: float, sigma: float, support: float
) -> torch.Tensor:
    """The `rendered` depth (`(V, H, W)`, the map's, NaN where not rendered) left out (NaN)
    where the same views' multi-view depth `sweeps` (NaN where unknown) around it says it is
    off: where the sweep/map depth ratio, averaged over a Gaussian of `sigma` pixels over the
    pixels that have both, is more than `gate` from 1, and the sweeps cover at least
    `support` of the Gaussian's weight there. Where the map was fitted to other poses than
    the current ones (an adjustment moved them), it renders its surfaces too deep or too near
    over whole regions; the sweep, found at the current poses, shows which."""
    found = torch.isfinite(sweeps)
    both = found & torch.isfinite(rendered) & (rendered > 0)
    ratio = torch.where(both, sweeps / rendered.clamp_min(1e-6), torch.zeros_like(rendered))
    weight = _smooth(both.float(), sigma)
    local = _smooth(ratio, sigma) / weight.clamp_min(1e-6)
    covered = (_smooth(found.float(), sigma) >= support) & (weight > 1e-3)
    off = covered & ((local - 1).abs() > gate)
    return torch.where(off, torch.full_like(rendered, math.nan), rendered)

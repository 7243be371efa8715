"""The neural implicit map: multi-resolution dense feature grids plus a small MLP decoder.

Paper section 3.1 / design.md section 3. A point `p` (map units) is encoded by trilinear
lookups in L dense grids of decreasing voxel size (one geometry channel each), concatenated;
an MLP (3 hidden layers of 32, ReLU) decodes the occupancy logit. Colour comes from a second
head that reads the decoder's last hidden layer plus a few colour channels stored on the finest
levels: six geometry scalars alone are too weak for texture (design.md allows this; the
public code reads 3 colour channels from its two finest levels).

Occupancy is `sigmoid(logit)` inside the scene bound and exactly 0 outside it: monocular input
has no known room size, so the bound is a generous box around the first camera (config).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from dimslam.common.geometry.shapes import check_shape
from dimslam.common.options import option


@dataclass(frozen=True)
class MapConfig:
    """Shape of the implicit map. Lengths are in map units (the scale gauge makes them ~metres)."""

    voxel_sizes: tuple[float, ...] = option(
        (0.64, 0.48, 0.32, 0.24, 0.16, 0.08),
        "Voxel size of each geometry grid, coarse to fine (paper: 64/48/32/24/16/8 cm).",
    )
    geometry_channels: int = option(1, "Feature channels per geometry grid (paper: 1).")
    color_channels: int = option(
        3, "Colour feature channels on each of the `color_levels` finest grids (0: none)."
    )
    color_levels: int = option(2, "How many of the finest levels also store colour features.")
    hidden: int = option(32, "Width of the decoder's hidden layers.")
    layers: int = option(3, "Number of hidden layers of the decoder.")
    init_std: float = option(
        0.001, "Standard deviation of the grids' normal initialization (paper: 0.001)."
    )
    bound: tuple[float, ...] = option(
        (-6.0, -6.0, -6.0, 6.0, 6.0, 6.0),
        "Scene box (xmin, ymin, zmin, xmax, ymax, zmax) in the first camera's frame.",
    )


@dataclass(frozen=True)
class FieldOutput:
    """What the decoder says about a batch of points.

    Attributes:
        occupancy: `(N,)` probability in [0, 1], 0 outside the bound.
        rgb: `(N, 3)` colour in [0, 1].
    """

    occupancy: torch.Tensor
    rgb: torch.Tensor


class Field(nn.Module):
    """Feature grids and decoder; call it on `(N, 3)` points to get a `FieldOutput`."""

    def __init__(self, cfg: MapConfig, device: torch.device | str | None = None) -> None:
        super().__init__()
        self.cfg = cfg
        if len(cfg.bound) != 6:
            raise ValueError(f"map bound needs 6 numbers (min xyz, max xyz), got {cfg.bound}")
        bound = torch.tensor(cfg.bound, dtype=torch.float32).view(2, 3)
        if not torch.all(bound[1] > bound[0]):
            raise ValueError(f"map bound must have min < max on every axis, got {cfg.bound}")
        self.register_buffer("bound", bound)
        self.geometry = nn.ParameterList()
        self.color = nn.ParameterList()
        spans = []
        n_color = cfg.color_levels if cfg.color_channels > 0 else 0
        for level, voxel in enumerate(cfg.voxel_sizes):
            # Cells cover the bound exactly; align_corners=True puts -1/+1 on the end vertices.
            counts = [math.ceil(float(e) / voxel) + 1 for e in bound[1] - bound[0]]
            spans.append([(n - 1) * voxel for n in counts])
            shape = (1, cfg.geometry_channels, counts[2], counts[1], counts[0])
            self.geometry.append(nn.Parameter(torch.randn(shape) * cfg.init_std))
            if level >= len(cfg.voxel_sizes) - n_color:
                shape = (1, cfg.color_channels, counts[2], counts[1], counts[0])
                self.color.append(nn.Parameter(torch.randn(shape) * cfg.init_std))
        self.register_buffer("spans", torch.tensor(spans, dtype=torch.float32))  # (L, 3)
        self.n_color_levels = n_color

        width = cfg.hidden
        layers: list[nn.Module] = []
        size_in = cfg.geometry_channels * len(cfg.voxel_sizes)
        for _ in range(cfg.layers):
            layers += [nn.Linear(size_in, width), nn.ReLU()]
            size_in = width
        self.trunk = nn.Sequential(*layers)
        self.occupancy_head = nn.Linear(width, 1)
        color_in = width + cfg.color_channels * n_color
        self.color_head = nn.Sequential(nn.Linear(color_in, width), nn.ReLU(), nn.Linear(width, 3))
        if device is not None:
            self.to(device)

    def grid_parameters(self) -> list[nn.Parameter]:
        """The feature grids (geometry and colour): the map's local memory."""
        return [*self.geometry, *self.color]

    def decoder_parameters(self) -> list[nn.Parameter]:
        """The MLP decoder's weights."""
        return [
            *self.trunk.parameters(),
            *self.occupancy_head.parameters(),
            *self.color_head.parameters(),
        ]

    def _normalized(self, p: torch.Tensor, level: int) -> torch.Tensor:
        return (p - self.bound[0]) / self.spans[level] * 2 - 1

    def _lookup(self, grid: torch.Tensor, p: torch.Tensor, level: int) -> torch.Tensor:
        """Trilinear lookup of `(N, 3)` points in one `(1, C, D, H, W)` grid -> `(N, C)`."""
        coords = self._normalized(p, level).view(1, 1, 1, -1, 3)
        out = F.grid_sample(
            grid, coords, mode="bilinear", padding_mode="border", align_corners=True
        )
        return out.view(grid.shape[1], -1).t()

    def geometry_features(self, p: torch.Tensor) -> torch.Tensor:
        """`(N, L * C)` concatenated geometry features of points `(N, 3)`."""
        return torch.cat([self._lookup(g, p, i) for i, g in enumerate(self.geometry)], dim=-1)

    def inside(self, p: torch.Tensor) -> torch.Tensor:
        """`(N,)` bool: points inside the scene bound."""
        return ((p >= self.bound[0]) & (p <= self.bound[1])).all(dim=-1)

    def forward(self, p: torch.Tensor, with_color: bool = True) -> FieldOutput:
        """Occupancy and colour of points `(N, 3)` in map coordinates."""
        check_shape("p", p, (None, 3))
        hidden = self.trunk(self.geometry_features(p))
        logit = self.occupancy_head(hidden)[:, 0]
        occupancy = torch.sigmoid(logit) * self.inside(p)
        if not with_color:
            return FieldOutput(occupancy, torch.zeros_like(p))
        first = len(self.geometry) - self.n_color_levels
        colour_feats = [self._lookup(g, p, first + i) for i, g in enumerate(self.color)]
        rgb = torch.sigmoid(self.color_head(torch.cat([hidden, *colour_feats], dim=-1)))
        return FieldOutput(occupancy, rgb)

    def occupancy(self, p: torch.Tensor) -> torch.Tensor:
        """`(N,)` occupancy probabilities only (cheaper: skips the colour head)."""
        return self.forward(p, with_color=False).occupancy

    def memory_bytes(self) -> int:
        """Bytes held by all parameters (grids and decoder)."""
        return sum(t.numel() * t.element_size() for t in self.parameters())

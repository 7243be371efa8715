"""The neural implicit map: multi-resolution feature grids plus a small MLP decoder.

Paper section 3.1 / design.md section 3. A point `p` (map units) is encoded by trilinear
lookups in L grids of decreasing voxel size (one geometry channel each), concatenated;
an MLP (3 hidden layers of 32, ReLU) decodes the occupancy logit. Colour comes from a second
head that reads the decoder's last hidden layer plus a few colour channels stored on the finest
levels: six geometry scalars alone are too weak for texture (design.md allows this; the
public code reads 3 colour channels from its two finest levels).

The grids are dense tensors over a fixed box (`DenseField`, the paper's) or blocks of cells
stored where the mapper's rays have looked (`SparseField`, `common/map/sparse.py`): memory
and optimizer work then follow the scene instead of a box.
"""

from __future__ import annotations

import math
from contextlib import contextmanager
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from dimslam.common.geometry.shapes import check_shape
from dimslam.common.map.sparse import SparseGrids
from dimslam.common.options import option

OBSERVED = 1024
"""At most about this many points of each rendered batch are considered for storing cells."""


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
        "Scene box (xmin, ymin, zmin, xmax, ymax, zmax) in the first camera's frame "
        "(dense grids only: sparse ones have no bound).",
    )
    fine_band: float = option(
        0.0,
        "Sparse grids: the finest levels (those with colour) are stored only within this "
        "distance of where rays stop (their transmittance falls to one half), map units "
        "(0: wherever rays see, as the coarse levels).",
    )
    reclaim_every: int = option(
        0,
        "Sparse grids with `fine_band`: every this many mapping rounds (and after the "
        "initialization) the finest levels forget the blocks that no keyframe's ray now stops "
        "near: what the band stored where surfaces used to render (0: never).",
    )
    grids: str = option(
        "dense",
        "dense: every cell of the bound stored; sparse: blocks of cells stored where the "
        "mapper's rays have looked, growing with the scene (common/map/sparse.py).",
    )

    def __post_init__(self) -> None:
        if self.reclaim_every < 0:
            raise ValueError(f"map.reclaim_every must be >= 0, got {self.reclaim_every}")
        if self.reclaim_every and (self.grids != "sparse" or self.fine_band <= 0):
            raise ValueError(
                "map.reclaim_every needs map.grids sparse and map.fine_band > 0: only the "
                "band's blocks are forgotten, and without one rays store them again at once"
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
    """Feature grids and decoder; call it on `(N, 3)` points to get a `FieldOutput`.

    The decoder lives here; `DenseField` and `SparseField` store the grids (`make_field`
    picks one from the config).
    """

    def __init__(self, cfg: MapConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.n_color_levels = cfg.color_levels if cfg.color_channels > 0 else 0
        self.grows = False
        width = cfg.hidden
        layers: list[nn.Module] = []
        size_in = cfg.geometry_channels * len(cfg.voxel_sizes)
        for _ in range(cfg.layers):
            layers += [nn.Linear(size_in, width), nn.ReLU()]
            size_in = width
        self.trunk = nn.Sequential(*layers)
        self.occupancy_head = nn.Linear(width, 1)
        color_in = width + cfg.color_channels * self.n_color_levels
        self.color_head = nn.Sequential(nn.Linear(color_in, width), nn.ReLU(), nn.Linear(width, 3))

    bound: torch.Tensor
    """`(2, 3)` min and max corner of the region the grids store, map units."""

    def grid_parameters(self) -> list[nn.Parameter]:
        """The feature grids (geometry and colour): the map's local memory."""
        raise NotImplementedError

    def geometry_features(self, p: torch.Tensor) -> torch.Tensor:
        """`(N, L * C)` concatenated geometry features of points `(N, 3)`, coarse to fine."""
        raise NotImplementedError

    def color_features(self, p: torch.Tensor) -> torch.Tensor:
        """`(N, color_levels * color_channels)` colour features of points `(N, 3)`."""
        raise NotImplementedError

    def inside(self, p: torch.Tensor) -> torch.Tensor:
        """`(N,)` bool: points where the map may be occupied."""
        raise NotImplementedError

    def allocate(self, points: torch.Tensor, surface: torch.Tensor | None = None) -> None:
        """Store the cells around `(N, 3)` points (grids that grow; others hold every cell);
        `surface`: each point's distance to where its ray stops (inf: it does not)."""

    def observe(self, points: torch.Tensor, surface: torch.Tensor | None = None) -> None:
        """Rays see `(N, 3)` points (`surface`: as in `allocate`); grids that grow store their
        cells while `learning`."""

    def adopt_growth(self, optimizer: torch.optim.Optimizer | None = None) -> None:
        """Before an optimizer step: fit it to grids that grew since the last one."""

    def follow(self, optimizer: torch.optim.Optimizer) -> torch.optim.Optimizer:
        """Hook `optimizer` (over this field's parameters, fresh) up to grids that grow."""
        return optimizer

    @contextmanager
    def learning(self):
        """While inside, `observe` stores new cells (the mapper's optimization)."""
        previous, self.grows = self.grows, True
        try:
            yield self
        finally:
            self.grows = previous

    def decoder_parameters(self) -> list[nn.Parameter]:
        """The MLP decoder's weights."""
        return [
            *self.trunk.parameters(),
            *self.occupancy_head.parameters(),
            *self.color_head.parameters(),
        ]

    def forward(self, p: torch.Tensor, with_color: bool = True) -> FieldOutput:
        """Occupancy and colour of points `(N, 3)` in map coordinates."""
        check_shape("p", p, (None, 3))
        hidden = self.trunk(self.geometry_features(p))
        logit = self.occupancy_head(hidden)[:, 0]
        occupancy = torch.sigmoid(logit) * self.inside(p)
        if not with_color:
            return FieldOutput(occupancy, torch.zeros_like(p))
        features = [hidden]
        if self.n_color_levels:
            features.append(self.color_features(p))
        rgb = torch.sigmoid(self.color_head(torch.cat(features, dim=-1)))
        return FieldOutput(occupancy, rgb)

    def occupancy(self, p: torch.Tensor) -> torch.Tensor:
        """`(N,)` occupancy probabilities only (cheaper: skips the colour head)."""
        return self.forward(p, with_color=False).occupancy

    def memory_bytes(self) -> int:
        """Bytes held by the map: stored grid cells and decoder."""
        return sum(t.numel() * t.element_size() for t in self.parameters())


class DenseField(Field):
    """Every cell of the bound stored, one dense tensor per level (`grid_sample` lookups).

    Occupancy is 0 outside the bound: monocular input has no known room size, so the bound
    is a generous box around the first camera (config).
    """

    def __init__(self, cfg: MapConfig, device: torch.device | str | None = None) -> None:
        super().__init__(cfg)
        if len(cfg.bound) != 6:
            raise ValueError(f"map bound needs 6 numbers (min xyz, max xyz), got {cfg.bound}")
        bound = torch.tensor(cfg.bound, dtype=torch.float32).view(2, 3)
        if not torch.all(bound[1] > bound[0]):
            raise ValueError(f"map bound must have min < max on every axis, got {cfg.bound}")
        self.register_buffer("bound", bound)
        self.geometry = nn.ParameterList()
        self.color = nn.ParameterList()
        spans = []
        for level, voxel in enumerate(cfg.voxel_sizes):
            # Cells cover the bound exactly; align_corners=True puts -1/+1 on the end vertices.
            counts = [math.ceil(float(e) / voxel) + 1 for e in bound[1] - bound[0]]
            spans.append([(n - 1) * voxel for n in counts])
            shape = (1, cfg.geometry_channels, counts[2], counts[1], counts[0])
            self.geometry.append(nn.Parameter(torch.randn(shape) * cfg.init_std))
            if level >= len(cfg.voxel_sizes) - self.n_color_levels:
                shape = (1, cfg.color_channels, counts[2], counts[1], counts[0])
                self.color.append(nn.Parameter(torch.randn(shape) * cfg.init_std))
        self.register_buffer("spans", torch.tensor(spans, dtype=torch.float32))  # (L, 3)
        if device is not None:
            self.to(device)

    def grid_parameters(self) -> list[nn.Parameter]:
        return [*self.geometry, *self.color]

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
        return torch.cat([self._lookup(g, p, i) for i, g in enumerate(self.geometry)], dim=-1)

    def color_features(self, p: torch.Tensor) -> torch.Tensor:
        first = len(self.geometry) - self.n_color_levels
        return torch.cat([self._lookup(g, p, first + i) for i, g in enumerate(self.color)], -1)

    def inside(self, p: torch.Tensor) -> torch.Tensor:
        return ((p >= self.bound[0]) & (p <= self.bound[1])).all(dim=-1)


class SparseField(Field):
    """Grids stored block by block where the mapper's rays have looked (`SparseGrids`); no
    bound: the map grows with the scene. Unstored cells read as zero features, as a dense
    grid's untouched ones (whose initialization is ~N(0, init_std))."""

    def __init__(self, cfg: MapConfig, device: torch.device | str | None = None) -> None:
        super().__init__(cfg)
        self._seen: list[tuple[torch.Tensor, torch.Tensor | None]] = []
        voxels = tuple(cfg.voxel_sizes)
        self.geometry = SparseGrids(voxels, cfg.geometry_channels, cfg.init_std)
        if self.n_color_levels:
            fine = voxels[len(voxels) - self.n_color_levels :]
            self.color = SparseGrids(fine, cfg.color_channels, cfg.init_std)
        if device is not None:
            self.to(device)

    def _grids(self) -> list[SparseGrids]:
        return [self.geometry, self.color] if self.n_color_levels else [self.geometry]

    @property
    def bound(self) -> torch.Tensor:
        """The box of the finest level's stored blocks (zero size while nothing is stored)."""
        return self.geometry.extent(-1)

    def grid_parameters(self) -> list[nn.Parameter]:
        return [g.atlas for g in self._grids()]

    def geometry_features(self, p: torch.Tensor) -> torch.Tensor:
        return self.geometry.lookup(p).reshape(p.shape[0], -1)

    def color_features(self, p: torch.Tensor) -> torch.Tensor:
        return self.color.lookup(p).reshape(p.shape[0], -1)

    def inside(self, p: torch.Tensor) -> torch.Tensor:
        return torch.ones_like(p[:, 0], dtype=torch.bool)

    def allocate(self, points: torch.Tensor, surface: torch.Tensor | None = None) -> None:
        fine = self.n_color_levels if self.cfg.fine_band > 0 and surface is not None else 0
        coarse = len(self.cfg.voxel_sizes) - fine
        self.geometry.allocate(points, slice(0, coarse))
        near = points if not fine else points[surface < self.cfg.fine_band]
        self.geometry.allocate(near, slice(coarse, None))
        if self.n_color_levels:
            self.color.allocate(near)

    def observe(self, points: torch.Tensor, surface: torch.Tensor | None = None) -> None:
        """While `learning`, the cells are stored at the next optimizer step
        (`adopt_growth`): grids that changed shape inside one forward pass would no longer
        match the gradients autograd computes for them."""
        if self.grows:
            # Blocks span 8 cells and rays are random: a spread-out sample of the points finds
            # the same blocks at a fraction of the cost.
            step = max(1, points.shape[0] // OBSERVED)
            near = surface[::step].detach() if surface is not None else None
            self._seen.append((points[::step].detach(), near))

    def adopt_growth(self, optimizer: torch.optim.Optimizer | None = None) -> None:
        """Store the cells seen since the last step; the optimizer steps the grown atlases
        (its state padded, new copies of old owners given their owners' state) and their
        gradients are settled (`SparseGrids.settle_gradient`)."""
        before = [(g.atlas, g.blocks.shape[0]) for g in self._grids()]
        if self._seen:
            points = torch.cat([p for p, _ in self._seen])
            surface = None
            if all(s is not None for _, s in self._seen):
                surface = torch.cat([s for _, s in self._seen])
            self.allocate(points, surface)
            self._seen.clear()
        for grids, (old, blocks) in zip(self._grids(), before, strict=True):
            if grids.atlas is not old:
                if old.grad is not None:
                    grids.atlas.grad = grids.grown(old.grad)
                if optimizer is not None:
                    _swap_parameter(optimizer, old, grids.atlas, grids.grown)
            state = optimizer.state.get(grids.atlas, {}) if optimizer is not None else {}
            if grids.blocks.shape[0] != blocks:
                # New copies of old owners must start from their owners' Adam state too.
                for value in state.values():
                    if torch.is_tensor(value) and value.shape == grids.atlas.shape:
                        grids.mirror(value)
            grids.settle_gradient()

    @contextmanager
    def learning(self):
        with super().learning():
            try:
                yield self
            finally:
                self._seen.clear()  # seen after the last step: the next optimization sees them

    @torch.no_grad()
    def reclaim(self, points: torch.Tensor, optimizer: torch.optim.Optimizer | None = None) -> int:
        """Forget the blocks of the levels `fine_band` stores near where rays stop that hold
        no corner of a cell of `points` `(N, 3)` (where rays stop now); `optimizer`, over
        these grids, follows them.

        Returns:
            Bytes freed.
        """
        fine = self.n_color_levels if self.cfg.fine_band > 0 else 0
        if not fine:
            return 0
        before = self.memory_bytes()
        first = len(self.cfg.voxel_sizes) - fine
        for grids, start in ((self.geometry, first), (self.color, 0)):
            banded = grids.blocks[:, 0] >= start
            old = grids.atlas
            bricks = grids.forget(banded & ~grids.holding(points, slice(start, None)))
            if bricks is None:
                continue
            if old.grad is not None:
                grids.atlas.grad = grids.moved(old.grad, bricks)
            if optimizer is not None:
                _swap_parameter(
                    optimizer, old, grids.atlas, lambda v, g=grids, b=bricks: g.moved(v, b)
                )
        return before - self.memory_bytes()

    def follow(self, optimizer: torch.optim.Optimizer) -> torch.optim.Optimizer:
        for grids in self._grids():
            grids.stale = True  # copies and owners equal at the optimizer's start
        optimizer.register_step_pre_hook(lambda opt, *_: self.adopt_growth(opt))
        return optimizer

    def memory_bytes(self) -> int:
        decoder = sum(t.numel() * t.element_size() for t in self.decoder_parameters())
        return decoder + sum(g.stored_bytes() for g in self._grids())


def _swap_parameter(optimizer: torch.optim.Optimizer, old, new, resize) -> None:
    """`optimizer` steps `new` instead of `old`, with `old`'s state `resize`d."""
    for group in optimizer.param_groups:
        group["params"] = [new if p is old else p for p in group["params"]]
    if old in optimizer.state:
        state = optimizer.state.pop(old)
        optimizer.state[new] = {
            k: resize(v) if torch.is_tensor(v) and v.dim() == new.dim() else v
            for k, v in state.items()
        }


def make_field(cfg: MapConfig, device: torch.device | str | None = None) -> Field:
    """The field `cfg.grids` asks for."""
    kinds = {"dense": DenseField, "sparse": SparseField}
    if cfg.grids not in kinds:
        raise ValueError(f"map grids must be one of {sorted(kinds)}, got {cfg.grids!r}")
    return kinds[cfg.grids](cfg, device)

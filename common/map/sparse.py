"""Feature grids stored only where rays have looked: bricks of cells, allocated as the map grows.

Each level's grid is cut into blocks of `BLOCK`^3 vertices (block `b` on a level of voxel `v`
owns the vertices `BLOCK * b + (0 .. BLOCK - 1)` on each axis, vertex `k` at `k * v` in map
coordinates). A stored block is a brick of `BRICK`^3 vertices in one dense atlas tensor: its
own vertices plus a copy of the first vertices of its upper neighbours, so that every cell
lies whole inside one brick and one `grid_sample` over the atlas interpolates all levels of
all points at once (the fused kernel; a gather of 8 corner rows per point and level measured
4x slower on one core). The copies are kept equal to their owners: before each optimizer step a
copy and its owner both get the sum of their gradients, so that Adam moves them alike
(`settle_gradient`; `Field.follow` hooks an optimizer up). A per-level index over the box of
stored block coordinates gives a block's brick; it is rebuilt when blocks are added, so there
is no scene bound: a camera that walks away keeps being mapped.

Brick 0 is all zeros and stands for every block nobody stored, which is what a dense grid's
untouched vertex holds (its initialization is ~N(0, 0.001)): the sparse field is a dense field
whose unobserved cells are never stored, never get a gradient, and never reach an optimizer.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

BLOCK = 8
"""Vertices per block edge (a block of the finest 8 cm level spans 64 cm)."""

BRICK = BLOCK + 1
"""Vertices per brick edge: the block's own and the first of its upper neighbours'."""

COLUMNS = 64
"""Bricks per atlas row (the atlas grows by rows of bricks); `brick >> 6` is its row."""

_BIAS = 1 << 16  # block coordinates within +-2^16 blocks (42 km at 8 cm voxels)


class SparseGrids(torch.nn.Module):
    """Multi-level grids of `channels` features, allocated block by block.

    `lookup(p)` gives `(N, L, C)` trilinear features of points `p` `(N, 3)` on all levels.
    """

    def __init__(
        self,
        voxel_sizes: tuple[float, ...],
        channels: int,
        init_std: float,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__()
        self.init_std = init_std
        self.register_buffer("voxels", torch.tensor(voxel_sizes, dtype=torch.float32))
        # (B, 4): level, then the block's x, y, z; block i lives in brick i + 1.
        self.register_buffer("blocks", torch.zeros(0, 4, dtype=torch.long))
        self.atlas = torch.nn.Parameter(torch.zeros(1, channels, BRICK, BRICK, BRICK * COLUMNS))
        self.stale = True
        """The copies may differ from their owners (new links, a load, a new optimizer):
        synced on the next lookup."""
        if device is not None:
            self.to(device)
        self._rebuild()

    @property
    def levels(self) -> int:
        return self.voxels.shape[0]

    @property
    def channels(self) -> int:
        return self.atlas.shape[1]

    def stored_bytes(self) -> int:
        """Bytes of the stored blocks' own vertices (what the map holds; the atlas adds the
        bricks' copies of their neighbours and the free bricks of its last row)."""
        return self.blocks.shape[0] * BLOCK**3 * self.channels * self.atlas.element_size()

    def lookup(self, p: torch.Tensor) -> torch.Tensor:
        """`(N, L, C)` features of points `(N, 3)`; unstored vertices read as zero."""
        self._sync()
        x = p[:, None, :] / self.voxels[None, :, None]  # (N, L, 3) in vertices
        base = torch.floor(x)
        vertex = base.int()
        brick = self._bricks(vertex)
        local = x - base + (vertex & (BLOCK - 1)).to(x.dtype)  # in [0, BLOCK)
        corner = torch.stack([(brick & (COLUMNS - 1)) * BRICK, 0 * brick, (brick >> 6) * BRICK], -1)
        grid = (corner + local) * self._scale - 1  # atlas coordinates in [-1, 1]
        out = F.grid_sample(
            self.atlas,
            grid.view(1, 1, 1, -1, 3),
            mode="bilinear",
            padding_mode="border",
            align_corners=True,
        )
        return out.view(self.channels, *base.shape[:2]).permute(1, 2, 0)

    def allocated(self, p: torch.Tensor) -> torch.Tensor:
        """`(N,)` bool: the block holding the point's cell on the finest level is stored
        (with its upper neighbours where the cell reaches into them)."""
        base = torch.floor(p[:, None, :] / self.voxels[None, :, None]).int()
        return self._complete(base)[:, -1]

    def _bricks(self, vertex: torch.Tensor) -> torch.Tensor:
        """Brick `(N, L)` of the block owning vertices `(N, L, 3)` (one per level); 0 if none."""
        # floor division by BLOCK (arithmetic shift)
        return self._slot((vertex >> 3) - self._origin, self._dims, self._offset)

    def _find(self, level: torch.Tensor, block: torch.Tensor) -> torch.Tensor:
        """Numbers `(M,)` of blocks `(M, 3)` on levels `(M,)`; -1 where not stored."""
        rel = block - self._origin[level]
        return self._slot(rel, self._dims[level], self._offset[level]).long() - 1

    def _slot(self, rel: torch.Tensor, dims: torch.Tensor, offset: torch.Tensor) -> torch.Tensor:
        """Index entries (brick, 0 if none) of blocks at `rel` `(..., 3)` in their level's box
        of `dims` `(..., 3)`, whose entries start at `offset`."""
        inside = ((rel >= 0) & (rel < dims)).all(dim=-1)
        flat = (rel[..., 2] * dims[..., 1] + rel[..., 1]) * dims[..., 0] + rel[..., 0]
        return self._index[torch.where(inside, flat + offset, -1)]  # last entry: 0

    def _complete(self, base: torch.Tensor) -> torch.Tensor:
        """`(N, L)` bool: all 8 corners of the cells with lowest corners `base` `(N, L, 3)`
        are stored (the block, and the upper neighbours the cell reaches into)."""
        brick = self._bricks(base)
        edge = ((base & (BLOCK - 1)) == BLOCK - 1).int()
        need = self._need[(edge[..., 2] * 4 + edge[..., 1] * 2 + edge[..., 0]).long()]
        return (brick > 0) & ((self._around[brick.long()] & need) == need)

    @torch.no_grad()
    def allocate(self, p: torch.Tensor, levels: slice = slice(None)) -> int:
        """Store the blocks holding the 8 corners of the cells of points `(N, 3)` on `levels`.

        Returns:
            How many blocks were added.
        """
        if p.numel() == 0:
            return 0
        new = self._cell_blocks(p, levels, missing_only=True)
        new = new[self._find(new[:, 0], new[:, 1:]) < 0]
        count = new.shape[0]
        if count == 0:
            return 0
        first = self.blocks.shape[0] + 1  # brick of the first new block
        self.blocks = torch.cat([self.blocks, new])
        rows = -(-(self.blocks.shape[0] + 1) // COLUMNS)
        grow = rows * BRICK - self.atlas.shape[2]
        if grow > 0:
            self._replace_atlas(F.pad(self.atlas.data, (0, 0, 0, 0, 0, grow)))
        owners = self._own_vertices(torch.arange(first, first + count, device=p.device))
        init = torch.randn(self.channels, owners.numel(), device=p.device) * self.init_std
        self.atlas.data.view(self.channels, -1)[:, owners] = init.to(self.atlas.dtype)
        self._rebuild_index()
        # The new blocks, and their lower neighbours: their copies and _around reach in.
        lower = new[:, None, 1:] - self._unit.long()  # (m, 8, 3)
        touched = self._find(new[:, None, 0].expand(-1, 8).reshape(-1), lower.reshape(-1, 3))
        self._link(torch.unique(touched[touched >= 0]))
        return count

    def _cell_blocks(self, p: torch.Tensor, levels: slice, missing_only: bool) -> torch.Tensor:
        """`(M, 4)` level and coordinates of the blocks holding the 8 corners of the cells of
        points `(N, 3)` on `levels`, each once (`missing_only`: of the cells not yet stored
        whole)."""
        level = torch.arange(self.levels, device=p.device)[levels]
        base = torch.floor(p[:, None, :] / self.voxels[level][None, :, None]).int()
        if missing_only:
            wanted = ~self._complete_on(base, level)
        else:
            wanted = torch.ones(base.shape[:2], dtype=torch.bool, device=p.device)
        corners = base[wanted][:, None, :] + self._unit  # (M, 8, 3)
        lv = level.view(1, -1).expand(wanted.shape)[wanted][:, None].expand(-1, 8)
        return _unpack(torch.unique(_pack(lv, (corners >> 3).long()).view(-1)))

    @torch.no_grad()
    def holding(self, p: torch.Tensor, levels: slice = slice(None)) -> torch.Tensor:
        """`(B,)` bool: the stored blocks holding a corner of a cell of points `(N, 3)` on
        `levels`."""
        held = torch.zeros(self.blocks.shape[0], dtype=torch.bool, device=self.blocks.device)
        if p.numel():
            blocks = self._cell_blocks(p, levels, missing_only=False)
            found = self._find(blocks[:, 0], blocks[:, 1:])
            held[found[found >= 0]] = True
        return held

    @torch.no_grad()
    def forget(self, gone: torch.Tensor) -> torch.Tensor | None:
        """Stop storing blocks `gone` (`(B,)` bool): their cells read zero again, as never
        stored, and the atlas shrinks to the blocks kept, in their order.

        Returns:
            The kept blocks' old bricks (for `moved`: gradients, optimizer state), None when
            nothing was forgotten.
        """
        if not bool(gone.any()):
            return None
        kept = (~gone).nonzero()[:, 0]
        bricks = torch.cat([kept.new_zeros(1), kept + 1])
        data = self._moved(self.atlas.data, bricks)
        self.blocks = self.blocks[kept]
        self._replace_atlas(data)
        self._rebuild()  # links, copies (those of forgotten owners become orphans: zero)
        return bricks

    def _moved(self, tensor: torch.Tensor, bricks: torch.Tensor) -> torch.Tensor:
        """An atlas-shaped `tensor`'s `bricks` (old numbers, in their new order; brick 0
        first) laid into a fresh atlas of as many bricks."""
        C, D, _, W = tensor.shape[1:]
        rows = D // BRICK
        # (C, row, z, y, column, x) -> (C, brick, z, y, x)
        old = tensor.view(C, rows, BRICK, BRICK, W // BRICK, BRICK).permute(0, 1, 4, 2, 3, 5)
        taken = old.reshape(C, -1, BRICK, BRICK, BRICK)[:, bricks]
        new_rows = -(-bricks.numel() // COLUMNS)
        taken = F.pad(taken, (0, 0, 0, 0, 0, 0, 0, new_rows * COLUMNS - bricks.numel()))
        new = taken.view(C, new_rows, COLUMNS, BRICK, BRICK, BRICK).permute(0, 1, 3, 4, 2, 5)
        return new.reshape(1, C, new_rows * BRICK, BRICK, COLUMNS * BRICK).contiguous()

    def moved(self, state: torch.Tensor, bricks: torch.Tensor) -> torch.Tensor:
        """A tensor shaped as the atlas before `forget` (gradient, optimizer state), shaped as
        it is now: the kept blocks' entries follow them, copies settled again."""
        out = self._moved(state, bricks)
        self.mirror(out)
        return out

    def _complete_on(self, base: torch.Tensor, level: torch.Tensor) -> torch.Tensor:
        """`_complete` for lowest corners `(N, l, 3)` on some `level`s `(l,)`."""
        if level.numel() == self.levels:
            return self._complete(base)
        full = torch.zeros(base.shape[0], self.levels, 3, dtype=base.dtype, device=base.device)
        full[:, level] = base
        return self._complete(full)[:, level]

    def _replace_atlas(self, data: torch.Tensor) -> None:
        """A new atlas parameter (an optimizer holding the old one must follow: see
        `SparseField.adopt_growth`). Resizing the old one in place is not safe: autograd keeps
        its shape in the gradient accumulator of any graph still referenced."""
        self.atlas = torch.nn.Parameter(data, requires_grad=self.atlas.requires_grad)

    def grown(self, state: torch.Tensor) -> torch.Tensor:
        """A tensor shaped as the atlas before it grew (gradient, optimizer state), padded to
        its new shape."""
        if state.shape == self.atlas.shape:
            return state
        return F.pad(state, (0, 0, 0, 0, 0, self.atlas.shape[2] - state.shape[2]))

    def _flat(self, brick: torch.Tensor, xyz: torch.Tensor) -> torch.Tensor:
        """Flat index into one channel of the atlas of vertices `xyz` (..., 3) of bricks."""
        row, column = brick >> 6, brick & (COLUMNS - 1)
        D, H, W = self.atlas.shape[2:]
        z = row * BRICK + xyz[..., 2]
        x = column * BRICK + xyz[..., 0]
        return (z * H + xyz[..., 1]) * W + x

    def _own_vertices(self, bricks: torch.Tensor) -> torch.Tensor:
        """Flat atlas indices of the `BLOCK`^3 own vertices of `bricks`."""
        return self._flat(bricks[:, None], self._local(BLOCK)[None]).view(-1)

    def _local(self, n: int) -> torch.Tensor:
        a = torch.arange(n, device=self.blocks.device)
        return torch.stack(torch.meshgrid(a, a, a, indexing="ij")[::-1], dim=-1).view(-1, 3)

    def _rebuild(self) -> None:
        """Index and links of every block, from `blocks` (after loading or moving them)."""
        device = self.blocks.device
        n = self.blocks.shape[0]
        unit = [[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)]
        self._unit = torch.tensor(unit, dtype=torch.int32, device=device)
        need = [sum(1 << k for k in range(8) if (k & ~edges) == 0) for edges in range(8)]
        self._need = torch.tensor(need, dtype=torch.int32, device=device)
        local = self._local(BRICK)
        self._apron = local[(local == BLOCK).any(dim=-1)]  # (217, 3) a brick's copies
        self._owner_table = torch.full((n + 1, self._apron.shape[0]), -1, device=device)
        self._copy_table = torch.zeros(0, self._apron.shape[0], dtype=torch.long, device=device)
        self._around = torch.zeros(n + 1, dtype=torch.int32, device=device)
        self._rebuild_index()
        self._link(torch.arange(n, device=device))

    def _rebuild_index(self) -> None:
        """The per-level boxes of stored blocks and the block -> brick index over them."""
        device = self.blocks.device
        L = self.levels
        origin = torch.zeros(L, 3, dtype=torch.long, device=device)
        dims = torch.zeros(L, 3, dtype=torch.long, device=device)
        for level in range(L):
            mine = self.blocks[self.blocks[:, 0] == level, 1:]
            if mine.numel():
                origin[level] = mine.min(dim=0).values
                dims[level] = mine.max(dim=0).values - origin[level] + 1
        sizes = dims.prod(dim=-1)
        offset = torch.cumsum(sizes, 0) - sizes
        index = torch.zeros(int(sizes.sum()) + 1, dtype=torch.int32, device=device)
        n = self.blocks.shape[0]
        if n:
            lv = self.blocks[:, 0]
            rel = self.blocks[:, 1:] - origin[lv]
            d = dims[lv]
            flat = offset[lv] + (rel[:, 2] * d[:, 1] + rel[:, 1]) * d[:, 0] + rel[:, 0]
            index[flat] = torch.arange(1, n + 1, device=device, dtype=torch.int32)
        self._index = index
        self._origin, self._dims, self._offset = origin.int(), dims.int(), offset.int()
        D, H, W = self.atlas.shape[2:]
        self._scale = 2 / torch.tensor([W - 1, H - 1, D - 1], dtype=torch.float32, device=device)

    def _link(self, ids: torch.Tensor) -> None:
        """For blocks `ids`: where each copy in their brick comes from (the upper neighbour's
        vertex, or nothing) and which upper neighbours are stored (`_around`)."""
        device = self.blocks.device
        n = self.blocks.shape[0]
        grow = n + 1 - self._owner_table.shape[0]
        if grow > 0:
            self._owner_table = F.pad(self._owner_table, (0, 0, 0, grow), value=-1)
            self._around = F.pad(self._around, (0, grow))
        if ids.numel():
            blocks = self.blocks[ids]
            k = self._apron.shape[0]
            vertex = blocks[:, None, 1:] * BLOCK + self._apron  # (m, 217, 3)
            owner = self._find(
                blocks[:, None, 0].expand(-1, k).reshape(-1), (vertex >> 3).reshape(-1, 3)
            ).view(-1, k)
            owned = self._flat(owner + 1, vertex & (BLOCK - 1))
            self._owner_table[ids + 1] = torch.where(owner >= 0, owned, -1)
            # Bit j of _around[brick]: the block at offset _unit[j] from the brick's is stored
            # (brick 0: none); _need[edges]: the bits a cell needs, by which upper faces of
            # its block it touches (bit 0: x, 1: y, 2: z).
            up = blocks[:, None, 1:] + self._unit.long()  # (m, 8, 3)
            there = self._find(blocks[:, None, 0].expand(-1, 8).reshape(-1), up.reshape(-1, 3))
            bits = (there >= 0).view(-1, 8).int() << torch.arange(8, device=device).int()
            self._around[ids + 1] = bits.sum(-1).int()
        first = self._copy_table.shape[0]
        if n + 1 > first:
            bricks = torch.arange(first, n + 1, device=device)
            added = self._flat(bricks[:, None], self._apron[None])
            self._copy_table = torch.cat([self._copy_table, added])
        self._copies, self._owners = self._copy_table.view(-1), self._owner_table.view(-1)
        has = self._owners >= 0
        self._owned_copies, self._owning = self._copies[has], self._owners[has]
        self._orphans = self._copies[~has]
        # 0 at orphan copies, 1 elsewhere: a multiply over the atlas clears their gradients
        # faster than indexing them (most copies are orphans where the map is a thin shell).
        self._keep = torch.ones(self.atlas.shape[2:], device=device)
        self._keep.view(-1)[self._orphans] = 0
        self.stale = True

    @torch.no_grad()
    def _sync(self) -> None:
        """Copies take their owners' values (zero where the owner is not stored)."""
        if not self.stale:
            return
        self.mirror(self.atlas.data)
        self.stale = False

    @torch.no_grad()
    def mirror(self, tensor: torch.Tensor) -> None:
        """Set the copies of `tensor` (shaped as the atlas: values, optimizer state) to their
        owners' entries, orphan copies to zero."""
        flat = tensor.view(self.channels, -1)
        flat[:, self._owned_copies] = flat[:, self._owning]
        flat[:, self._orphans] = 0

    @torch.no_grad()
    def settle_gradient(self) -> None:
        """Give every copy and its owner the sum of their gradients (orphan copies none):
        call after backward, before an optimizer step. An elementwise optimizer (Adam) then
        moves a copy exactly as its owner, given equal values and state at its start, which
        `stale` (set when it is hooked up, `Field.follow`) and the next lookup ensure. (A
        tensor hook would pin autograd's record of the atlas's shape, which `allocate`
        changes; the fused Adam does not bump the version counter a sync could check.)"""
        grad = self.atlas.grad
        if grad is None:
            return
        grad = self.grown(grad)
        flat = grad.view(self.channels, -1)
        flat.index_add_(1, self._owning, flat[:, self._owned_copies])
        flat[:, self._owned_copies] = flat[:, self._owning]
        grad.mul_(self._keep)
        self.atlas.grad = grad

    def extent(self, level: int = -1) -> torch.Tensor:
        """`(2, 3)` box (map units) covered by the level's stored blocks."""
        level = level % self.levels
        mine = self.blocks[self.blocks[:, 0] == level, 1:]
        span = float(self.voxels[level]) * BLOCK
        if mine.numel() == 0:
            return torch.zeros(2, 3, device=self.blocks.device)
        lo = mine.min(dim=0).values.float() * span
        hi = (mine.max(dim=0).values + 1).float() * span
        return torch.stack([lo, hi])

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # A snapshot's grids have their own number of blocks: take its shapes, then the values.
        blocks = state_dict.get(prefix + "blocks")
        atlas = state_dict.get(prefix + "atlas")
        if blocks is not None and atlas is not None:
            _check_blocks(blocks, atlas.shape, self.levels, self.channels)
            self.blocks = torch.empty(blocks.shape, dtype=torch.long, device=self.blocks.device)
            self._replace_atlas(torch.empty(atlas.shape, device=self.atlas.device))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)
        self._rebuild()

    def _apply(self, fn, recurse=True):
        out = super()._apply(fn, recurse)
        self._rebuild()
        return out


MAX_INDEX = 1 << 26
"""Most entries the block index may hold (256 MB): a map whose stored blocks spread wider is
refused rather than allocated."""


def _check_blocks(blocks: torch.Tensor, atlas: tuple[int, ...], levels: int, channels: int):
    """Refuse stored blocks that cannot be these grids' (ValueError)."""
    if blocks.dim() != 2 or blocks.shape[1] != 4 or blocks.dtype != torch.long:
        raise ValueError(f"blocks must be (B, 4) int64, got {tuple(blocks.shape)} {blocks.dtype}")
    rows = -(-(blocks.shape[0] + 1) // COLUMNS)
    want = (1, channels, max(1, rows) * BRICK, BRICK, BRICK * COLUMNS)
    if tuple(atlas) != want:
        raise ValueError(f"atlas of {blocks.shape[0]} blocks must be {want}, got {tuple(atlas)}")
    if blocks.numel() == 0:
        return
    if blocks[:, 0].min() < 0 or blocks[:, 0].max() >= levels:
        raise ValueError(f"block levels must be in [0, {levels})")
    if blocks[:, 1:].abs().max() >= _BIAS:
        raise ValueError(f"block coordinates must be within +-{_BIAS}")
    size = 0
    for level in range(levels):
        mine = blocks[blocks[:, 0] == level, 1:]
        if mine.numel():
            size += int((mine.max(dim=0).values - mine.min(dim=0).values + 1).prod())
    if size > MAX_INDEX:
        raise ValueError(f"stored blocks spread over {size} index entries (limit {MAX_INDEX})")
    if torch.unique(_pack(blocks[:, 0], blocks[:, 1:])).numel() != blocks.shape[0]:
        raise ValueError("a block is stored twice")


def _pack(level: torch.Tensor, block: torch.Tensor) -> torch.Tensor:
    """One int64 key per (level, block x, y, z), for sorting and deduplication."""
    b = block + _BIAS
    return ((level * (2 * _BIAS) + b[..., 0]) * (2 * _BIAS) + b[..., 1]) * (2 * _BIAS) + b[..., 2]


def _unpack(key: torch.Tensor) -> torch.Tensor:
    """`(M, 4)` level, block x, y, z from `_pack`'s keys."""
    z = key % (2 * _BIAS)
    y = key // (2 * _BIAS) % (2 * _BIAS)
    x = key // (2 * _BIAS) ** 2 % (2 * _BIAS)
    level = key // (2 * _BIAS) ** 3
    return torch.stack([level, x - _BIAS, y - _BIAS, z - _BIAS], dim=-1)

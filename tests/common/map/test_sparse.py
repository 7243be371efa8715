"""The sparse grids: trilinear features and gradients as a dense grid's, growth, snapshots."""

import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from walls import CAM, SMALL_MAP, small_mapper

from dimslam.common.geometry import pose
from dimslam.common.map.field import DenseField, MapConfig, SparseField, make_field
from dimslam.common.map.render import RenderConfig, render_pixels
from dimslam.common.map.sparse import BLOCK, COLUMNS, SparseGrids
from dimslam.common.net.exchange import load_map, to_snapshot
from dimslam.common.net.messages import MapSnapshot, MessageError
from dimslam.common.optim.window import FrameState
from dimslam.mapper.mapper import Mapper, MapperConfig

VOXELS = (0.3, 0.1)


def vertex_value(level: int, v: tuple[int, int, int]) -> float:
    """A value per vertex that no two neighbours share."""
    return math.sin(1.3 * v[0] + 2.1 * v[1] + 0.7 * v[2] + 5.0 * level)


def filled(points: torch.Tensor) -> SparseGrids:
    """Grids stored around `points`, each stored vertex holding `vertex_value`."""
    grids = SparseGrids(VOXELS, 1, 0.0)
    grids.allocate(points)
    with torch.no_grad():
        for i, (level, bx, by, bz) in enumerate(grids.blocks.tolist()):
            row, col = divmod(i + 1, COLUMNS)
            for x in range(BLOCK):
                for y in range(BLOCK):
                    for z in range(BLOCK):
                        v = (bx * BLOCK + x, by * BLOCK + y, bz * BLOCK + z)
                        grids.atlas[0, 0, row * (BLOCK + 1) + z, y, col * (BLOCK + 1) + x] = (
                            vertex_value(level, v)
                        )
    return grids


def trilinear(level: int, p: np.ndarray, stored) -> float:
    """The reference: trilinear interpolation of `vertex_value` (0 where not `stored`)."""
    x = p / VOXELS[level]
    base = np.floor(x).astype(int)
    f = x - base
    total = 0.0
    for k in range(8):
        o = np.array([k & 1, (k >> 1) & 1, (k >> 2) & 1])
        w = np.prod(np.where(o == 1, f, 1 - f))
        v = tuple(int(c) for c in base + o)
        if stored(level, v):
            total += w * vertex_value(level, v)
    return total


def test_lookup_interpolates_stored_vertices_across_block_borders_and_zero_elsewhere():
    gen = torch.Generator().manual_seed(0)
    stored_region = torch.rand(3000, 3, generator=gen) * 1.6 - 0.8  # spans several blocks
    grids = filled(stored_region)
    blocks = {tuple(b) for b in grids.blocks.tolist()}

    def stored(level, v):
        return (level, *(c // BLOCK for c in v)) in blocks

    inside = torch.rand(300, 3, generator=gen) * 1.6 - 0.8
    outside = torch.rand(100, 3, generator=gen) * 2 + 3.0  # never stored
    points = torch.cat([inside, outside])
    got = grids.lookup(points).detach()
    for n in range(points.shape[0]):
        for level in range(len(VOXELS)):
            want = trilinear(level, points[n].double().numpy(), stored)
            assert got[n, level, 0].item() == pytest.approx(want, abs=2e-4)  # float32 coords
    assert got[300:].abs().max() == 0
    assert grids.allocated(inside).all() and not grids.allocated(outside).any()


def test_gradients_reach_each_vertex_once_whichever_brick_holds_its_copy():
    gen = torch.Generator().manual_seed(1)
    grids = filled(torch.rand(2000, 3, generator=gen) * 1.6 - 0.8)
    points = torch.rand(200, 3, generator=gen) * 1.2 - 0.6
    weights = torch.rand(200, len(VOXELS), 1, generator=gen)
    (grids.lookup(points) * weights).sum().backward()
    grids.settle_gradient()
    # The reference: d loss / d vertex of the finest level, summed over the points.
    want: dict[tuple, float] = {}
    for n, p in enumerate(points.double().numpy()):
        x = p / VOXELS[1]
        base = np.floor(x).astype(int)
        f = x - base
        for k in range(8):
            o = np.array([k & 1, (k >> 1) & 1, (k >> 2) & 1])
            v = tuple(int(c) for c in base + o)
            want[v] = want.get(v, 0.0) + float(np.prod(np.where(o == 1, f, 1 - f))) * float(
                weights[n, 1, 0]
            )
    index = {tuple(b): i for i, b in enumerate(grids.blocks.tolist())}
    grad = grids.atlas.grad
    crossing = 0
    for v, g in want.items():
        i = index[(1, *(c // BLOCK for c in v))]
        row, col = divmod(i + 1, COLUMNS)
        local = [c % BLOCK for c in v]
        got = grad[0, 0, row * (BLOCK + 1) + local[2], local[1], col * (BLOCK + 1) + local[0]]
        assert got.item() == pytest.approx(g, rel=2e-3, abs=1e-5)  # float32 coords
        crossing += any(c == 0 for c in local)
    assert crossing > 0  # some of those vertices were reached through a lower brick's copy
    # Every copy of a vertex carries its owner's whole gradient (so that Adam moves them
    # alike); a copy whose owner is not stored carries none.
    checked = 0
    for i, (level, *block) in enumerate(grids.blocks.tolist()):
        row, col = divmod(i + 1, COLUMNS)
        for local in [(BLOCK, 3, 5), (2, BLOCK, 7), (6, 1, BLOCK), (BLOCK, BLOCK, BLOCK)]:
            copy = grad[0, 0, row * (BLOCK + 1) + local[2], local[1], col * (BLOCK + 1) + local[0]]
            v = [b * BLOCK + c for b, c in zip(block, local, strict=True)]
            owner = index.get((level, *(c // BLOCK for c in v)))
            if owner is None:
                assert copy == 0
                continue
            orow, ocol = divmod(owner + 1, COLUMNS)
            o = [c % BLOCK for c in v]
            want = grad[0, 0, orow * (BLOCK + 1) + o[2], o[1], ocol * (BLOCK + 1) + o[0]]
            assert copy == want
            checked += want != 0
    assert checked > 0


def test_a_sparse_field_matches_a_dense_one_where_nothing_was_learned():
    cfg = MapConfig(voxel_sizes=(0.5, 0.25), init_std=0.0, bound=(-3, -3, -3, 3, 3, 3))
    dense = DenseField(cfg)
    sparse = SparseField(replace(cfg, grids="sparse"))
    decoder = ("trunk", "occupancy", "color_head")
    weights = {k: v for k, v in dense.state_dict().items() if k.startswith(decoder)}
    sparse.load_state_dict({**sparse.state_dict(), **weights})
    p = torch.rand(500, 3) * 4 - 2
    sparse.allocate(p[:250])
    a, b = dense(p), sparse(p)
    assert torch.allclose(a.occupancy, b.occupancy, atol=1e-6)
    assert torch.allclose(a.rgb, b.rgb, atol=1e-6)


def sparse_mapper(grids: str) -> Mapper:
    return small_mapper(
        MapperConfig(prior_iters=60),
        replace(SMALL_MAP, grids=grids),
        RenderConfig(n_stratified=16, n_importance=8, importance_rounds=1, far=6.0),
    )


def test_the_map_grows_to_follow_a_camera_that_leaves_the_initial_bounds():
    """The plane at the gauge depth is fitted in front of a camera 20 m away, far out of the
    dense map's box: the sparse map stores cells there and renders the plane; the dense one
    cannot (its occupancy is zero outside the box)."""
    far = pose.make_pose(torch.eye(3), torch.tensor([20.0, 0.0, 0.0]))
    uv = torch.tensor([[40.0, 30.0], [10.0, 50.0], [70.0, 12.0]])
    depths = {}
    for grids in ("sparse", "dense"):
        m = sparse_mapper(grids)
        m.fit_prior(FrameState(0, 0.0, None, torch.eye(4)))
        before = m.field.bound.clone()
        m.fit_prior(FrameState(1, 0.1, None, far))
        with torch.no_grad():
            depths[grids] = render_pixels(m.field, CAM, uv, far, m.render_cfg).depth
        if grids == "sparse":
            assert before[1, 0] < 6 and m.field.bound[1, 0] > 20  # the stored region grew
            assert m.field.memory_bytes() < 2e6
    assert torch.allclose(depths["sparse"], torch.full((3,), 2.0), atol=0.3)
    assert not torch.allclose(depths["dense"], torch.full((3,), 2.0), atol=0.5)


def test_a_sparse_snapshot_loads_into_a_fresh_field_of_any_size():
    m = sparse_mapper("sparse")
    m.fit_prior(FrameState(0, 0.0, None, torch.eye(4)))
    snap = MapSnapshot.from_bytes(to_snapshot(1, 0, "d", m.field, [], []).to_bytes())
    fresh = make_field(m.field.cfg).requires_grad_(False)
    load_map(fresh, snap)
    p = torch.rand(300, 3) * 3 - 1.5
    assert torch.equal(fresh(p).occupancy, m.field(p).occupancy.detach())
    assert not fresh.geometry.atlas.requires_grad
    bad = dict(snap.state)
    bad["geometry.blocks"] = bad["geometry.blocks"].copy()
    bad["geometry.blocks"][0, 1] = 1 << 20  # a block far away: the index would explode
    with pytest.raises(MessageError, match="does not fit"):
        load_map(fresh, MapSnapshot(2, 0, "d", bad, {}))


def test_adam_keeps_every_copy_equal_to_its_owner_while_the_map_grows():
    field = SparseField(MapConfig(voxel_sizes=VOXELS, grids="sparse"))
    gen = torch.Generator().manual_seed(2)
    field.allocate(torch.rand(500, 3, generator=gen))
    optimizer = field.follow(torch.optim.Adam(field.parameters(), lr=1e-2, fused=True))
    with field.learning():
        for step in range(12):
            p = torch.rand(800, 3, generator=gen) * (1 + step / 4)  # reaching further each step
            field.observe(p)
            optimizer.zero_grad(set_to_none=True)
            out = field(p)
            (out.occupancy.square().mean() + out.rgb.square().mean()).backward()
            optimizer.step()
    for grids in field._grids():
        flat = grids.atlas.detach().view(grids.channels, -1)
        assert grids.blocks.shape[0] > 0 and flat.abs().max() > 0.01  # it grew and moved
        diff = flat[:, grids._owned_copies] - flat[:, grids._owning]
        assert diff.abs().max() < 1e-6
        assert flat[:, grids._orphans].abs().max() == 0


def test_fine_levels_are_stored_only_near_where_rays_stop():
    cfg = MapConfig(voxel_sizes=(0.64, 0.32, 0.16, 0.08), grids="sparse", fine_band=0.2)
    field = SparseField(cfg)
    depth = torch.linspace(0.1, 4.0, 200)
    points = torch.stack([torch.zeros(200), torch.zeros(200), depth], -1)  # one ray
    field.allocate(points, (depth - 3.0).abs())  # it stops at 3 m
    for grids, levels in ((field.geometry, (2, 3)), (field.color, (0, 1))):
        for level in levels:
            z = grids.blocks[grids.blocks[:, 0] == level, 3] * BLOCK * grids.voxels[level]
            assert z.min() >= 2.0 and z.max() <= 3.5  # blocks around the surface only
    coarse = field.geometry.blocks[field.geometry.blocks[:, 0] == 0, 3] * BLOCK * 0.64
    assert coarse.min() <= 0.1 and coarse.max() + BLOCK * 0.64 >= 4.0  # the whole ray


def test_forgotten_blocks_read_zero_and_the_kept_ones_keep_their_values():
    gen = torch.Generator().manual_seed(3)
    near = torch.rand(300, 3, generator=gen) * 1.5
    far = torch.rand(300, 3, generator=gen) * 1.5 + torch.tensor([1.2, 0.0, 0.0])
    grids = filled(torch.cat([near, far]))
    kept_before = grids.blocks[grids.holding(near)]
    bricks = grids.forget(~grids.holding(near))
    assert bricks is not None and bricks[0] == 0 and grids.blocks.shape[0] < 2 * len(bricks)
    assert torch.equal(grids.blocks, kept_before)  # the kept blocks, in their order
    kept = {tuple(b) for b in grids.blocks.tolist()}

    def stored(level, v):
        return (level, *(c // BLOCK for c in v)) in kept

    probe = torch.cat([near, far, torch.rand(200, 3, generator=gen) * 3])
    got = grids.lookup(probe)
    for i in range(0, probe.shape[0], 7):
        for level in range(len(VOXELS)):
            want = trilinear(level, probe[i].double().numpy(), stored)
            assert got[i, level, 0].item() == pytest.approx(want, abs=2e-4)  # float32 coords
    assert grids.forget(torch.zeros(grids.blocks.shape[0], dtype=torch.bool)) is None


def test_reclaim_keeps_the_band_where_rays_stop_now_and_adam_follows():
    cfg = MapConfig(voxel_sizes=(0.64, 0.32, 0.16, 0.08), grids="sparse", fine_band=0.2)
    field = SparseField(cfg)
    depth = torch.linspace(0.1, 4.0, 200)
    ray = torch.stack([torch.zeros(200), torch.zeros(200), depth], -1)
    field.allocate(ray, (depth - 3.0).abs())  # the surface was at 3 m ...
    field.allocate(ray, (depth - 1.5).abs())  # ... and is at 1.5 m now
    optimizer = field.follow(torch.optim.Adam(field.parameters(), lr=1e-2, fused=True))
    with field.learning():
        sum(x.square().sum() for x in vars(field(ray)).values()).backward()
        optimizer.step()
    coarse = field.geometry.blocks[field.geometry.blocks[:, 0] < 2].clone()
    moved = field.geometry.lookup(ray[depth < 2.0]).detach()
    surface = ray[(depth > 1.3) & (depth <= 1.5)]
    freed = field.reclaim(surface, optimizer)
    assert freed > 0
    for grids, levels in ((field.geometry, (2, 3)), (field.color, (0, 1))):
        for level in levels:
            z = grids.blocks[grids.blocks[:, 0] == level, 3] * BLOCK * grids.voxels[level]
            assert z.max() < 2.0  # nothing left about 3 m on the fine levels
    assert torch.equal(field.geometry.blocks[field.geometry.blocks[:, 0] < 2], coarse)
    kept = field.geometry.lookup(ray[depth < 2.0])  # unchanged, but for the atlas coordinates
    assert torch.allclose(kept, moved, atol=1e-6)
    for grids in field._grids():
        state = optimizer.state[grids.atlas]
        assert state["exp_avg"].shape == grids.atlas.shape
    with field.learning():  # the optimizer steps the new atlases
        optimizer.zero_grad(set_to_none=True)
        sum(x.square().sum() for x in vars(field(ray)).values()).backward()
        optimizer.step()
    for grids in field._grids():
        flat = grids.atlas.detach().view(grids.channels, -1)
        assert torch.allclose(flat[:, grids._owned_copies], flat[:, grids._owning], atol=1e-6)
        assert not flat[:, grids._orphans].any()


def test_reclaim_needs_a_sparse_map_with_a_band():
    with pytest.raises(ValueError, match="reclaim_every needs"):
        MapConfig(grids="sparse", reclaim_every=5)
    with pytest.raises(ValueError, match="reclaim_every needs"):
        MapConfig(fine_band=0.3, reclaim_every=5)


def test_the_mapper_forgets_the_fine_cells_of_a_surface_that_moved():
    """The plane is fitted at depth 2 before frame 0, then at depth 2 before a frame 1 m
    ahead: its rays carve the first plane away. Reclaiming from frame 1 forgets the fine
    cells about the first plane, and frame 1 still renders its plane."""
    voxels = (0.5, 0.25, 0.125, 0.0625)  # the fine levels' blocks: 1 m and 0.5 m
    cfg = replace(SMALL_MAP, voxel_sizes=voxels, grids="sparse", fine_band=0.3, reclaim_every=1)
    m = small_mapper(
        MapperConfig(prior_iters=80),
        cfg,
        RenderConfig(n_stratified=16, n_importance=8, importance_rounds=1, far=6.0),
    )
    m.fit_prior(FrameState(0, 0.0, None, torch.eye(4)))
    ahead = FrameState(1, 0.1, None, pose.make_pose(torch.eye(3), torch.tensor([0.0, 0.0, 1.0])))
    m.fit_prior(ahead)
    uv = torch.tensor([[32.0, 24.0], [12.0, 40.0], [50.0, 8.0]])

    def fine_z() -> torch.Tensor:
        blocks = m.field.color.blocks
        return blocks[:, 3] * BLOCK * m.field.color.voxels[blocks[:, 0]]

    with torch.no_grad():
        before = render_pixels(m.field, CAM, uv, ahead.T_wc, m.render_cfg).depth
    assert before.sub(2.0).abs().max() < 0.3 and fine_z().min() < 2.0  # cells at both planes
    stored = m.field.memory_bytes()
    assert m.reclaim([ahead]) > 0 and m.field.memory_bytes() < stored
    with torch.no_grad():
        after = render_pixels(m.field, CAM, uv, ahead.T_wc, m.render_cfg).depth
    assert fine_z().min() >= 2.0  # the first plane's fine cells are gone
    # Still the plane (here nearer it: the first plane's leftovers in front of it are gone).
    assert after.sub(2.0).abs().max() < 0.1

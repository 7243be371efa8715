"""The implicit map: trilinear lookup by hand, bound handling, gradients, parameter groups."""

import pytest
import torch

from dimslam.common.map.field import DenseField, MapConfig

SMALL = MapConfig(voxel_sizes=(0.5, 0.25), bound=(-1.0, -1.0, -1.0, 1.0, 1.0, 1.0))


def trilinear_by_hand(grid: torch.Tensor, p: torch.Tensor, origin: float, voxel: float) -> float:
    """Value of a (D, H, W) grid indexed [z, y, x] at point p, by the textbook formula."""
    f = (p - origin) / voxel
    i0 = torch.floor(f).long()
    a = f - i0
    total = 0.0
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                w = (
                    (a[0] if dx else 1 - a[0])
                    * (a[1] if dy else 1 - a[1])
                    * (a[2] if dz else 1 - a[2])
                )
                total += float(w) * float(grid[i0[2] + dz, i0[1] + dy, i0[0] + dx])
    return total


def test_lookup_matches_hand_computation():
    torch.manual_seed(0)
    field = DenseField(SMALL)
    with torch.no_grad():
        for g in field.geometry:
            g.copy_(torch.randn_like(g))
    assert field.geometry[0].shape == (1, 1, 5, 5, 5)  # 2 m / 0.5 m + 1 vertices per axis
    points = torch.rand(20, 3) * 1.8 - 0.9
    feats = field.geometry_features(points)
    assert feats.shape == (20, 2)
    grids = [g.detach()[0, 0] for g in field.geometry]
    for n, p in enumerate(points):
        for level, voxel in enumerate(SMALL.voxel_sizes):
            expected = trilinear_by_hand(grids[level], p, -1.0, voxel)
            assert feats[n, level].item() == pytest.approx(expected, abs=1e-5)


def test_bound_not_a_multiple_of_the_voxel_is_covered():
    cfg = MapConfig(voxel_sizes=(0.3,), bound=(0.0, 0.0, 0.0, 1.0, 0.5, 0.7))
    field = DenseField(cfg)
    assert field.geometry[0].shape == (1, 1, 4, 3, 5)  # ceil(e / 0.3) + 1 for z, y, x
    with torch.no_grad():
        field.geometry[0].copy_(torch.arange(60.0).view(1, 1, 4, 3, 5))
    # The vertex at (0.9, 0.3, 0.6) is index (x=3, y=1, z=2): value 2*15 + 1*5 + 3 = 38.
    assert field.geometry_features(torch.tensor([[0.9, 0.3, 0.6]]))[0, 0].item() == pytest.approx(
        38.0
    )


def test_outside_the_bound_is_empty_and_inside_is_not():
    field = DenseField(SMALL)
    out = field(torch.tensor([[0.0, 0.0, 0.0], [1.5, 0.0, 0.0], [0.0, -3.0, 0.0]]))
    assert out.occupancy[0] > 0 and out.occupancy[1] == 0 and out.occupancy[2] == 0
    assert out.rgb.shape == (3, 3) and ((out.rgb >= 0) & (out.rgb <= 1)).all()


def test_gradients_reach_grids_and_decoder():
    field = DenseField(SMALL)
    out = field(torch.rand(64, 3) * 1.6 - 0.8)
    (out.occupancy.sum() + out.rgb.sum()).backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in field.grid_parameters())
    assert all(p.grad is not None for p in field.decoder_parameters())
    names = {id(p) for p in field.grid_parameters()} | {id(p) for p in field.decoder_parameters()}
    assert names == {id(p) for p in field.parameters()}  # the two groups cover everything


def test_paper_configuration_sizes():
    field = DenseField(MapConfig())
    assert len(field.geometry) == 6 and len(field.color) == 2
    assert field.geometry[-1].shape[2:] == (151, 151, 151)  # 12 m at 8 cm
    # 6 geometry grids + 3 colour channels on the two finest: ~62 MB at 12 m^3.
    assert 50e6 < field.memory_bytes() < 80e6


def test_invalid_bound_is_rejected():
    with pytest.raises(ValueError, match="min < max"):
        DenseField(MapConfig(bound=(0.0, 0.0, 0.0, 1.0, -1.0, 1.0)))

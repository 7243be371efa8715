"""The renderer: a known occupancy step renders the right depth; weights and sampling."""

from dataclasses import replace

import pytest
import torch

from dimslam.common.geometry import pose
from dimslam.common.geometry.camera import Camera
from dimslam.common.map.field import DenseField, FieldOutput, MapConfig
from dimslam.common.map.render import (
    DepthPrior,
    RenderConfig,
    camera_rays,
    median_depth,
    ray_weights,
    render_image,
    render_pixels,
    sample_pdf,
    surface_depths,
)

CAM = Camera(40, 30, 35.0, 35.0, 19.5, 14.5)
CFG = RenderConfig(near=0.1, far=6.0)


def plane_field(normal, offset, sharpness=5000.0):
    """Occupied behind the plane n.p = offset (a soft step); colour from position."""
    n = torch.tensor(normal, dtype=torch.float32)
    n = n / n.norm()

    def field(p: torch.Tensor, with_color: bool = True) -> FieldOutput:
        occ = torch.sigmoid(sharpness * (p @ n - offset))
        return FieldOutput(occ, torch.sigmoid(p))

    return field


def test_fronto_parallel_step_renders_its_depth():
    field = plane_field((0, 0, 1), 2.0)
    uv = torch.tensor([[0.0, 0.0], [19.5, 14.5], [39.0, 29.0]])
    out = render_pixels(
        field, CAM, uv, torch.eye(4), CFG, generator=torch.Generator().manual_seed(0)
    )
    assert torch.allclose(out.depth, torch.full((3,), 2.0), atol=0.01)
    assert torch.allclose(out.opacity, torch.ones(3), atol=1e-3)


def test_tilted_plane_from_a_moved_camera():
    # Plane x + z = 3 seen from a camera shifted and rotated: z-depth along each pixel ray.
    field = plane_field((1, 0, 1), 3.0 / 2**0.5)
    T_wc = pose.make_pose(
        pose.exp_so3(torch.tensor([0.0, 0.2, 0.05])), torch.tensor([0.3, -0.2, 0.1])
    )
    uv = torch.rand(50, 2, generator=torch.Generator().manual_seed(1)) * torch.tensor([39.0, 29.0])
    out = render_pixels(field, CAM, uv, T_wc, CFG)
    o, d = camera_rays(CAM, uv, T_wc)
    t_true = (3.0 - (o[:, 0] + o[:, 2])) / (d[:, 0] + d[:, 2])  # unit-z directions: t is z-depth
    assert torch.allclose(out.depth, t_true, atol=0.01)


def test_normalized_depth_divides_by_the_opacity_down_to_its_floor():
    # A veil that stops 0.6 of each ray at one of its evenly spaced samples: the paper's depth
    # renders it at 0.6 of its depth, a normalized one at its depth; a floor above the opacity
    # divides by the floor instead.
    cfg = RenderConfig(near=0.1, far=6.0, n_stratified=64, importance_rounds=0)
    wall = 0.1 + (6.0 - 0.1) * 20.5 / 64  # a sample's depth, about 1.99

    def veil(p: torch.Tensor, with_color: bool = True) -> FieldOutput:
        occ = 0.6 * ((p[:, 2] - wall).abs() < 0.03).float()
        return FieldOutput(occ, torch.zeros_like(p))

    uv = torch.tensor([[19.5, 14.5]])
    plain = render_pixels(veil, CAM, uv, torch.eye(4), cfg)
    assert plain.opacity.item() == pytest.approx(0.6, rel=1e-4)
    assert plain.depth.item() == pytest.approx(0.6 * wall, rel=1e-4)
    for floor, expected in ((0.01, wall), (0.6, wall), (0.8, wall * 0.6 / 0.8)):
        norm = replace(cfg, normalize_depth=True, normalize_floor=floor)
        out = render_pixels(veil, CAM, uv, torch.eye(4), norm)
        assert out.depth.item() == pytest.approx(expected, rel=1e-4)
    with pytest.raises(ValueError, match="normalize_floor"):
        RenderConfig(normalize_floor=0.0)


def test_median_depth_is_where_half_the_stopped_light_has_stopped():
    t = torch.linspace(0.5, 4.0, 36)[None].repeat(3, 1)  # samples 0.1 apart
    occ = torch.zeros(3, 36)
    occ[0, 15] = 0.9  # one sharp surface at 2.0 leaking a tenth of the light to one at 3.0
    occ[0, 25] = 0.9
    occ[1, 20:23] = 0.3  # a soft surface from 2.5 to 2.7
    occ[2, 15] = 0.4  # a veil: the median of what it stops is the veil, whatever the opacity
    occ.requires_grad_(True)
    w = ray_weights(occ)
    depth = median_depth(w, t)
    # Sample i owns (t[i-1], t[i]]: the crossing's share of that interval places the depth.
    assert depth[0].item() == pytest.approx(1.9 + 0.1 * 0.5 * w[0].sum().item() / 0.9, abs=1e-5)
    mean = (w * t).sum(-1) / w.sum(-1)
    assert mean[0].item() > 2.05  # the mean is pulled behind the surface by the leak
    assert 2.4 < depth[1].item() < 2.6
    assert depth[2].item() == pytest.approx(1.95, abs=1e-5)
    depth.sum().backward()
    assert torch.isfinite(occ.grad).all()
    assert occ.grad[0, 15] < 0  # a denser surface renders nearer
    # As a render option: the veil of the test above renders at its depth, not 0.6 of it.
    cfg = RenderConfig(near=0.1, far=6.0, n_stratified=64, importance_rounds=0, median_depth=True)
    wall = 0.1 + (6.0 - 0.1) * 20.5 / 64

    def veil(p: torch.Tensor, with_color: bool = True) -> FieldOutput:
        occ = 0.6 * ((p[:, 2] - wall).abs() < 0.03).float()
        return FieldOutput(occ, torch.zeros_like(p))

    out = render_pixels(veil, CAM, torch.tensor([[19.5, 14.5]]), torch.eye(4), cfg)
    assert wall - 0.1 < out.depth.item() <= wall
    with pytest.raises(ValueError, match="exclude each other"):
        RenderConfig(median_depth=True, normalize_depth=True)


def test_importance_sampling_concentrates_on_the_surface():
    t = torch.linspace(0.1, 6.0, 32).expand(4, 32)
    w = torch.zeros(4, 32)
    w[:, 10] = 1.0
    drawn = sample_pdf(t, w, 64, generator=torch.Generator().manual_seed(0))
    lo, hi = t[0, 9], t[0, 10]  # the surface lies between the last free and first occupied
    inside = ((drawn >= lo) & (drawn <= hi)).float().mean()
    assert inside > 0.95


def test_weights_follow_the_termination_rule():
    occ = torch.tensor([[0.5, 0.5, 1.0, 0.3]])
    assert torch.allclose(ray_weights(occ), torch.tensor([[0.5, 0.25, 0.25, 0.0]]))


def test_gradients_flow_to_pose_and_map():
    field = DenseField(MapConfig(voxel_sizes=(0.5, 0.25), bound=(-3, -3, -1, 3, 3, 5)))
    xi = torch.zeros(6, requires_grad=True)
    T = pose.retract(torch.eye(4), xi)
    out = render_pixels(field, CAM, torch.tensor([[5.0, 5.0], [30.0, 20.0]]), T, CFG)
    (out.depth.sum() + out.rgb.sum()).backward()
    assert xi.grad is not None and torch.isfinite(xi.grad).all() and xi.grad.abs().sum() > 0
    assert field.geometry[0].grad.abs().sum() > 0


def test_render_image_shapes_and_determinism():
    field = plane_field((0, 0, 1), 1.5)
    depth, rgb = render_image(field, CAM, torch.eye(4), CFG, chunk=300)
    assert depth.shape == (30, 40) and rgb.shape == (30, 40, 3)
    assert depth.mean().item() == pytest.approx(1.5, abs=0.01)
    again, _ = render_image(field, CAM, torch.eye(4), CFG, chunk=1200)
    assert torch.equal(depth, again)


def test_surface_sampling_finds_the_surface_near_a_rough_prior_in_one_pass():
    field = plane_field((0, 0, 1), 2.0, sharpness=50.0)
    cfg = RenderConfig(near=0.1, far=6.0, surface_samples=16, coarse_samples=8)
    uv = torch.tensor([[0.0, 0.0], [19.5, 14.5], [39.0, 29.0]])
    gen = torch.Generator().manual_seed(0)
    full = render_pixels(field, CAM, uv, torch.eye(4), cfg, generator=gen)
    prior = torch.tensor([1.85, 2.0, 2.2])  # the map's depth from before the round's updates
    calls = []

    def counted(p, with_color=True):
        calls.append(p.shape[0])
        return field(p, with_color)

    near = render_pixels(counted, CAM, uv, torch.eye(4), cfg, generator=gen, depth_prior=prior)
    # Occupancy weights depend on how densely a ray is sampled before its surface: the soft
    # step renders a few cm nearer under the full sampler's denser placement.
    assert torch.allclose(near.depth, torch.full((3,), 2.0), atol=0.03)
    assert torch.allclose(full.depth, torch.full((3,), 2.0), atol=0.08)
    assert calls == [3 * (16 + 8)]  # one evaluation, no placement rounds
    t, reach, stop = surface_depths(prior, cfg, gen)
    assert torch.equal(stop, prior)
    assert (t.diff(dim=-1) >= 0).all()
    assert ((t >= prior[:, None] * 0.85 - 1e-6) & (t <= reach[:, None] + 1e-6)).sum(-1).min() >= 16


def test_depth_prior_reads_each_frames_rendered_depth():
    poses = torch.stack([torch.eye(4), pose.make_pose(torch.eye(3), torch.tensor([0, 0, 0.5]))])
    prior = DepthPrior(plane_field((0, 0, 1), 2.0), CAM, poses, CFG, width=20)
    uv = torch.tensor([[3.0, 4.0], [30.0, 20.0]])
    got = prior(torch.tensor([0, 1]), uv)
    assert torch.allclose(got, torch.tensor([2.0, 1.5]), atol=0.02)

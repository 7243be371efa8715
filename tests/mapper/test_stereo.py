"""Multi-view depth by plane sweep (`mapper/stereo.py`) on the built-in scene, and the
mapping round that pulls the map's depth towards it."""

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from walls import CAM, small_mapper, textured_wall_image

from dimslam.common.geometry import pose
from dimslam.common.io.synth import SynthScene, default_camera
from dimslam.common.map.render import render_image
from dimslam.common.optim.window import FrameState
from dimslam.mapper import mapper as mapper_module
from dimslam.mapper.mapper import MESH_MAP_WEIGHT, MapperConfig
from dimslam.mapper.stereo import (
    PATCH,
    WIDTH,
    _box,
    agreeing_depths,
    consistent_depths,
    plane_sweep,
    sample_depths,
)


@pytest.fixture(scope="module")
def views():
    """Frames 20-30 of the built-in path (about 1.5 cm apart) with their true depth."""
    scene = SynthScene(0)
    camera = default_camera(320, 240)
    path = scene.path(31)[20:]
    rendered = [scene.render(T, camera) for T in path]
    images = [torch.from_numpy(rgb).float() for rgb, _ in rendered]
    poses = [torch.from_numpy(T).float() for T in path]
    return camera, images, poses, rendered[5][1]


@pytest.mark.parametrize("n", [1, 48])
def test_the_patch_mean_is_poolings_at_the_edges_too(n):
    """OpenCV's running sums (`_box` on a CPU) against torch's pooling over the pixels inside."""
    x = torch.rand(n, 120, 160, generator=torch.Generator().manual_seed(n))
    pooled = F.avg_pool2d(x[:, None], PATCH, stride=1, padding=PATCH // 2, count_include_pad=False)
    assert torch.allclose(_box(x), pooled[:, 0], atol=1e-6)
    x.requires_grad_()
    _box(x).sum().backward()  # pooling, which has a gradient, where one is wanted
    assert x.grad is not None and x.grad.shape == x.shape


def _sweep(views, sources):
    camera, images, poses, _ = views
    return plane_sweep(
        images[5], poses[5], [(images[i], poses[i]) for i in sources], camera, 0.3, 8.0
    )


def test_sweep_finds_the_true_depth(views):
    """Measured: 73 % of the pixels kept, their depth 0.997 of the truth (median), 91 % within
    10 % of it."""
    camera, _, _, depth = views
    sweep = _sweep(views, [0, 2, 8, 10])
    assert sweep.camera.width == WIDTH and sweep.depth.shape == (120, 160)
    v, u = torch.meshgrid(torch.arange(240), torch.arange(320), indexing="ij")
    uv = torch.stack([u, v], -1).view(-1, 2).float()
    found = sample_depths(sweep.depth[None], sweep.camera, torch.zeros(len(uv)).long(), uv, camera)
    true = torch.from_numpy(depth).view(-1)
    ok = torch.isfinite(found)
    assert ok.float().mean() > 0.3  # the textured part of the view
    ratio = found[ok] / true[ok]
    assert abs(float(ratio.median()) - 1) < 0.02  # no bias: the scale is the poses'
    assert float(((ratio - 1).abs() < 0.1).float().mean()) > 0.7


def test_sweep_keeps_nothing_without_parallax_or_texture(views):
    camera, images, poses, _ = views
    still = plane_sweep(images[5], poses[5], [(images[5], poses[5])] * 2, camera, 0.3, 8.0)
    assert still.kept == 0.0  # every depth matches equally well: none is kept
    blank = torch.full_like(images[0], 0.5)
    flat = plane_sweep(blank, poses[5], [(blank, poses[0]), (blank, poses[10])], camera, 0.3, 8.0)
    assert flat.kept == 0.0
    with pytest.raises(ValueError, match="source"):
        plane_sweep(images[5], poses[5], [], camera, 0.3, 8.0)


def test_sweep_depth_follows_the_poses_scale(views):
    """Poses scaled by 2 (a map at another scale) give depths scaled by 2."""
    camera, images, poses, _ = views
    scaled = [T.clone() for T in poses]
    for T in scaled:
        T[:3, 3] *= 2
    one = _sweep(views, [0, 10])
    two = plane_sweep(
        images[5], scaled[5], [(images[0], scaled[0]), (images[10], scaled[10])], camera, 0.6, 16
    )
    both = torch.isfinite(one.depth) & torch.isfinite(two.depth)
    assert both.float().mean() > 0.2
    assert math.isclose(float((two.depth[both] / one.depth[both]).median()), 2.0, rel_tol=0.02)
    assert np.isfinite(one.kept)


def test_mapping_rounds_pull_a_wrong_depth_towards_the_sweeps():
    """A map whose first plane is at 1.2 (the wall is at 2): three rounds with the sweeps'
    target end nearer the wall than three without (measured 1.98 against 1.49)."""
    ends = {}
    for weight in (0.0, 0.3):
        torch.manual_seed(0)  # the grids' initialization
        frames = [
            FrameState(i + 1, i / 30, textured_wall_image(T), T.clone(), keyframe=True)
            for i, T in enumerate(
                pose.make_pose(torch.eye(3), torch.tensor([0.05 * i, 0.0, 0.0])) for i in range(6)
            )
        ]
        m = small_mapper(
            MapperConfig(
                pixels=128, iters=20, window_keyframes=0, gauge_depth=1.2, stereo_weight=weight
            )
        )
        m.fit_prior(frames[0])
        for _ in range(3):
            m.map(frames, [])
        if weight > 0:
            assert sorted(m.sweeps) == [f.index for f in frames]
            for sweep in m.sweeps.values():
                assert sweep.kept > 0.5
                assert abs(float(sweep.depth.nanmedian()) - 2.0) < 0.05
        else:
            assert not m.sweeps
        depth, _ = render_image(m.field, CAM, frames[2].T_wc, m.render_cfg)
        ends[weight] = abs(float(depth.median()) - 2.0)
    assert ends[0.3] < 0.5 * ends[0.0]


def _wall_depth(T_wc: torch.Tensor) -> torch.Tensor:
    """`CAM`'s z-depth of the wall z = 2 (`textured_wall_image`) seen from `T_wc`."""
    v, u = torch.meshgrid(
        torch.arange(float(CAM.height)), torch.arange(float(CAM.width)), indexing="ij"
    )
    d_w = CAM.unproject(torch.stack([u, v], -1), torch.ones_like(u)) @ T_wc[:3, :3].T
    t = (2.0 - T_wc[2, 3]) / d_w[..., 2]  # along the ray of unit z in the camera
    return t


def _wall_poses(n: int = 6) -> torch.Tensor:
    """`n` views of the wall, 5 cm apart along x, each turned 0.02 rad more about y."""
    turn = [pose.exp_so3(torch.tensor([0.0, 0.02 * i, 0.0])) for i in range(n)]
    return torch.stack(
        [pose.make_pose(R, torch.tensor([0.05 * i, 0.0, 0.0])) for i, R in enumerate(turn)]
    )


def test_consistent_depths_drop_what_the_neighbours_contradict():
    """The true depth of six views is kept where nothing contradicts it; a patch of one view
    put 20 % too deep is dropped (its neighbours see the wall elsewhere), the rest kept."""
    T = _wall_poses()
    true = torch.stack([_wall_depth(T_i) for T_i in T])
    wrong = true.clone()
    wrong[2, 10:30, 10:30] *= 1.2
    kept = consistent_depths(wrong, T, CAM)
    assert torch.isnan(kept[2, 10:30, 10:30]).all()
    others = torch.ones_like(true, dtype=torch.bool)
    others[2, 10:30, 10:30] = False
    assert float(torch.isfinite(kept[others]).float().mean()) > 0.9
    assert torch.equal(kept[others & torch.isfinite(kept)], wrong[others & torch.isfinite(kept)])
    unknown = torch.full_like(true, math.nan)
    assert torch.isnan(consistent_depths(unknown, T, CAM)).all()


def test_agreeing_depths_drop_the_map_where_the_sweeps_say_it_is_off():
    """A map rendering the left half of a view 30 % too deep: that half is left out, the
    right half kept, and a region no sweep saw is kept as the map renders it."""
    true = _wall_depth(torch.eye(4))[None]
    rendered = true.clone()
    rendered[:, :, :32] *= 1.3
    sweeps = true.clone()
    sweeps[:, ::2] = math.nan  # half the rows unknown: the local mean fills them
    sweeps[:, 30:, 40:] = math.nan  # a corner no sweep saw
    kept = agreeing_depths(rendered, sweeps, gate=0.1, sigma=3.0, support=0.1)
    assert torch.isnan(kept[0, :, :24]).all()
    assert torch.equal(kept[0, :, 40:], rendered[0, :, 40:])
    assert torch.equal(kept[0, :20, 36:], rendered[0, :20, 36:])


@pytest.mark.parametrize("sweeps", [True, False])
def test_the_mesh_takes_the_sweeps_depth_where_the_map_is_off(sweeps, monkeypatch):
    """A map fitted to a plane at 2.6 where the wall is at 2 (as a map fitted to poses that an
    adjustment then moved): with `mesh_sweeps` the mesh lies on the wall (its plane sweeps),
    the map's depth left out; without, on the map's plane. The sweeps are computed once for
    unchanged poses and again for the keyframes whose poses (or sources') moved."""
    calls = []
    original = mapper_module.plane_sweep
    monkeypatch.setattr(
        mapper_module, "plane_sweep", lambda *a, **k: calls.append(a[1]) or original(*a, **k)
    )
    torch.manual_seed(0)
    frames = [
        FrameState(i, i / 30, textured_wall_image(T), T.clone(), keyframe=True)
        for i, T in enumerate(_wall_poses(10))
    ]
    m = small_mapper(MapperConfig(gauge_depth=2.6, mesh_sweeps=sweeps, mesh_width=64))
    m.fit_prior(frames[0])
    poses = torch.stack([f.T_wc for f in frames])
    depths = m.mesh_depths(poses, frames)
    views = len(frames)
    if sweeps:
        assert len(depths.depths) == views and len(calls) == views
        swept = depths.weights == 1  # the sweep's pixels; the map's weigh MESH_MAP_WEIGHT
        assert torch.equal(
            depths.weights[~swept], torch.full_like(depths.weights[~swept], MESH_MAP_WEIGHT)
        )
        assert abs(float(depths.depths[swept].median()) - 2.0) < 0.05
        assert float(swept.float().mean()) > 0.3
        # the map's plane is left out where the sweeps around say it is off: measured, of the
        # 16 % of the pixels that render it and have no sweep, two thirds (the rest lie
        # beyond the sweeps' reach, at the images' edges)
        plane = ((depths.rendered - 2.6).abs() < 0.2) & ~swept
        kept = plane & torch.isfinite(depths.depths)
        assert float(kept.float().mean()) < 0.5 * float(plane.float().mean())
    else:
        assert torch.equal(depths.depths, depths.rendered) and not calls
    assert abs(float(depths.rendered.nanmedian()) - 2.6) < 0.15  # the map's plane
    mesh = m.extract_mesh(poses, 4.0, frames)
    z = float(np.median(mesh.vertices[:, 2]))
    assert abs(z - (2.0 if sweeps else 2.6)) < 0.1, z
    if sweeps:
        calls.clear()
        m.mesh_depths(poses, frames)
        assert not calls  # nothing moved: every sweep from the cache
        frames[0].T_wc = frames[0].T_wc.clone()
        frames[0].T_wc[0, 3] -= 0.01
        m.mesh_depths(poses, frames)
        assert 1 <= len(calls) < views  # frame 0 and those it is a source of, not the others

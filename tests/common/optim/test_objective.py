"""The window objective's optional terms and shapes: the pose gate, the margin its patches
need."""

import torch

from dimslam.common.geometry import pose
from dimslam.common.geometry.camera import Camera
from dimslam.common.map.field import DenseField, MapConfig
from dimslam.common.map.render import RenderConfig, render_pixels
from dimslam.common.optim.objective import LossConfig, window_objective

CAM = Camera(40, 30, 35.0, 35.0, 19.5, 14.5)
RENDER = RenderConfig(n_stratified=16, n_importance=8, importance_rounds=1, near=0.1, far=1.5)


def see_through(field: DenseField, uv: torch.Tensor, T_wc: torch.Tensor) -> None:
    """Train `field` until the rays of pixels `uv` at poses `T_wc` mostly pass."""
    optimizer = torch.optim.Adam(field.parameters(), lr=1e-2)
    for _ in range(100):
        optimizer.zero_grad()
        passed = render_pixels(field, CAM, uv, T_wc, RENDER).opacity.mean()
        if float(passed.detach()) < 0.4:
            break
        passed.backward()
        optimizer.step()


def test_rays_under_the_pose_gate_move_the_map_but_no_pose():
    torch.manual_seed(0)
    field = DenseField(MapConfig(voxel_sizes=(0.5, 0.25), bound=(-2.0, -2.0, -2.0, 2.0, 2.0, 2.0)))
    images = torch.rand(3, CAM.height, CAM.width, 3)
    moves = ([0, 0, 0], [0.05, 0, 0], [0.1, 0.02, 0])
    start = torch.stack([pose.make_pose(torch.eye(3), torch.tensor(t)) for t in moves])
    uv = torch.tensor([[u, v] for u in range(6, 34, 4) for v in range(6, 24, 4)]).float()
    frame = torch.arange(len(uv)) % 3
    only_warp = LossConfig(render_weight=0.0)
    see_through(field, uv, start[frame])
    with torch.no_grad():
        opacity = render_pixels(field, CAM, uv, start[frame], RENDER).opacity
    assert 0 < float(opacity.min()) and float(opacity.max()) < 1

    def grads(gate: float) -> tuple[torch.Tensor, torch.Tensor]:
        field.zero_grad()
        poses = start.clone().requires_grad_(True)
        loss = window_objective(
            field, images, poses, CAM, frame, uv, only_warp, RENDER, pose_gate=gate
        ).total
        loss.backward()
        map_grad = torch.cat([p.grad.flatten() for p in field.parameters() if p.grad is not None])
        return poses.grad, map_grad

    every_pose, every_map = grads(0.0)
    assert float(every_pose.abs().sum()) > 0
    # A gate under every ray's opacity changes nothing; one above all of them moves no pose.
    low_pose, low_map = grads(float(opacity.min()) / 2)
    assert torch.allclose(low_pose, every_pose) and torch.allclose(low_map, every_map)
    half_pose, _ = grads(float(opacity.median()))  # some rays pass: some pose gradient
    assert 0 < float(half_pose.abs().sum()) and not torch.allclose(half_pose, every_pose)
    gated_pose, gated_map = grads(1.0)
    assert float(gated_pose.abs().sum()) == 0.0
    assert torch.allclose(gated_map, every_map)


def test_the_margin_fits_the_largest_patch():
    assert LossConfig(patch_sizes=(1, 3, 5)).margin() == 2
    assert LossConfig().margin() == 5 and LossConfig(patch_sizes=(1, 15)).margin() == 7
    assert len(LossConfig(patch_sizes=(1, 5)).offsets()) == 25

"""A small camera, a textured wall it looks at and a small mapper, for tests of the window
optimizations."""

import torch

from dimslam.common.geometry.camera import Camera
from dimslam.common.map.field import FieldOutput, MapConfig
from dimslam.common.map.render import RenderConfig
from dimslam.common.optim.objective import LossConfig
from dimslam.mapper.mapper import Mapper, MapperConfig

CAM = Camera(64, 48, 50.0, 50.0, 31.5, 23.5)


def textured_wall_image(T_wc: torch.Tensor, camera: Camera = CAM) -> torch.Tensor:
    """`(H, W, 3)` view of the wall z = 2 painted with smooth stripes, seen from `T_wc`."""
    v, u = torch.meshgrid(
        torch.arange(float(camera.height)), torch.arange(float(camera.width)), indexing="ij"
    )
    d_c = camera.unproject(torch.stack([u, v], -1), torch.ones_like(u))  # rays with unit z
    d_w = d_c @ T_wc[:3, :3].T
    o = T_wc[:3, 3]
    p = o + d_w * ((2.0 - o[2]) / d_w[..., 2])[..., None]
    x, y = p[..., 0], p[..., 1]
    phases = torch.tensor([0.0, 2.1, 4.2])
    return 0.5 + 0.2 * torch.sin(9 * x[..., None] + phases) * torch.cos(7 * y[..., None] - phases)


def wall(p: torch.Tensor, with_color: bool = True) -> FieldOutput:
    """The map of that wall: occupied from z = 2 on (a sharp step), grey."""
    return FieldOutput(torch.sigmoid(2000 * (p[:, 2] - 2.0)), torch.full_like(p, 0.5))


SMALL_MAP = MapConfig(voxel_sizes=(0.5, 0.25), bound=(-3.0, -3.0, -1.0, 3.0, 3.0, 5.0))
SMALL_LOSS = LossConfig(patch_sizes=(1, 5), min_views=1, smooth_blocks=4)
SMALL_RENDER = RenderConfig(n_stratified=8, n_importance=4, importance_rounds=1, far=4.0)


def small_mapper(
    cfg: MapperConfig,
    map_cfg: MapConfig = SMALL_MAP,
    render_cfg: RenderConfig = SMALL_RENDER,
    loss_cfg: LossConfig = SMALL_LOSS,
) -> Mapper:
    """A mapper of a small map seen by `CAM`, for tests that need no trained map."""
    return Mapper(
        cfg,
        map_cfg,
        loss_cfg,
        render_cfg,
        0.0,
        50,
        CAM,
        torch.device("cpu"),
        torch.Generator().manual_seed(0),
    )

"""A small camera and a textured wall it looks at, for tests of the window optimizations."""

import torch

from dimslam.common.geometry.camera import Camera
from dimslam.common.map.field import FieldOutput

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

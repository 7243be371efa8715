"""A small camera and a textured wall it looks at, for tests of the window optimizations."""

import torch

from dimslam.common.geometry.camera import Camera

CAM = Camera(64, 48, 50.0, 50.0, 31.5, 23.5)


def textured_wall_image(T_wc: torch.Tensor) -> torch.Tensor:
    """`(48, 64, 3)` view of the wall z = 2 painted with smooth stripes, seen from `T_wc`."""
    v, u = torch.meshgrid(torch.arange(48.0), torch.arange(64.0), indexing="ij")
    d_c = CAM.unproject(torch.stack([u, v], -1), torch.ones_like(u))  # rays with unit z
    d_w = d_c @ T_wc[:3, :3].T
    o = T_wc[:3, 3]
    p = o + d_w * ((2.0 - o[2]) / d_w[..., 2])[..., None]
    x, y = p[..., 0], p[..., 1]
    phases = torch.tensor([0.0, 2.1, 4.2])
    return 0.5 + 0.2 * torch.sin(9 * x[..., None] + phases) * torch.cos(7 * y[..., None] - phases)

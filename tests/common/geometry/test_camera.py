"""Pinhole intrinsics: project/unproject, resize and crop consistency, undistortion, calib files."""

import math

import cv2
import numpy as np
import pytest
import torch

from dimslam.common.errors import DatasetError
from dimslam.common.geometry import pose
from dimslam.common.geometry.camera import Camera, frustum_mask, read_calib

CAM = Camera(640, 480, 525.0, 520.0, 319.5, 239.5)


def test_project_unproject_round_trip():
    g = torch.Generator().manual_seed(0)
    uv = torch.rand(100, 2, generator=g, dtype=torch.float64) * torch.tensor([640.0, 480.0])
    depth = 0.5 + 3 * torch.rand(100, generator=g, dtype=torch.float64)
    p = CAM.unproject(uv, depth)
    uv2, z = CAM.project(p)
    assert torch.allclose(uv2, uv) and torch.allclose(z, depth)


def test_resize_keeps_projection_consistent():
    # A 3D point must land on the same relative image position after a resize.
    p = torch.tensor([[0.3, -0.2, 2.0]], dtype=torch.float64)
    small = CAM.resized(160)
    assert small.size == (160, 120)
    uv, _ = CAM.project(p)
    uv_small, _ = small.project(p)
    assert torch.allclose((uv_small + 0.5) * 4, uv + 0.5)
    # Image corners map to corners.
    assert small.cx == pytest.approx((319.5 + 0.5) / 4 - 0.5)


def test_crop_shifts_principal_point():
    c = CAM.cropped(10, 20, 600, 400)
    p = torch.tensor([[0.1, 0.1, 1.0]], dtype=torch.float64)
    assert torch.allclose(
        c.project(p)[0], CAM.project(p)[0] - torch.tensor([10.0, 20.0], dtype=torch.float64)
    )
    with pytest.raises(ValueError):
        CAM.cropped(0, 0, 700, 10)


def test_undistort_maps_invert_the_distortion():
    cam = Camera(320, 240, 260.0, 260.0, 160.0, 120.0, (0.2, -0.3, 0.001, -0.002, 0.05))
    map_x, map_y = cam.undistort_maps()
    # The map at an undistorted pixel gives where cv2.projectPoints puts that ray (distorted).
    u, v = 250, 60
    ray = np.array([[(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, 1.0]])
    distorted, _ = cv2.projectPoints(ray, np.zeros(3), np.zeros(3), cam.K, np.array(cam.dist))
    assert map_x[v, u] == pytest.approx(distorted[0, 0, 0], abs=1e-2)
    assert map_y[v, u] == pytest.approx(distorted[0, 0, 1], abs=1e-2)
    assert not cam.undistorted().distorted


def test_invalid_intrinsics_rejected():
    with pytest.raises(ValueError):
        Camera(640, 480, -1.0, 500.0, 320, 240)
    with pytest.raises(ValueError):
        Camera(640, 480, 500.0, 500.0, 320, 240, (0.1, 0.2))


@pytest.mark.parametrize(
    "text,expected",
    [
        ("262.4 262.4 159.5 119.5\n", (262.4, 262.4, 159.5, 119.5, ())),
        (
            "# comment\n500 501 320 240 0.1 -0.2 0.001 0.002\n",
            (500, 501, 320, 240, (0.1, -0.2, 0.001, 0.002)),
        ),
    ],
)
def test_read_calib(tmp_path, text, expected):
    f = tmp_path / "calib.txt"
    f.write_text(text)
    fx, fy, cx, cy, dist = read_calib(f)
    assert (fx, fy, cx, cy) == pytest.approx(expected[:4])
    assert dist == pytest.approx(expected[4])


@pytest.mark.parametrize(
    "text", ["1 2 3\n", "a b c d\n", "1 2 3 4\n5 6 7 8\n", "0 1 2 3\n", "1 1 nan 3\n"]
)
def test_read_calib_errors_name_the_file(tmp_path, text):
    f = tmp_path / "calib.txt"
    f.write_text(text)
    with pytest.raises(DatasetError, match="calib.txt"):
        read_calib(f)


def test_read_calib_missing_file(tmp_path):
    with pytest.raises(DatasetError, match="nothere.txt"):
        read_calib(tmp_path / "nothere.txt")


# At z = 2 this camera sees |x|, |y| <= 2 exactly (pixel edges -0.5 .. 199.5, cx = 99.5, fx = 100).
WIDE = Camera(200, 200, 100.0, 100.0, 99.5, 99.5)


def test_frustum_mask_keeps_what_the_camera_sees():
    points = np.array([[0, 0, 2], [1.99, 1.99, 2], [2.01, 0, 2], [0, 0, -2], [0, 0, 0.5]])
    mask = frustum_mask(points, np.eye(4)[None], WIDE)
    assert mask.tolist() == [True, True, False, False, True]
    # A second camera turned around sees the point behind the first.
    T_back = pose.make_pose(pose.exp_so3(torch.tensor([0.0, math.pi, 0.0])), torch.zeros(3))
    both = np.stack([np.eye(4), T_back.double().numpy()])
    assert frustum_mask(points, both, WIDE).tolist() == [True, True, False, True, True]


def test_pixels_lists_every_pixel_row_by_row():
    small = CAM.resized(8)
    uv = small.pixels()
    assert uv.shape == (small.width * small.height, 2)
    k = torch.arange(len(uv))
    assert torch.equal(uv[:, 0], (k % small.width).float())
    assert torch.equal(uv[:, 1], (k // small.width).float())

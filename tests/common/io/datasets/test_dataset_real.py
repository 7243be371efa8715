"""The development sequences in ../shared/data (skipped where they are absent).

The data is found through `DIMSLAM_DATA`, else `../shared/data` beside the repository.
"""

from __future__ import annotations

import numpy as np
import pytest
from repo import DATA

from dimslam.common.io.datasets import ReaderOptions, detect_layout, open_dataset


def sequence(name: str):
    path = DATA / name
    if not path.is_dir():
        pytest.skip(f"{path} is absent")
    return path


def intrinsics(cam) -> tuple:
    return cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy


def check_ground_truth(reader, n: int) -> None:
    gt = reader.ground_truth()
    assert len(gt) == n
    assert np.isfinite(gt.poses).all()
    assert np.all(np.diff(gt.timestamps) > 0)
    R = gt.poses[:, :3, :3]
    # KinectFusion's rotations are orthonormal to about 2e-4 only.
    assert np.allclose(R @ R.transpose(0, 2, 1), np.eye(3), atol=1e-3)


@pytest.mark.parametrize("name", ["room0", "room3", "room5"])
def test_synthetic_rooms(name):
    root = sequence(name)
    assert detect_layout(root) == "tum"
    reader = open_dataset(root)
    assert len(reader) == 300
    check_ground_truth(reader, 300)
    assert intrinsics(reader.camera) == (320, 240, 262.4, 262.4, 159.5, 119.5)
    frames = list(open_dataset(root, options=ReaderOptions(stride=60)))
    assert [f.index for f in frames] == [0, 60, 120, 180, 240]
    assert all(f.rgb.shape == (240, 320, 3) and f.T_wc is not None for f in frames)


def test_7scenes_redkitchen():
    root = sequence("7scenes-redkitchen-000-499")
    assert detect_layout(root) == "7scenes"
    reader = open_dataset(root)
    assert len(reader) == 500
    check_ground_truth(reader, 500)
    assert reader.ground_truth().timestamps[-1] == pytest.approx(499 / 30)
    assert intrinsics(reader.camera) == (640, 480, 585, 585, 320, 240)
    frames = list(open_dataset(root, options=ReaderOptions(stride=100, width=320)))
    assert len(frames) == 5 and all(f.rgb.shape == (240, 320, 3) for f in frames)

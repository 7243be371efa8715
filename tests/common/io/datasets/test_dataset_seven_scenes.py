"""7-Scenes specifics: intrinsics lookup order, optional and bad pose files."""

from __future__ import annotations

import re

import pytest
from dataset_fixtures import make_seven_scenes, write_calib

from dimslam.common.errors import DatasetError
from dimslam.common.io.datasets import ReaderOptions, open_dataset


def test_builtin_intrinsics_without_camera_intrinsics_txt(tmp_path):
    seq = make_seven_scenes(tmp_path / "seq-01", n=2, size=(640, 480), K=None)
    cam = open_dataset(seq.root).camera
    assert (cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy) == (640, 480, 585, 585, 320, 240)


def test_calib_txt_wins_over_camera_intrinsics_txt(tmp_path):
    seq = make_seven_scenes(tmp_path / "seq-01")
    write_calib(seq.root, (50, 51, 16, 12))
    cam = open_dataset(seq.root).camera
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (50, 51, 16, 12)


def test_non_finite_pose_names_the_file(tmp_path):
    seq = make_seven_scenes(tmp_path / "seq-01")
    bad = seq.root / "frame-000102.pose.txt"
    bad.write_text(bad.read_text().replace(bad.read_text().split()[3], "-inf", 1))
    with pytest.raises(DatasetError, match=re.escape(f"{bad}: non-finite pose")):
        open_dataset(seq.root)


def test_malformed_pose_file(tmp_path):
    seq = make_seven_scenes(tmp_path / "seq-01")
    bad = seq.root / "frame-000104.pose.txt"
    bad.write_text("1 0 0\n0 1 0\n")
    with pytest.raises(DatasetError, match=re.escape(f"{bad}: pose must be 4x4 numbers, got 6")):
        open_dataset(seq.root)


def test_bad_pose_outside_the_selection_is_not_read(tmp_path):
    seq = make_seven_scenes(tmp_path / "seq-01")
    (seq.root / "frame-000105.pose.txt").write_text("garbage")
    assert len(open_dataset(seq.root, options=ReaderOptions(end=5))) == 5


def test_bad_camera_intrinsics_txt(tmp_path):
    seq = make_seven_scenes(tmp_path / "seq-01")
    (seq.root / "camera-intrinsics.txt").write_text("585 0 320\n0 585 240\n")
    with pytest.raises(DatasetError, match="intrinsic matrix must be 3x3 numbers"):
        _ = open_dataset(seq.root).camera

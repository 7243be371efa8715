"""TUM RGB-D specifics: Freiburg built-in intrinsics, calib.txt, index and ground-truth errors."""

from __future__ import annotations

import re

import pytest
from dataset_fixtures import make_tum, write_calib

from dimslam.common.errors import DatasetError
from dimslam.common.io.datasets import open_dataset
from dimslam.common.io.datasets.tum import FREIBURG


def pinhole(intr) -> tuple:
    return intr.fx, intr.fy, intr.cx, intr.cy, intr.dist


@pytest.mark.parametrize(
    "name,camera",
    [("rgbd_dataset_freiburg1_desk", 1), ("rgbd_dataset_freiburg2_xyz", 2), ("fr3_office", 3)],
)
def test_freiburg_intrinsics_from_the_folder_name(tmp_path, name, camera):
    seq = make_tum(tmp_path / name, n=2, size=(640, 480), calib=None)
    reader = open_dataset(seq.root)
    expected, raw = FREIBURG[camera], reader.raw_camera
    assert (raw.fx, raw.fy, raw.cx, raw.cy, raw.dist) == pinhole(expected)
    assert reader.camera.dist == ()
    assert next(iter(reader)).rgb.shape == (480, 640, 3)


def test_freiburg_values_are_the_published_ones():
    # TUM RGB-D "file formats" page, "Intrinsic Camera Calibration of the Kinect".
    fr1 = (517.3, 516.5, 318.6, 255.3, (0.2624, -0.9531, -0.0054, 0.0026, 1.1633))
    fr2 = (520.9, 521.0, 325.1, 249.7, (0.2312, -0.7849, -0.0033, -0.0001, 0.9172))
    assert pinhole(FREIBURG[1]) == fr1
    assert pinhole(FREIBURG[2]) == fr2
    assert pinhole(FREIBURG[3]) == (535.4, 539.2, 320.1, 247.6, ())
    assert all(FREIBURG[k].size == (640, 480) for k in (1, 2, 3))


def test_calib_txt_wins_over_the_folder_name(tmp_path):
    seq = make_tum(tmp_path / "rgbd_dataset_freiburg1_desk", n=2, calib=(100, 101, 15, 11))
    cam = open_dataset(seq.root).camera
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.dist) == (100, 101, 15, 11, ())


def test_no_calib_and_no_freiburg_name_names_calib_txt(tmp_path):
    seq = make_tum(tmp_path / "my_room", n=2, calib=None)
    reader = open_dataset(seq.root)
    assert len(reader.ground_truth()) > 0  # ground truth needs no intrinsics
    with pytest.raises(DatasetError, match=re.escape(f"{seq.root / 'calib.txt'}: missing")):
        _ = reader.camera
    with pytest.raises(DatasetError, match="calib.txt: missing"):
        list(reader)


def test_freiburg_size_mismatch_is_an_error(tmp_path):
    seq = make_tum(tmp_path / "rgbd_dataset_freiburg3_small", n=2, calib=None)
    with pytest.raises(DatasetError, match="are for 640x480 images but the images are 32x24"):
        _ = open_dataset(seq.root).camera


@pytest.mark.parametrize(
    "name, line, message",
    [
        ("rgb.txt", "1305031109.0", r"rgb\.txt:10: expected 'timestamp filename'"),
        ("rgb.txt", "soon rgb/x.png", r"rgb\.txt:10: not a number"),
        ("groundtruth.txt", "1305031109.0 0 0 nan 0 0 0 1", r"groundtruth\.txt:9: non-finite"),
    ],
)
def test_a_bad_line_names_its_file_and_line(tmp_path, name, line, message):
    seq = make_tum(tmp_path / "scene")
    with open(seq.root / name, "a") as f:
        f.write(line + "\n")
    with pytest.raises(DatasetError, match=message):
        open_dataset(seq.root)


def test_without_groundtruth_txt(tmp_path):
    seq = make_tum(tmp_path / "scene")
    (seq.root / "groundtruth.txt").unlink()
    reader = open_dataset(seq.root)
    assert reader.ground_truth() is None
    assert all(f.T_wc is None for f in reader)


def test_empty_rgb_txt(tmp_path):
    seq = make_tum(tmp_path / "scene")
    (seq.root / "rgb.txt").write_text("# nothing\n")
    write_calib(seq.root)
    with pytest.raises(DatasetError, match="no frames found"):
        open_dataset(seq.root)

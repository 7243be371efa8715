"""Shared reader machinery: options, detection, association, decoding, intrinsics lookup."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from dataset_fixtures import image, make_folder, make_tum, write_calib

from dimslam.common.errors import DatasetError
from dimslam.common.io.datasets import LAYOUTS, ReaderOptions, detect_layout, open_dataset
from dimslam.common.io.datasets.base import read_image
from dimslam.common.io.datasets.files import associate


def test_layout_names():
    assert set(LAYOUTS) == {"tum", "replica", "euroc", "7scenes", "folder", "video", "camera"}


@pytest.mark.parametrize(
    "kwargs,message",
    [
        ({"stride": 0}, "stride must be at least 1"),
        ({"start": -1}, "start must be 0 or more"),
        ({"start": 5, "end": 5}, r"end \(5\) must be after start \(5\)"),
        ({"width": 0}, "width must be positive"),
        ({"fps": 0.0}, "fps must be positive"),
        ({"fps": float("nan")}, "fps must be positive"),
    ],
)
def test_bad_options_are_dataset_errors(kwargs, message):
    with pytest.raises(DatasetError, match=message):
        ReaderOptions(**kwargs)


def test_associate_takes_the_nearest_within_tolerance():
    gt = np.array([0.30, 0.10, 0.20, 0.50])  # unsorted on purpose
    frames = np.array([0.0, 0.09, 0.161, 0.29, 0.40, 0.519, 0.6])
    assert associate(frames, gt, max_dt=0.02).tolist() == [-1, 1, -1, 0, -1, 3, -1]
    assert associate(frames, np.array([])).tolist() == [-1] * len(frames)


def test_detect_layout_lists_the_known_layouts(tmp_path):
    (tmp_path / "notes.txt").write_text("nothing to see")
    with pytest.raises(DatasetError) as err:
        detect_layout(tmp_path)
    for name in LAYOUTS:
        assert f"{name}:" in str(err.value)
    assert str(tmp_path) in str(err.value)


def test_missing_source_and_unknown_layout(tmp_path):
    with pytest.raises(DatasetError, match="no such file or folder"):
        open_dataset(tmp_path / "absent")
    with pytest.raises(DatasetError, match="unknown layout 'kitti'"):
        open_dataset(tmp_path, layout="kitti")


def test_digits_mean_a_camera():
    assert detect_layout(0) == "camera"
    assert detect_layout("2") == "camera"


def test_tum_wins_over_folder_even_with_images_beside_rgb_txt(tmp_path):
    seq = make_tum(tmp_path / "scene")
    cv2.imwrite(str(seq.root / "thumbnail.png"), image(5))
    assert detect_layout(seq.root) == "tum"
    assert detect_layout(seq.root / "rgb") == "folder"


def test_named_layout_overrides_detection(tmp_path):
    seq = make_tum(tmp_path / "scene")
    write_calib(seq.root / "rgb")
    reader = open_dataset(seq.root / "rgb", layout="folder")
    assert reader.layout == "folder" and len(reader) == len(seq.images)
    with pytest.raises(DatasetError, match=r"rgb\.txt: cannot read"):
        open_dataset(seq.root / "rgb", layout="tum")


def test_options_calib_overrides_calib_txt(tmp_path):
    seq = make_folder(tmp_path / "imgs")
    other = tmp_path / "other.txt"
    other.write_text("# fx fy cx cy\n40 41 16 12\n")
    cam = open_dataset(seq.root, options=ReaderOptions(calib=other)).camera
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (40, 41, 16, 12)


def test_malformed_calib_names_the_file(tmp_path):
    seq = make_folder(tmp_path / "imgs")
    (seq.root / "calib.txt").write_text("500 500 320\n")
    with pytest.raises(DatasetError, match=r"calib\.txt: expected 4, 8 or 9 numbers"):
        list(open_dataset(seq.root))


@pytest.mark.parametrize("cut", ["half", "empty", "text"])
def test_read_image_reports_corrupt_files(tmp_path, cut):
    path = tmp_path / "x.jpg"
    cv2.imwrite(str(path), image(1))
    data = path.read_bytes()
    path.write_bytes({"half": data[: len(data) // 2], "empty": b"", "text": b"hello"}[cut])
    img, reason = read_image(path)
    assert img is None and reason


def test_read_image_missing_file(tmp_path):
    img, reason = read_image(tmp_path / "absent.png")
    assert img is None and "No such file" in reason


def test_reader_is_a_context_manager(tmp_path):
    seq = make_folder(tmp_path / "imgs")
    with open_dataset(seq.root) as reader:
        assert len(list(reader)) == len(seq.images)


def test_camera_index_with_a_file_layout(tmp_path):
    with pytest.raises(DatasetError, match="tum: needs a path, got the camera index 0"):
        open_dataset(0, layout="tum")


def test_frame_pose_is_a_copy(tmp_path):
    seq = make_tum(tmp_path / "scene")
    reader = open_dataset(seq.root)
    frame = next(iter(reader))
    frame.T_wc[:3, 3] = 1e6
    assert np.allclose(reader.ground_truth().poses[0], seq.poses[0], atol=1e-6)

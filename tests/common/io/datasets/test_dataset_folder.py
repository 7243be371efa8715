"""Image folders: name order, timestamps from names, calib.txt, and undistortion."""

from __future__ import annotations

import re

import cv2
import numpy as np
import pytest
from dataset_fixtures import image, make_folder, write_calib

from dimslam.common.errors import DatasetError
from dimslam.common.io.datasets import ReaderOptions, open_dataset


def test_natural_order_and_fps_timestamps(tmp_path):
    for i in (10, 2, 1):
        cv2.imwrite(str(tmp_path / f"img{i}.png"), image(i))
    write_calib(tmp_path)
    frames = list(open_dataset(tmp_path, options=ReaderOptions(fps=10)))
    assert [f.timestamp for f in frames] == pytest.approx([0.0, 0.1, 0.2])
    # img1, img2, img10 (not img1, img10, img2): compare contents, RGB order.
    for frame, seed in zip(frames, (1, 2, 10), strict=True):
        assert np.array_equal(frame.rgb, image(seed)[..., ::-1])


def test_decimal_names_are_timestamps_in_order_of_value(tmp_path):
    for stem in ("1.5", "1.25", "10.0", "2.000000"):
        cv2.imwrite(str(tmp_path / f"{stem}.png"), image(3))
    write_calib(tmp_path)
    assert [f.timestamp for f in open_dataset(tmp_path)] == [1.25, 1.5, 2.0, 10.0]


def test_frame_numbers_are_not_seconds(tmp_path):
    for i in (3, 1, 2):
        cv2.imwrite(str(tmp_path / f"{i:06d}.png"), image(i))
    write_calib(tmp_path)
    frames = list(open_dataset(tmp_path, options=ReaderOptions(fps=30)))
    assert [f.timestamp for f in frames] == pytest.approx([0.0, 1 / 30, 2 / 30])
    assert np.array_equal(frames[0].rgb, image(1)[..., ::-1])


def test_mixed_extensions_and_other_files(tmp_path):
    cv2.imwrite(str(tmp_path / "a.png"), image(1))
    cv2.imwrite(str(tmp_path / "b.JPG"), image(2))
    cv2.imwrite(str(tmp_path / "c.bmp"), image(3))
    cv2.imwrite(str(tmp_path / "d.tiff"), image(4))
    (tmp_path / "notes.md").write_text("not an image")
    write_calib(tmp_path)
    assert len(open_dataset(tmp_path)) == 4


def test_missing_calib_txt_names_it(tmp_path):
    seq = make_folder(tmp_path / "imgs", calib=None)
    with pytest.raises(DatasetError, match=re.escape(f"{seq.root / 'calib.txt'}: missing")):
        list(open_dataset(seq.root))


def test_distorted_calib_is_undistorted(tmp_path):
    """A dot drawn where the lens puts a point must come out where the pinhole puts it."""
    width, height, fx, fy, cx, cy = 160, 120, 100.0, 100.0, 79.5, 59.5
    dist = (-0.3, 0.05, 0.001, -0.001)
    ideal = np.array([140.0, 100.0])
    ray = np.array([[(ideal[0] - cx) / fx, (ideal[1] - cy) / fy, 1.0]])
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    seen, _ = cv2.projectPoints(ray, np.zeros(3), np.zeros(3), K, np.array(dist))
    seen = seen.reshape(2)
    assert np.linalg.norm(seen - ideal) > 5  # the test would notice a missing undistortion
    raw = np.zeros((height, width, 3), np.uint8)
    cv2.circle(raw, (int(round(seen[0])), int(round(seen[1]))), 2, (255, 255, 255), -1)
    cv2.imwrite(str(tmp_path / "0.png"), raw)
    write_calib(tmp_path, (fx, fy, cx, cy, *dist))
    reader = open_dataset(tmp_path)
    assert reader.camera.dist == () and reader.raw_camera.dist == dist
    gray = next(iter(reader)).rgb[..., 0].astype(float)
    v, u = np.mgrid[:height, :width]
    centroid = np.array([(gray * u).sum(), (gray * v).sum()]) / gray.sum()
    assert np.linalg.norm(centroid - ideal) < 1.0


def test_undistortion_happens_before_resizing(tmp_path):
    write_calib(tmp_path, (30, 31, 15.5, 11.5, -0.2, 0.0, 0.0, 0.0))
    cv2.imwrite(str(tmp_path / "0.png"), image(1))
    reader = open_dataset(tmp_path, options=ReaderOptions(width=16))
    raw = reader.raw_camera
    assert reader.camera == raw.undistorted().resized(16)
    undistorted = cv2.remap(image(1)[..., ::-1], *raw.undistort_maps(), cv2.INTER_LINEAR)
    expected = cv2.resize(undistorted, (16, 12), interpolation=cv2.INTER_AREA)
    assert np.array_equal(next(iter(reader)).rgb, expected)

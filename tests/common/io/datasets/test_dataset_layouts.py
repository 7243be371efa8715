"""What every file layout must do alike: detection, frames, ground truth, options, bad input.

The shared behaviour lives once in `datasets.base`; these tests run it through every layout's
fixture so that a layout that bypasses it is caught.
"""

from __future__ import annotations

import logging

import cv2
import numpy as np
import pytest
from dataset_fixtures import BUILDERS, CALIB, HEIGHT, WIDTH, image

from dimslam.common.errors import DatasetError
from dimslam.common.geometry.camera import Camera
from dimslam.common.io.datasets import ReaderOptions, detect_layout, open_dataset

LAYOUT_NAMES = sorted(BUILDERS)


@pytest.fixture(params=LAYOUT_NAMES)
def seq(request, tmp_path):
    sequence = BUILDERS[request.param](tmp_path / f"seq_{request.param}")
    sequence.extra["layout"] = request.param
    return sequence


def assert_red(rgb: np.ndarray) -> None:
    """Pure red written as BGR must read as RGB (255, 0, 0), JPEG loss allowed."""
    r, g, b = (rgb[..., c].astype(int) for c in range(3))
    assert r.min() > 230 and g.max() < 40 and b.max() < 40


def test_detects_and_reads_every_frame(seq):
    assert detect_layout(seq.root) == seq.extra["layout"]
    reader = open_dataset(seq.root)
    assert reader.layout == seq.extra["layout"]
    assert len(reader) == len(seq.images)
    frames = list(reader)
    assert [f.index for f in frames] == list(range(len(seq.images)))
    assert np.allclose([f.timestamp for f in frames], seq.timestamps, rtol=0, atol=1e-6)
    for f in frames:
        assert f.rgb.shape == (HEIGHT, WIDTH, 3) and f.rgb.dtype == np.uint8
    if seq.color:
        assert_red(frames[0].rgb)
    else:  # grayscale source: three equal channels, unchanged near the principal point
        rgb = frames[1].rgb
        assert np.array_equal(rgb[..., 0], rgb[..., 1]) and np.array_equal(rgb[..., 0], rgb[..., 2])
        centre = np.s_[11:13, 15:17]
        assert np.abs(rgb[centre][..., 0].astype(int) - image(1, gray=True)[centre]).max() <= 2
    assert reader.skipped == 0


def test_ground_truth_round_trips(seq):
    reader = open_dataset(seq.root)
    frames = list(reader)
    for f, expected in zip(frames, seq.poses, strict=True):
        if expected is None:
            assert f.T_wc is None
        else:
            assert f.T_wc.shape == (4, 4) and f.T_wc.dtype == np.float64
            assert np.allclose(f.T_wc, expected, atol=1e-6)
    gt = reader.ground_truth()
    known = [i for i, T in enumerate(seq.poses) if T is not None]
    if not known:
        assert gt is None
        return
    assert len(gt) == len(known)
    assert np.allclose(gt.timestamps, [seq.timestamps[i] for i in known], rtol=0, atol=1e-6)
    assert np.allclose(gt.poses, [seq.poses[i] for i in known], atol=1e-6)


def test_intrinsics_from_the_dataset(seq):
    cam = open_dataset(seq.root).camera
    assert (cam.width, cam.height) == (WIDTH, HEIGHT)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == pytest.approx(CALIB)
    assert cam.dist == ()


def test_stride_start_end(seq):
    reader = open_dataset(seq.root, options=ReaderOptions(start=1, end=5, stride=2))
    assert len(reader) == 2
    frames = list(reader)
    assert [f.index for f in frames] == [1, 3]
    assert [f.timestamp for f in frames] == pytest.approx([seq.timestamps[1], seq.timestamps[3]])
    gt = reader.ground_truth()
    expected = [seq.timestamps[i] for i in (1, 3) if seq.poses[i] is not None]
    assert (gt is None and not expected) or list(gt.timestamps) == pytest.approx(expected)


def test_start_beyond_the_end_is_an_error(seq):
    with pytest.raises(DatasetError, match="start 99 is beyond the last frame"):
        open_dataset(seq.root, options=ReaderOptions(start=99))


def test_resize_scales_intrinsics_like_camera_resized(seq):
    reader = open_dataset(seq.root, options=ReaderOptions(width=WIDTH // 2))
    raw = Camera(WIDTH, HEIGHT, *CALIB)
    assert reader.camera == raw.resized(WIDTH // 2)
    frame = next(iter(reader))
    assert frame.rgb.shape == (HEIGHT // 2, WIDTH // 2, 3)
    if seq.color:
        assert_red(frame.rgb)


def test_corrupt_image_is_skipped_with_a_warning(seq, caplog):
    seq.images[2].write_bytes(b"this is not an image")
    reader = open_dataset(seq.root)
    with caplog.at_level(logging.WARNING):
        frames = list(reader)
    assert [f.index for f in frames] == [0, 1, 3, 4, 5]
    assert reader.skipped == 1
    assert seq.images[2].name in caplog.text


@pytest.mark.parametrize("layout", ["tum", "euroc"])  # the layouts with an index file
def test_image_missing_from_the_index_is_skipped(layout, tmp_path, caplog):
    seq = BUILDERS[layout](tmp_path / layout)
    seq.images[-1].unlink()
    reader = open_dataset(seq.root)
    with caplog.at_level(logging.WARNING):
        assert len(list(reader)) == len(seq.images) - 1
    assert reader.skipped == 1 and seq.images[-1].name in caplog.text


def test_every_image_unreadable_is_an_error(seq):
    for path in seq.images:
        path.write_bytes(b"")
    with pytest.raises(DatasetError, match="none of the 6 selected images can be read"):
        list(open_dataset(seq.root))


def test_inconsistent_image_sizes_are_an_error(seq):
    cv2.imwrite(str(seq.images[3]), image(3, WIDTH + 2, HEIGHT))
    reader = open_dataset(seq.root)
    with pytest.raises(DatasetError, match=rf"{seq.images[3].name}: image is {WIDTH + 2}x{HEIGHT}"):
        list(reader)


def test_ground_truth_decodes_no_image(seq):
    # Ground truth of a dataset whose images are all corrupt still reads: nothing is decoded.
    for path in seq.images:
        path.write_bytes(b"corrupt")
    reader = open_dataset(seq.root)
    gt = reader.ground_truth()
    assert (gt is None) == all(T is None for T in seq.poses)

"""Video files and live cameras (through cv2.VideoCapture)."""

from __future__ import annotations

import re

import cv2
import numpy as np
import pytest
from dataset_fixtures import CALIB, HEIGHT, WIDTH, image, write_calib

from dimslam.common.errors import DatasetError
from dimslam.common.io.datasets import ReaderOptions, detect_layout, open_dataset
from dimslam.common.io.datasets.video import CameraReader

FPS = 10.0
N = 6


@pytest.fixture
def video(tmp_path):
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), FPS, (WIDTH, HEIGHT))
    assert writer.isOpened()
    for i in range(N):
        writer.write(image(i))
    writer.release()
    write_calib(tmp_path)
    return path


def test_reads_frames_with_container_timestamps(video):
    assert detect_layout(video) == "video"
    reader = open_dataset(video)
    assert reader.layout == "video" and len(reader) == N
    frames = list(reader)
    assert [f.index for f in frames] == list(range(N))
    assert [f.timestamp for f in frames] == pytest.approx([i / FPS for i in range(N)])
    assert frames[0].rgb.shape == (HEIGHT, WIDTH, 3) and frames[0].rgb.dtype == np.uint8
    red = frames[0].rgb.astype(int)
    assert red[..., 0].min() > 230 and red[..., 1:].max() < 40
    assert all(f.T_wc is None for f in frames) and reader.ground_truth() is None
    cam = reader.camera
    assert (cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy) == (WIDTH, HEIGHT, *CALIB)


def test_stride_start_end_and_resize(video):
    reader = open_dataset(video, options=ReaderOptions(start=1, end=5, stride=2, width=16))
    assert len(reader) == 2
    frames = list(reader)
    assert [f.index for f in frames] == [1, 3]
    assert [f.timestamp for f in frames] == pytest.approx([0.1, 0.3])
    assert frames[0].rgb.shape == (12, 16, 3)
    assert reader.camera.fx == pytest.approx(CALIB[0] / 2)


def test_reads_twice(video):
    reader = open_dataset(video)
    assert len(list(reader)) == len(list(reader)) == N


def test_start_beyond_the_end(video):
    with pytest.raises(DatasetError, match="start 6 is beyond the last frame"):
        open_dataset(video, options=ReaderOptions(start=6))


def test_missing_calib_names_it(video):
    (video.parent / "calib.txt").unlink()
    with pytest.raises(DatasetError, match=re.escape(f"{video.parent / 'calib.txt'}: missing")):
        open_dataset(video)


def test_unreadable_video(tmp_path):
    bad = tmp_path / "broken.mp4"
    bad.write_bytes(b"not a video at all")
    write_calib(tmp_path)
    with pytest.raises(DatasetError, match="cannot open it as a video"):
        open_dataset(bad)


class _NoTimestamps:
    """A capture whose container gives every frame position 0 ms."""

    def get(self, prop: int) -> float:
        return 0.0


def test_timestamps_fall_back_to_fps_and_never_go_back(video):
    reader = open_dataset(video, options=ReaderOptions(fps=20))
    stamps = [reader._timestamp(_NoTimestamps(), i) for i in (0, 1, 3)]
    assert stamps == pytest.approx([0.0, 0.05, 0.15])


def test_nonexistent_camera_is_a_dataset_error(tmp_path):
    write_calib(tmp_path)
    with pytest.raises(DatasetError, match="camera 97: cannot open"):
        open_dataset("97", options=ReaderOptions(calib=tmp_path / "calib.txt"))


def test_camera_needs_calib():
    with pytest.raises(DatasetError, match="--calib"):
        CameraReader(0)

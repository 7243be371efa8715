"""Replica (NICE-SLAM renders) specifics: built-in camera, frame numbers, traj.txt errors."""

from __future__ import annotations

import numpy as np
import pytest
from dataset_fixtures import make_replica

from dimslam.common.errors import DatasetError
from dimslam.common.io.datasets import open_dataset


def test_builtin_camera(tmp_path):
    seq = make_replica(tmp_path / "room0", n=2, size=(1200, 680), calib=None)
    cam = open_dataset(seq.root).camera
    assert (cam.width, cam.height) == (1200, 680)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (600, 600, 599.5, 339.5)


def test_frame_numbers_give_timestamps_and_trajectory_lines(tmp_path):
    seq = make_replica(tmp_path / "room0", n=6)
    for path in seq.images[:3]:  # a render that starts at frame 3
        path.unlink()
    frames = list(open_dataset(seq.root))
    assert [f.index for f in frames] == [0, 1, 2]
    assert [f.timestamp for f in frames] == pytest.approx([3 / 30, 4 / 30, 5 / 30])
    assert np.allclose(frames[0].T_wc, seq.poses[3])


def test_non_finite_pose_names_the_line(tmp_path):
    seq = make_replica(tmp_path / "room0")
    lines = (seq.root / "traj.txt").read_text().splitlines()
    lines[2] = lines[2].replace(lines[2].split()[5], "inf", 1)
    (seq.root / "traj.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=r"traj\.txt:3: non-finite"):
        open_dataset(seq.root)


def test_short_trajectory_is_an_error(tmp_path):
    seq = make_replica(tmp_path / "room0")
    lines = (seq.root / "traj.txt").read_text().splitlines()
    (seq.root / "traj.txt").write_text("\n".join(lines[:4]) + "\n")
    with pytest.raises(DatasetError, match=r"4 poses, but frame000004\.jpg needs line 5"):
        open_dataset(seq.root)


def test_malformed_trajectory_line(tmp_path):
    seq = make_replica(tmp_path / "room0")
    (seq.root / "traj.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(DatasetError, match=r"traj\.txt:1: expected 16 values"):
        open_dataset(seq.root)

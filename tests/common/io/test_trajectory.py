"""TUM trajectory files: round trip, comments, and clear errors on bad lines."""

import numpy as np
import pytest
import torch

from dimslam.common.errors import DatasetError
from dimslam.common.geometry import pose
from dimslam.common.io.trajectory import Trajectory, read_tum, write_tum


def test_round_trip(tmp_path):
    g = torch.Generator().manual_seed(3)
    xi = torch.randn(40, 6, generator=g, dtype=torch.float64)
    traj = Trajectory(np.arange(40) / 30.0 + 1.0, pose.exp_se3(xi).numpy())
    write_tum(tmp_path / "t.txt", traj, header="test")
    back = read_tum(tmp_path / "t.txt")
    assert len(back) == 40
    assert np.allclose(back.timestamps, traj.timestamps, atol=1e-6)
    assert np.allclose(back.poses, traj.poses, atol=1e-6)


def test_reads_room0_style_lines(tmp_path):
    f = tmp_path / "gt.txt"
    f.write_text(
        "# header\n# timestamp tx ty tz qx qy qz qw\n\n1.0 1 2 3 0 0 0 1\n1.5 0 0 0 0 0 1 0\n"
    )
    t = read_tum(f)
    assert np.allclose(t.positions[0], [1, 2, 3])
    assert np.allclose(t.poses[1, :3, :3], np.diag([-1.0, -1.0, 1.0]))


@pytest.mark.parametrize(
    "line,what",
    [
        ("1 2 3", "expected 8 values"),
        ("1 2 3 4 x 0 0 1", "not a number"),
        ("1 2 3 nan 0 0 0 1", "non-finite"),
        ("1 2 3 4 0 0 0 0", "zero quaternion"),
    ],
)
def test_bad_lines_name_file_and_line(tmp_path, line, what):
    f = tmp_path / "bad.txt"
    f.write_text("# ok\n" + line + "\n")
    with pytest.raises(DatasetError, match=rf"bad.txt:2: {what}"):
        read_tum(f)


def test_missing_and_empty_files(tmp_path):
    with pytest.raises(DatasetError, match="cannot read"):
        read_tum(tmp_path / "none.txt")
    (tmp_path / "empty.txt").write_text("# nothing\n")
    with pytest.raises(DatasetError, match="no poses"):
        read_tum(tmp_path / "empty.txt")

"""Trajectories and their TUM text format, the one place quaternions are read or written.

A TUM line is `timestamp tx ty tz qx qy qz qw` (camera-to-world, quaternion xyzw); `#` starts a
comment. Inside the system a trajectory is timestamps plus `T_wc` 4x4 matrices.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from dimslam.common.errors import DatasetError
from dimslam.common.geometry import pose
from dimslam.common.geometry.shapes import check_shape


@dataclass(frozen=True)
class Trajectory:
    """Timestamped camera-to-world poses.

    Attributes:
        timestamps: `(N,)` float64 seconds.
        poses: `(N, 4, 4)` float64 `T_wc`.
    """

    timestamps: np.ndarray
    poses: np.ndarray

    def __post_init__(self) -> None:
        check_shape("timestamps", self.timestamps, (None,))
        check_shape("poses", self.poses, (len(self.timestamps), 4, 4))

    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def positions(self) -> np.ndarray:
        """`(N, 3)` camera centres in the world frame."""
        return self.poses[:, :3, 3]

    @classmethod
    def from_lists(cls, timestamps, poses) -> Trajectory:
        """Build from sequences of floats and 4x4 arrays (float64 copies)."""
        ts = np.asarray(list(timestamps), dtype=np.float64)
        T = np.asarray(list(poses), dtype=np.float64).reshape(len(ts), 4, 4)
        return cls(ts, T)


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM trajectory file.

    Raises:
        DatasetError: naming the file and line if it is missing, malformed or non-finite.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as e:
        raise DatasetError(f"{path}: cannot read trajectory ({e.strerror})") from None
    rows = []
    for number, line in enumerate(text.splitlines(), 1):
        line = line.split("#")[0].strip()
        if not line:
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != 8:
            raise DatasetError(
                f"{path}:{number}: expected 8 values 'timestamp tx ty tz qx qy qz qw', "
                f"got {len(parts)}"
            )
        try:
            values = [float(x) for x in parts]
        except ValueError:
            raise DatasetError(f"{path}:{number}: not a number in {line!r}") from None
        if not np.all(np.isfinite(values)):
            raise DatasetError(f"{path}:{number}: non-finite pose {line!r}")
        if np.linalg.norm(values[4:]) < 1e-9:
            raise DatasetError(f"{path}:{number}: zero quaternion")
        rows.append(values)
    if not rows:
        raise DatasetError(f"{path}: no poses in file")
    data = np.asarray(rows, dtype=np.float64)
    R = pose.quat_to_matrix(torch.from_numpy(data[:, 4:8]))
    T = pose.make_pose(R, torch.from_numpy(data[:, 1:4]))
    return Trajectory(data[:, 0].copy(), T.numpy())


def tum_lines(traj: Trajectory) -> list[str]:
    """One TUM line `timestamp tx ty tz qx qy qz qw` per pose, in order, without comments."""
    T = torch.from_numpy(np.ascontiguousarray(traj.poses, dtype=np.float64))
    q = pose.matrix_to_quat(T[:, :3, :3]).numpy()
    t = traj.poses[:, :3, 3]
    return [
        f"{traj.timestamps[i]:.6f} "
        + " ".join(f"{x:.7f}" for x in t[i])
        + " "
        + " ".join(f"{x:.7f}" for x in q[i])
        for i in range(len(traj))
    ]


def format_tum(traj: Trajectory, header: str | None = None) -> str:
    """The text of a TUM trajectory file: optional `# header`, column names, one line per pose."""
    lines = [f"# {header}"] if header else []
    lines.append("# timestamp tx ty tz qx qy qz qw")
    lines.extend(tum_lines(traj))
    return "\n".join(lines) + "\n"


def write_tum(path: str | Path, traj: Trajectory, header: str | None = None) -> None:
    """Write a TUM trajectory file (parent folders created), one line per pose."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(format_tum(traj, header))

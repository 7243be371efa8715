"""EuRoC MAV (ASL layout): `mav0/cam0/` images, `sensor.yaml`, and the Vicon/Leica ground truth.

Image timestamps are integer nanoseconds. The ground truth is the body (IMU) pose `T_wb` with
its quaternion in w x y z order; the camera pose is `T_wc = T_wb @ T_bs`, `T_BS` from
`sensor.yaml`. The grayscale images become three equal channels; their radial-tangential
distortion is undone.

There is no YAML parser among the dependencies, and `sensor.yaml` is simple: the few keys
needed (`key: [numbers]`, possibly over several lines) are read with a regular expression.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import ClassVar

import numpy as np
import torch

from dimslam.common.errors import DatasetError
from dimslam.common.geometry import pose
from dimslam.common.io.datasets.base import Entry, FileReader, Intrinsics
from dimslam.common.io.datasets.files import (
    associate,
    attach,
    line_of,
    quat_poses,
    read_rows,
    read_table,
)

_RADTAN = {"radial-tangential", "radtan", "plumb_bob"}


def mav0_folder(path: Path) -> Path | None:
    """The `mav0` folder of an EuRoC sequence given as the sequence folder or `mav0` itself."""
    for mav0 in (path / "mav0", path):
        if (mav0 / "cam0" / "data.csv").is_file():
            return mav0
    return None


def yaml_numbers(
    path: Path, text: str, key: str, count: int, after: str | None = None
) -> list[float]:
    """The list of numbers `key: [a, b, ...]` in a YAML text (the list may span lines).

    Args:
        path: the file, for messages.
        text: its content.
        key: the entry's name.
        count: how many numbers it must hold.
        after: look for `key` only after this entry (for nested keys such as `T_BS: data:`).

    Raises:
        DatasetError: naming the file and key if the entry is missing or malformed.
    """
    start, name = 0, key
    if after is not None:
        parent = re.search(rf"^\s*{re.escape(after)}\s*:", text, re.MULTILINE)
        if parent is None:
            raise DatasetError(f"{path}: no '{after}:' entry")
        start, name = parent.end(), f"{after}: {key}"
    entry = re.compile(rf"^\s*{re.escape(key)}\s*:\s*\[([^\]]*)\]", re.MULTILINE)
    match = entry.search(text, start)
    if match is None:
        raise DatasetError(f"{path}: no '{name}: [...]' entry")
    try:
        values = [float(v) for v in match.group(1).replace("\n", " ").split(",") if v.strip()]
    except ValueError:
        raise DatasetError(f"{path}: '{name}' must be a list of numbers") from None
    if len(values) != count or not np.all(np.isfinite(values)):
        raise DatasetError(f"{path}: '{name}' must hold {count} finite numbers, got {values}")
    return values


class EurocReader(FileReader):
    layout: ClassVar[str] = "euroc"
    signature: ClassVar[str] = "mav0/cam0/data.csv + sensor.yaml"

    @classmethod
    def detect(cls, source: str | Path | int) -> bool:
        return isinstance(source, (str, Path)) and mav0_folder(Path(source)) is not None

    @property
    def _cam0(self) -> Path:
        return (mav0_folder(self.root) or self.root / "mav0") / "cam0"

    def _sensor_yaml(self) -> tuple[Path, str]:
        path = self._cam0 / "sensor.yaml"
        try:
            return path, path.read_text()
        except OSError as e:
            raise DatasetError(f"{path}: cannot read camera calibration ({e.strerror})") from None

    def _list(self) -> list[Entry]:
        index = self._cam0 / "data.csv"
        entries = []
        for number, fields in read_rows(index, "frame list '#timestamp [ns],filename'", sep=","):
            if len(fields) != 2 or not fields[0].isdigit():
                line = ",".join(fields)
                raise DatasetError(
                    f"{index}:{number}: expected 'timestamp_ns,filename', got {line!r}"
                )
            entries.append(Entry(int(fields[0]) / 1e9, self._cam0 / "data" / fields[1]))
        return entries

    def _with_poses(self, entries: list[Entry]) -> list[Entry]:
        path = self._cam0.parent / "state_groundtruth_estimate0" / "data.csv"
        if not path.exists():
            return entries
        table = read_table(path, 8, "timestamp, p_RS_R x y z, q_RS w x y z", sep=",")
        q_wxyz = table[:, 4:8]
        zero = np.linalg.norm(q_wxyz, axis=1) < 1e-9
        if zero.any():
            raise DatasetError(f"{path}:{line_of(path, int(np.argmax(zero)))}: zero quaternion")
        yaml_path, text = self._sensor_yaml()
        T_bs = np.array(yaml_numbers(yaml_path, text, "data", 16, after="T_BS")).reshape(4, 4)
        matches = associate(np.array([e.timestamp for e in entries]), table[:, 0] / 1e9)
        # The ground truth runs at 200 Hz: convert only the samples matched to a frame.
        found = matches >= 0
        rows = matches[found]
        T_wb = quat_poses(table[rows, 1:4], q_wxyz[rows][:, [1, 2, 3, 0]])
        T_wc = pose.compose(torch.from_numpy(T_wb), torch.from_numpy(T_bs)).numpy()
        positions = np.full(len(entries), -1)
        positions[found] = np.arange(len(rows))
        return attach(entries, T_wc, positions)

    def _builtin_intrinsics(self) -> Intrinsics:
        path, text = self._sensor_yaml()
        model = re.search(r"^\s*distortion_model\s*:\s*['\"]?([\w-]+)", text, re.MULTILINE)
        if model is not None and model.group(1) not in _RADTAN:
            raise DatasetError(
                f"{path}: distortion model {model.group(1)!r} is not supported "
                "(radial-tangential only)"
            )
        fu, fv, cu, cv = yaml_numbers(path, text, "intrinsics", 4)
        dist = yaml_numbers(path, text, "distortion_coefficients", 4)
        width, height = (int(v) for v in yaml_numbers(path, text, "resolution", 2))
        return Intrinsics(fu, fv, cu, cv, tuple(dist), (width, height), str(path))

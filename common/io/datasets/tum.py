"""TUM RGB-D: `rgb.txt` lists the frames, `groundtruth.txt` gives their poses.

`rgb.txt` lines are `timestamp filename`, `groundtruth.txt` lines `timestamp tx ty tz qx qy qz
qw`; a frame takes the nearest ground-truth pose within 0.02 s, or none. Intrinsics: a
`calib.txt` in the folder, else the Freiburg camera named by the folder
(`rgbd_dataset_freiburg1_desk`, `fr2_xyz`, ...).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import ClassVar

import numpy as np

from dimslam.common.errors import DatasetError
from dimslam.common.io.datasets.base import CALIB_NAME, Entry, FileReader, Intrinsics
from dimslam.common.io.datasets.files import associate, attach, numeric_table, read_rows
from dimslam.common.io.trajectory import read_tum

# The TUM RGB-D benchmark's calibration of its three Kinects' RGB cameras (640x480), as
# published on its "file formats" page: fx fy cx cy, then d0..d4 = OpenCV's k1 k2 p1 p2 k3.
# The images were stored unrectified, so the distortion must be undone.
FREIBURG = {
    1: Intrinsics(
        517.3,
        516.5,
        318.6,
        255.3,
        (0.2624, -0.9531, -0.0054, 0.0026, 1.1633),
        (640, 480),
        "built-in freiburg1",
    ),
    2: Intrinsics(
        520.9,
        521.0,
        325.1,
        249.7,
        (0.2312, -0.7849, -0.0033, -0.0001, 0.9172),
        (640, 480),
        "built-in freiburg2",
    ),
    3: Intrinsics(535.4, 539.2, 320.1, 247.6, (), (640, 480), "built-in freiburg3"),
}
_FREIBURG_NAME = re.compile(r"(?:^|[^a-z0-9])(?:freiburg|fr)([123])(?![0-9])", re.IGNORECASE)


def freiburg_camera(folder: Path) -> int | None:
    """1, 2 or 3 if the folder's name says which Freiburg Kinect recorded it, else None."""
    match = _FREIBURG_NAME.search(folder.resolve().name)
    return int(match.group(1)) if match else None


class TumReader(FileReader):
    layout: ClassVar[str] = "tum"
    signature: ClassVar[str] = "rgb.txt (+ groundtruth.txt)"

    @classmethod
    def detect(cls, source: str | Path | int) -> bool:
        return isinstance(source, (str, Path)) and (Path(source) / "rgb.txt").is_file()

    def _list(self) -> list[Entry]:
        index = self.root / "rgb.txt"
        rows = read_rows(index, "frame list 'timestamp filename'")
        for number, fields in rows:
            if len(fields) != 2:
                line = " ".join(fields)
                raise DatasetError(f"{index}:{number}: expected 'timestamp filename', got {line!r}")
        times = numeric_table(index, rows, 1, "timestamp filename")[:, 0]
        return [
            Entry(float(t), self.root / fields[1])
            for t, (_, fields) in zip(times, rows, strict=True)
        ]

    def _with_poses(self, entries: list[Entry]) -> list[Entry]:
        path = self.root / "groundtruth.txt"
        if not path.exists():
            return entries
        gt = read_tum(path)
        times = np.array([e.timestamp for e in entries])
        return attach(entries, gt.poses, associate(times, gt.timestamps))

    def _builtin_intrinsics(self) -> Intrinsics:
        camera = freiburg_camera(self.root)
        if camera is None:
            raise DatasetError(
                f"{self.root / CALIB_NAME}: missing; the folder name does not say freiburg1/2/3, "
                "so write the intrinsics there as 'fx fy cx cy [k1 k2 p1 p2 [k3]]' "
                "(or pass --calib)"
            )
        return FREIBURG[camera]

"""Microsoft 7-Scenes: `frame-XXXXXX.color.png|jpg` with an optional `frame-XXXXXX.pose.txt`.

Poses are 4x4 camera-to-world, whitespace separated. Intrinsics: `calib.txt`, else
`camera-intrinsics.txt` (a 3x3 K), else the dataset's nominal Kinect values. Frames are 30 Hz
and numbered in their names (a sequence may start at any number): timestamp = number / 30.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import ClassVar

import numpy as np

from dimslam.common.errors import DatasetError
from dimslam.common.io.datasets.base import Entry, FileReader, Intrinsics
from dimslam.common.io.datasets.files import read_rows

FPS = 30.0
BUILTIN = Intrinsics(585.0, 585.0, 320.0, 240.0, (), (640, 480), "built-in 7-Scenes")
INTRINSICS_NAME = "camera-intrinsics.txt"
_FRAME = re.compile(r"frame-(\d+)\.color\.(?:png|jpg)", re.IGNORECASE)


def read_matrix(path: Path, rows: int, cols: int, what: str) -> np.ndarray:
    """A whitespace-separated `rows x cols` matrix file as float64.

    Raises:
        DatasetError: naming the file if it is unreadable, the wrong size or non-finite.
    """
    lines = read_rows(path, what)
    try:
        values = np.array([float(v) for _, fields in lines for v in fields])
    except ValueError:
        raise DatasetError(f"{path}: {what} must be numbers") from None
    if values.size != rows * cols:
        raise DatasetError(f"{path}: {what} must be {rows}x{cols} numbers, got {values.size}")
    if not np.all(np.isfinite(values)):
        raise DatasetError(f"{path}: non-finite {what}")
    return values.reshape(rows, cols)


class SevenScenesReader(FileReader):
    layout: ClassVar[str] = "7scenes"
    signature: ClassVar[str] = "frame-XXXXXX.color.png|jpg (+ .pose.txt)"

    @classmethod
    def detect(cls, source: str | Path | int) -> bool:
        if not isinstance(source, (str, Path)) or not Path(source).is_dir():
            return False
        return any(_FRAME.fullmatch(p.name) for p in Path(source).iterdir())

    def _list(self) -> list[Entry]:
        # One image per frame number; the first extension in name order if both exist.
        frames: dict[int, Path] = {}
        for path in sorted(self.root.iterdir()):
            match = _FRAME.fullmatch(path.name)
            if match:
                frames.setdefault(int(match.group(1)), path)
        return [Entry(number / FPS, frames[number]) for number in sorted(frames)]

    def _with_poses(self, entries: list[Entry]) -> list[Entry]:
        out = []
        for e in entries:
            pose_path = e.path.with_name(e.path.name.split(".")[0] + ".pose.txt")
            T_wc = read_matrix(pose_path, 4, 4, "pose") if pose_path.exists() else None
            out.append(Entry(e.timestamp, e.path, T_wc))
        return out

    def _builtin_intrinsics(self) -> Intrinsics:
        path = self.root / INTRINSICS_NAME
        if not path.exists():
            return BUILTIN
        K = read_matrix(path, 3, 3, "intrinsic matrix")
        return Intrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], (), None, str(path))

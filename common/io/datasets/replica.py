"""Replica as rendered for iMAP / NICE-SLAM: `results/frame*.jpg` and `traj.txt`.

`traj.txt` has one row-major 4x4 camera-to-world pose (OpenCV axes) per line, line k for
`frame{k}`; the `depth*.png` beside the colour images are ignored. Frames are 30 Hz.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import ClassVar

from dimslam.common.errors import DatasetError
from dimslam.common.io.datasets.base import Entry, FileReader, Intrinsics
from dimslam.common.io.datasets.files import matrix_poses, natural_key, read_table

FPS = 30.0
# The renderer's fixed camera (NICE-SLAM configs/Replica/replica.yaml).
BUILTIN = Intrinsics(600.0, 600.0, 599.5, 339.5, (), (1200, 680), "built-in Replica")
_FRAME = re.compile(r"frame(\d+)\.jpg", re.IGNORECASE)


class ReplicaReader(FileReader):
    layout: ClassVar[str] = "replica"
    signature: ClassVar[str] = "results/frame*.jpg (+ traj.txt)"

    @classmethod
    def detect(cls, source: str | Path | int) -> bool:
        if not isinstance(source, (str, Path)) or not (Path(source) / "results").is_dir():
            return False
        return any(_FRAME.fullmatch(p.name) for p in (Path(source) / "results").iterdir())

    def _list(self) -> list[Entry]:
        folder = self.root / "results"
        if not folder.is_dir():
            raise DatasetError(f"{folder}: missing; Replica renders keep their frames there")
        names = [p.name for p in folder.iterdir() if _FRAME.fullmatch(p.name)]
        names.sort(key=natural_key)
        return [Entry(_number(n) / FPS, folder / n) for n in names]

    def _with_poses(self, entries: list[Entry]) -> list[Entry]:
        path = self.root / "traj.txt"
        if not path.exists():
            return entries
        poses = matrix_poses(path, read_table(path, 16, "4x4 row-major camera-to-world"))
        out = []
        for e in entries:
            k = _number(e.path.name)
            if k >= len(poses):
                raise DatasetError(
                    f"{path}: {len(poses)} poses, but {e.path.name} needs line {k + 1}"
                )
            out.append(Entry(e.timestamp, e.path, poses[k].copy()))
        return out

    def _builtin_intrinsics(self) -> Intrinsics:
        return BUILTIN


def _number(name: str) -> int:
    """The frame number in `frame000123.jpg`."""
    return int(_FRAME.fullmatch(name).group(1))

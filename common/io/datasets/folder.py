"""A plain folder of images, with a `calib.txt` beside them.

Images are taken in natural name order (`2.png` before `10.png`). If every file name (without
extension) is a decimal number such as `1305031102.175304`, it is the timestamp in seconds (the
TUM convention); otherwise, frame numbers like `000001.png` included, frames are `fps` apart.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import ClassVar

from dimslam.common.io.datasets.base import IMAGE_SUFFIXES, Entry, FileReader
from dimslam.common.io.datasets.files import natural_key


def _is_image(path: Path) -> bool:
    return path.suffix.lower() in IMAGE_SUFFIXES and path.is_file()


def _seconds(stem: str) -> float | None:
    if "." not in stem:  # `000001` is a frame number, not one second
        return None
    try:
        value = float(stem)
    except ValueError:
        return None
    return value if math.isfinite(value) else None


class FolderReader(FileReader):
    layout: ClassVar[str] = "folder"
    signature: ClassVar[str] = "images (png/jpg/jpeg/bmp/tif/tiff) + calib.txt"

    @classmethod
    def detect(cls, source: str | Path | int) -> bool:
        if not isinstance(source, (str, Path)) or not Path(source).is_dir():
            return False
        return any(_is_image(p) for p in Path(source).iterdir())

    def _list(self) -> list[Entry]:
        paths = [p for p in self.root.iterdir() if _is_image(p)]
        stamps = [_seconds(p.stem) for p in paths]
        if paths and all(s is not None for s in stamps):
            # Numeric names sort by value: natural order would put 1.5 before 1.25.
            entries = [Entry(t, p) for t, p in zip(stamps, paths, strict=True)]
            return sorted(entries, key=lambda e: (e.timestamp, e.path.name))
        # All or nothing: a mix of named and counted timestamps would not be monotonic.
        paths.sort(key=lambda p: natural_key(p.name))
        return [Entry(i / self.options.fps, p) for i, p in enumerate(paths)]

"""Dataset readers: one protocol (`Reader`), one small class per layout.

    reader = open_dataset("data/room0", options=ReaderOptions(stride=2, width=320))
    for frame in reader:            # Frame(index, timestamp, rgb (H, W, 3) uint8, T_wc | None)
        ...
    reader.camera                   # intrinsics of the yielded frames (undistorted, resized)
    reader.ground_truth()           # Trajectory of the selected frames, no image decoded

The layout is detected from the source (see `detect_layout`) or named (`LAYOUTS`).
"""

from __future__ import annotations

from pathlib import Path

from dimslam.common.datasets.base import Frame, Intrinsics, Reader, ReaderOptions
from dimslam.common.datasets.euroc import EurocReader
from dimslam.common.datasets.folder import FolderReader
from dimslam.common.datasets.replica import ReplicaReader
from dimslam.common.datasets.seven_scenes import SevenScenesReader
from dimslam.common.datasets.tum import TumReader
from dimslam.common.datasets.video import CameraReader, VideoReader
from dimslam.common.errors import DatasetError

# Name -> class, in detection order: a digit string is a camera; index files (rgb.txt,
# results/, mav0/) and 7-Scenes names are specific; a folder of any images is the last resort,
# since every dataset folder above also holds images.
LAYOUTS: dict[str, type[Reader]] = {
    cls.layout: cls
    for cls in (
        CameraReader,
        TumReader,
        ReplicaReader,
        EurocReader,
        SevenScenesReader,
        VideoReader,
        FolderReader,
    )
}

__all__ = [
    "LAYOUTS",
    "DatasetError",
    "Frame",
    "Intrinsics",
    "Reader",
    "ReaderOptions",
    "detect_layout",
    "open_dataset",
]


def detect_layout(source: str | Path | int) -> str:
    """The layout of `source`, from its files (no image is decoded).

    Args:
        source: a dataset folder, a video file, or a camera index (int or digit string).

    Returns:
        A key of `LAYOUTS`.

    Raises:
        DatasetError: if the source does not exist or matches no layout; the message lists
            what each layout looks for.
    """
    if CameraReader.detect(source):
        return CameraReader.layout
    path = Path(source)
    if not path.exists():
        raise DatasetError(f"{path}: no such file or folder")
    for name, cls in LAYOUTS.items():
        if cls.detect(path):
            return name
    known = "; ".join(f"{name}: {cls.signature}" for name, cls in LAYOUTS.items())
    raise DatasetError(f"{path}: not a known dataset layout. Known layouts: {known}")


def open_dataset(
    source: str | Path | int, layout: str | None = None, options: ReaderOptions | None = None
) -> Reader:
    """A reader for `source`, in the named layout or the detected one.

    Args:
        source: a dataset folder, a video file, or a camera index (int or digit string).
        layout: a key of `LAYOUTS`; None detects it.
        options: selection, resizing and intrinsics overrides (default: `ReaderOptions()`).

    Raises:
        DatasetError: for an unknown layout name or a source that cannot be read.
    """
    if layout is None:
        layout = detect_layout(source)
    elif layout not in LAYOUTS:
        raise DatasetError(f"unknown layout {layout!r}; choose one of {', '.join(LAYOUTS)}")
    if isinstance(source, int) and layout != CameraReader.layout:
        raise DatasetError(f"{layout}: needs a path, got the camera index {source}")
    return LAYOUTS[layout](source, options)

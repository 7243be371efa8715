"""Dataset readers: one protocol (`Reader`), one small class per layout.

    reader = open_dataset("data/room0", options=ReaderOptions(stride=2, width=320))
    for frame in reader:            # Frame(index, timestamp, rgb (H, W, 3) uint8, T_wc | None)
        ...
    reader.camera                   # intrinsics of the yielded frames (undistorted, resized)
    reader.ground_truth()           # Trajectory of the selected frames, no image decoded

The layout is detected from the source (see `detect_layout`) or named (`LAYOUTS`).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from dimslam.common.errors import DatasetError
from dimslam.common.io.datasets.base import Frame, Intrinsics, Reader, ReaderOptions
from dimslam.common.io.datasets.euroc import EurocReader
from dimslam.common.io.datasets.folder import FolderReader
from dimslam.common.io.datasets.replica import ReplicaReader
from dimslam.common.io.datasets.seven_scenes import SevenScenesReader
from dimslam.common.io.datasets.tum import TumReader
from dimslam.common.io.datasets.video import CameraReader, VideoReader

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
    "add_reader_arguments",
    "detect_layout",
    "open_dataset",
    "open_from_args",
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


def add_reader_arguments(p: argparse.ArgumentParser) -> None:
    """The options every dataset reader honours (see `ReaderOptions`)."""

    g = p.add_argument_group("dataset reading")
    g.add_argument(
        "--layout", choices=sorted(LAYOUTS), help="dataset layout (default: detected from the path)"
    )
    g.add_argument("--stride", type=int, default=1, help="use every N-th frame (default: 1)")
    g.add_argument("--start", type=int, default=0, help="first frame to use (default: 0)")
    g.add_argument("--end", type=int, default=None, help="frame to stop before (default: the last)")
    g.add_argument(
        "--width", type=int, default=None, help="resize frames to this width; intrinsics follow"
    )
    g.add_argument(
        "--calib",
        type=Path,
        default=None,
        help="intrinsics file 'fx fy cx cy [k1 k2 p1 p2 [k3]]' overriding the dataset's own",
    )
    g.add_argument(
        "--fps",
        type=float,
        default=ReaderOptions.fps,
        help="frame rate of sources whose frames carry no timestamp: image folders, videos "
        f"without them (default: {ReaderOptions.fps:g})",
    )


def reader_options(args: argparse.Namespace) -> ReaderOptions:
    """The `ReaderOptions` parsed by `add_reader_arguments`."""
    return ReaderOptions(
        stride=args.stride,
        start=args.start,
        end=args.end,
        width=args.width,
        calib=args.calib,
        fps=args.fps,
    )


def open_from_args(args: argparse.Namespace, source: str | int) -> Reader:
    """`open_dataset` with the options parsed by `add_reader_arguments`."""
    return open_dataset(source, layout=args.layout, options=reader_options(args))

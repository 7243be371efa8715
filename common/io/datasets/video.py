"""Sources read through `cv2.VideoCapture`: a video file or a live camera.

Both stream: frames are grabbed in order, those the options do not select are dropped before
decoding. Neither has ground truth. Intrinsics are checked when the source is opened, since
there is nothing else to do with a stream that has none.
"""

from __future__ import annotations

import abc
import logging
import math
import time
from collections.abc import Iterator
from pathlib import Path
from typing import ClassVar

import cv2

from dimslam.common.errors import DatasetError
from dimslam.common.io.datasets.base import Frame, Reader, ReaderOptions

log = logging.getLogger(__name__)

_EXTENSIONS = "mp4 avi mkv mov webm m4v mpg mpeg wmv flv ts 3gp ogv mjpeg mjpg h264 hevc"
VIDEO_SUFFIXES = frozenset(f".{ext}" for ext in _EXTENSIONS.split())


class _CaptureReader(Reader):
    """What a video file and a camera share: the grab / select / decode loop."""

    name: str
    _size: tuple[int, int]

    @abc.abstractmethod
    def _open(self) -> cv2.VideoCapture:
        """A fresh capture of the source; DatasetError if it cannot be opened."""

    @abc.abstractmethod
    def _timestamp(self, cap: cv2.VideoCapture, index: int) -> float:
        """Seconds for frame `index`, just grabbed from `cap`."""

    def _image_size(self) -> tuple[int, int]:
        return self._size

    def _probe(self, cap: cv2.VideoCapture) -> tuple[int, int]:
        """Frame size from the capture's properties (no decoding), or from a first frame."""
        width = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH))
        height = int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        if width > 0 and height > 0:
            return width, height
        ok, image = cap.read()
        if not ok or image is None:
            raise DatasetError(f"{self.name}: no frame can be read")
        return image.shape[1], image.shape[0]

    def _stream(self, cap: cv2.VideoCapture) -> Iterator[Frame]:
        end = self.options.end
        index = 0
        while end is None or index < end:
            if not cap.grab():
                self._ended(index)
                return
            if self.options.selects(index):
                timestamp = self._timestamp(cap, index)
                ok, image = cap.retrieve()
                name = f"{self.name} frame {index}"
                if ok and image is not None:
                    yield Frame(index, timestamp, self._prepare(image, name))
                else:
                    self._skip(name, "cannot decode")
            index += 1

    def _ended(self, index: int) -> None:
        """Called when no further frame can be grabbed, after `index` frames."""


class VideoReader(_CaptureReader):
    """A video file, with `calib.txt` in its folder (or `options.calib`).

    Timestamps come from the container; where it gives none that increase, frames are
    `options.fps` apart from the last good one.
    """

    layout: ClassVar[str] = "video"
    signature: ClassVar[str] = "a video file (" + " ".join(sorted(VIDEO_SUFFIXES)) + ") + calib.txt"

    def __init__(self, path: str | Path, options: ReaderOptions | None = None) -> None:
        super().__init__(options)
        self.path = Path(path)
        self.name = str(self.path)
        self._last: tuple[int, float] | None = None  # (index, seconds) of the last frame
        if not self.path.is_file():
            raise DatasetError(f"{self.path}: no such video file")
        self.intrinsics()  # fail now, not at the first frame
        cap = self._open()
        try:
            self._size = self._probe(cap)
            count = cap.get(cv2.CAP_PROP_FRAME_COUNT)
        finally:
            cap.release()
        # Containers may not know their length (0, or negative for some streams).
        self._count = int(count) if math.isfinite(count) and count > 0 else None
        if self._count is not None and self.options.start >= self._count:
            raise DatasetError(
                f"{self.path}: start {self.options.start} is beyond the last frame "
                f"({self._count - 1})"
            )

    @classmethod
    def detect(cls, source: str | Path | int) -> bool:
        return (
            isinstance(source, (str, Path))
            and Path(source).suffix.lower() in VIDEO_SUFFIXES
            and Path(source).is_file()
        )

    def _open(self) -> cv2.VideoCapture:
        cap = cv2.VideoCapture(str(self.path))
        if not cap.isOpened():
            raise DatasetError(f"{self.path}: OpenCV cannot open it as a video")
        return cap

    def _calib_dir(self) -> Path | None:
        return self.path.parent

    def __len__(self) -> int:
        """Selected frames, from the container's frame count (an estimate for some codecs).

        Raises:
            TypeError: if the container does not state its frame count.
        """
        if self._count is None:
            raise TypeError(f"{self.path}: the container does not say how many frames it has")
        return len(range(self._count)[self.options.start : self.options.end : self.options.stride])

    def __iter__(self) -> Iterator[Frame]:
        self._last = None
        cap = self._open()
        try:
            yield from self._stream(cap)
        finally:
            cap.release()

    def _timestamp(self, cap: cv2.VideoCapture, index: int) -> float:
        seconds = cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0
        last = self._last
        usable = math.isfinite(seconds) and seconds >= 0 and (last is None or seconds > last[1])
        if not usable:
            # Continue from the last good timestamp so that time never runs backwards.
            since, at = (0, 0.0) if last is None else last
            seconds = at + (index - since) / self.options.fps
        self._last = index, seconds
        return seconds

    def _ended(self, index: int) -> None:
        if self._count is not None and index < self._count:
            log.warning(
                "%s: ended after %d frames, the container said %d", self.path, index, self._count
            )


class CameraReader(_CaptureReader):
    """A live camera by device index; intrinsics from `options.calib`; wall-clock timestamps.

    The stream is unbounded unless `options.end` is set. Each iteration holds the device and
    releases it when the loop ends.
    """

    layout: ClassVar[str] = "camera"
    signature: ClassVar[str] = "a camera device index (0, 1, ...) + --calib"

    def __init__(self, index: int | str, options: ReaderOptions | None = None) -> None:
        super().__init__(options)
        if isinstance(index, str) and not index.isdigit():
            raise DatasetError(f"{index!r}: a camera is named by its device index (0, 1, ...)")
        self.index = int(index)
        self.name = f"camera {self.index}"
        self.intrinsics()  # fail before touching the device
        self._cap: cv2.VideoCapture | None = self._open()
        self._size = self._probe(self._cap)

    @classmethod
    def detect(cls, source: str | Path | int) -> bool:
        return (isinstance(source, int) and not isinstance(source, bool)) or (
            isinstance(source, str) and source.isdigit()
        )

    def _open(self) -> cv2.VideoCapture:
        cap = cv2.VideoCapture(self.index)
        if not cap.isOpened():
            cap.release()
            raise DatasetError(
                f"{self.name}: cannot open the device (is it connected, is {self.index} its index?)"
            )
        return cap

    def __len__(self) -> int:
        """Selected frames when `options.end` bounds the stream.

        Raises:
            TypeError: for an unbounded stream.
        """
        if self.options.end is None:
            raise TypeError(f"{self.name}: a live stream has no length (set an end frame)")
        return len(range(self.options.start, self.options.end, self.options.stride))

    def __iter__(self) -> Iterator[Frame]:
        cap, self._cap = self._cap or self._open(), None
        try:
            yield from self._stream(cap)
        finally:
            cap.release()

    def _timestamp(self, cap: cv2.VideoCapture, index: int) -> float:
        return time.time()

    def _ended(self, index: int) -> None:
        log.warning("%s: no frame after %d frames (device disconnected?)", self.name, index)

    def close(self) -> None:
        super().close()
        if self._cap is not None:
            self._cap.release()
            self._cap = None

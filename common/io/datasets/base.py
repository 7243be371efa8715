"""The reader protocol and everything the layouts share.

A layout class only says where its frames are, what their timestamps and ground-truth poses
are, and which intrinsics hold when the user gives none. Everything else lives here, once:
frame selection (start / end / stride), image decoding, grayscale and BGR to RGB, the image
size check, undistortion, resizing, skipping corrupt frames, and the order in which
intrinsics are looked up (`options.calib`, then a `calib.txt` beside the data, then the
layout's own).

Frame numbers: `Frame.index`, `ReaderOptions.start` and `ReaderOptions.end` count the frames of
the source in order from 0, before the stride is applied, whatever the file names say.
"""

from __future__ import annotations

import abc
import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import ClassVar

import cv2
import numpy as np

from dimslam.common.errors import DatasetError
from dimslam.common.geometry.camera import Camera, read_calib
from dimslam.common.io.trajectory import Trajectory

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = frozenset({".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"})
CALIB_NAME = "calib.txt"

# A JPEG cut short (an interrupted copy) has no end-of-image marker; some encoders pad the
# file after the marker, so look for it in the last few bytes rather than at the very end.
_JPEG_TAIL = 4096


@dataclass(frozen=True, eq=False)
class Frame:
    """One image of a sequence, ready for the system.

    Attributes:
        index: the frame's number in the source (counted from 0, before the stride).
        timestamp: seconds, as the dataset gives them.
        rgb: `(H, W, 3)` uint8, RGB order, undistorted and resized like `Reader.camera`.
        T_wc: `(4, 4)` float64 ground-truth camera-to-world, or None where unknown.
    """

    index: int
    timestamp: float
    rgb: np.ndarray
    T_wc: np.ndarray | None = None


@dataclass(frozen=True)
class ReaderOptions:
    """What every reader honours.

    Attributes:
        stride: use every `stride`-th frame.
        start: first source frame to use.
        end: source frame to stop before (None: the last).
        width: resize frames to this width, the height keeping the aspect ratio; the
            intrinsics follow.
        calib: an intrinsics file `fx fy cx cy [k1 k2 p1 p2 [k3]]` overriding the dataset's own.
        fps: frame rate for sources whose frames carry no timestamp.
    """

    stride: int = 1
    start: int = 0
    end: int | None = None
    width: int | None = None
    calib: Path | None = None
    fps: float = 30.0

    def __post_init__(self) -> None:
        if self.stride < 1:
            raise DatasetError(f"stride must be at least 1, got {self.stride}")
        if self.start < 0:
            raise DatasetError(f"start must be 0 or more, got {self.start}")
        if self.end is not None and self.end <= self.start:
            raise DatasetError(f"end ({self.end}) must be after start ({self.start})")
        if self.width is not None and self.width < 1:
            raise DatasetError(f"width must be positive, got {self.width}")
        if not (math.isfinite(self.fps) and self.fps > 0):
            raise DatasetError(f"fps must be positive, got {self.fps}")
        if self.calib is not None:
            object.__setattr__(self, "calib", Path(self.calib))

    def selects(self, index: int) -> bool:
        """Whether source frame `index` is used (for streams of unknown length)."""
        in_range = self.start <= index and (self.end is None or index < self.end)
        return in_range and (index - self.start) % self.stride == 0


@dataclass(frozen=True)
class Intrinsics:
    """Intrinsics before the image size is known.

    Attributes:
        fx, fy, cx, cy: pinhole parameters in pixels.
        dist: radial-tangential `(k1, k2, p1, p2[, k3])`, or `()`.
        size: `(width, height)` the values refer to, when the source states it; images of
            another size are then an error rather than silently wrong intrinsics.
        origin: where the values come from, for messages.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, ...] = ()
    size: tuple[int, int] | None = None
    origin: str = "built-in"

    @classmethod
    def from_calib(cls, path: Path) -> Intrinsics:
        """Read a `calib.txt` (see `camera.read_calib`)."""
        fx, fy, cx, cy, dist = read_calib(path)
        return cls(fx, fy, cx, cy, dist, origin=str(path))


class Reader(abc.ABC):
    """A sequence of frames with known intrinsics; one subclass per layout.

    Attributes:
        layout: the layout's name, as `open_dataset` takes it.
        signature: what detection looks for, for messages listing the layouts.
        options: the options the reader was opened with.
        skipped: corrupt or unreadable frames skipped so far.
    """

    layout: ClassVar[str]
    signature: ClassVar[str]

    def __init__(self, options: ReaderOptions | None = None) -> None:
        self.options = options if options is not None else ReaderOptions()
        self.skipped = 0
        self._cameras: tuple[Camera, Camera] | None = None
        self._maps: tuple[np.ndarray, np.ndarray] | None = None

    # -- what a layout provides ------------------------------------------------------------

    @classmethod
    @abc.abstractmethod
    def detect(cls, source: str | Path | int) -> bool:
        """Whether `source` looks like this layout (cheap: no image is decoded)."""

    @abc.abstractmethod
    def __iter__(self) -> Iterator[Frame]:
        """The selected frames, in order; unreadable ones are skipped and counted."""

    @abc.abstractmethod
    def __len__(self) -> int:
        """The number of selected frames (unreadable ones included)."""

    @abc.abstractmethod
    def _image_size(self) -> tuple[int, int]:
        """`(width, height)` of the images as stored, before undistortion and resizing."""

    def _calib_dir(self) -> Path | None:
        """The folder whose `calib.txt` overrides the layout's intrinsics, if any."""
        return None

    def _builtin_intrinsics(self) -> Intrinsics:
        """The layout's own intrinsics, used when there is no calibration file."""
        folder = self._calib_dir()
        if folder is None:
            raise DatasetError(
                f"{self.layout}: no intrinsics; pass a calibration file "
                "'fx fy cx cy [k1 k2 p1 p2 [k3]]' (--calib)"
            )
        raise DatasetError(
            f"{folder / CALIB_NAME}: missing; {self.layout} sources need their intrinsics in it "
            "as 'fx fy cx cy [k1 k2 p1 p2 [k3]]' (or pass --calib)"
        )

    def ground_truth(self) -> Trajectory | None:
        """Ground truth of the selected frames that have it (no image is decoded), or None."""
        return None

    # -- shared ----------------------------------------------------------------------------

    @property
    def camera(self) -> Camera:
        """Intrinsics of the yielded frames: undistorted (`dist == ()`) and resized."""
        return self._camera_pair()[1]

    @property
    def raw_camera(self) -> Camera:
        """Intrinsics of the images as stored: original size, with their distortion."""
        return self._camera_pair()[0]

    def intrinsics(self) -> Intrinsics:
        """The intrinsics in force: `options.calib`, else `calib.txt` beside the data, else
        the layout's own."""
        if self.options.calib is not None:
            return Intrinsics.from_calib(self.options.calib)
        folder = self._calib_dir()
        if folder is not None and (folder / CALIB_NAME).is_file():
            return Intrinsics.from_calib(folder / CALIB_NAME)
        return self._builtin_intrinsics()

    def _camera_pair(self) -> tuple[Camera, Camera]:
        if self._cameras is None:
            intr = self.intrinsics()
            size = self._image_size()
            if intr.size is not None and tuple(intr.size) != size:
                raise DatasetError(
                    f"{intr.origin}: intrinsics are for {intr.size[0]}x{intr.size[1]} images but "
                    f"the images are {size[0]}x{size[1]}; give the right ones in {CALIB_NAME}"
                )
            try:
                values = (float(v) for v in (intr.fx, intr.fy, intr.cx, intr.cy))
                raw = Camera(*size, *values, tuple(float(d) for d in intr.dist))
            except ValueError as e:
                raise DatasetError(f"{intr.origin}: {e}") from None
            out = raw.undistorted()
            if self.options.width is not None and self.options.width != raw.width:
                out = out.resized(self.options.width)
            self._cameras = raw, out
        return self._cameras

    def _prepare(self, image: np.ndarray, name: str) -> np.ndarray:
        """A decoded image (gray, BGR or BGRA) to the yielded RGB: checked, undistorted, resized.

        Raises:
            DatasetError: naming `name`, if its size differs from the first image's.
        """
        raw, out = self._camera_pair()
        if image.ndim == 2 or image.shape[2] == 1:
            rgb = cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)
        elif image.shape[2] == 4:
            rgb = cv2.cvtColor(image, cv2.COLOR_BGRA2RGB)
        else:
            rgb = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
        height, width = rgb.shape[:2]
        if (width, height) != raw.size:
            raise DatasetError(
                f"{name}: image is {width}x{height} but the sequence's first image is "
                f"{raw.width}x{raw.height}; all images must have one size"
            )
        if raw.distorted:
            if self._maps is None:
                self._maps = raw.undistort_maps()
            rgb = cv2.remap(rgb, *self._maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        if out.size != raw.size:
            # INTER_AREA averages the pixels a downscaled pixel covers (no aliasing).
            shrink = out.width < raw.width
            interpolation = cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
            rgb = cv2.resize(rgb, out.size, interpolation=interpolation)
        return np.ascontiguousarray(rgb)

    def _skip(self, name: str | Path, reason: str) -> None:
        self.skipped += 1
        log.warning("%s: skipped (%s)", name, reason)

    def close(self) -> None:
        """Release what the reader holds: the undistortion maps, a capture device (streams)."""
        self._maps = None

    def __enter__(self) -> Reader:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"<{type(self).__name__} layout={self.layout!r}>"


@dataclass(frozen=True, eq=False)
class Entry:
    """One frame of an image-file sequence, before decoding.

    Attributes:
        timestamp: seconds.
        path: the image file.
        T_wc: `(4, 4)` float64 ground truth, or None.
    """

    timestamp: float
    path: Path
    T_wc: np.ndarray | None = None


class FileReader(Reader):
    """A sequence of image files; a layout lists them and attaches their ground truth.

    Subclasses implement `_list()` (all frames of the source, in order, without poses) and,
    where the layout has ground truth, `_with_poses(entries)` for the selected ones only.
    """

    def __init__(self, root: str | Path, options: ReaderOptions | None = None) -> None:
        super().__init__(options)
        self.root = Path(root)
        if not self.root.is_dir():
            raise DatasetError(f"{self.root}: not a folder")
        options = self.options
        entries = self._list()
        if not entries:
            raise DatasetError(f"{self.root}: no frames found ({self.signature})")
        if options.start >= len(entries):
            raise DatasetError(
                f"{self.root}: start {options.start} is beyond the last frame ({len(entries) - 1})"
            )
        positions = range(len(entries))[options.start : options.end : options.stride]
        self._indices = list(positions)
        self._entries = self._with_poses([entries[i] for i in positions])

    @abc.abstractmethod
    def _list(self) -> list[Entry]:
        """Every frame of the source in order (no pose needed; nothing decoded)."""

    def _with_poses(self, entries: list[Entry]) -> list[Entry]:
        """`entries` with their ground truth attached; only selected frames get here."""
        return entries

    def _calib_dir(self) -> Path | None:
        return self.root

    def __len__(self) -> int:
        return len(self._entries)

    def __iter__(self) -> Iterator[Frame]:
        self._camera_pair()  # missing intrinsics or no readable image: fail before any frame
        for index, entry in zip(self._indices, self._entries, strict=True):
            image, reason = read_image(entry.path)
            if image is None:
                self._skip(entry.path, reason)
                continue
            rgb = self._prepare(image, str(entry.path))
            # A copy: a caller editing its frame's pose must not change `ground_truth()`.
            T_wc = None if entry.T_wc is None else entry.T_wc.copy()
            yield Frame(index, entry.timestamp, rgb, T_wc)

    def _image_size(self) -> tuple[int, int]:
        for entry in self._entries:
            image, _ = read_image(entry.path)
            if image is not None:
                return image.shape[1], image.shape[0]
        raise DatasetError(
            f"{self.root}: none of the {len(self._entries)} selected images can be read "
            f"(first: {self._entries[0].path})"
        )

    def ground_truth(self) -> Trajectory | None:
        known = [e for e in self._entries if e.T_wc is not None]
        if not known:
            return None
        return Trajectory.from_lists((e.timestamp for e in known), (e.T_wc for e in known))


# -- helpers for layouts ------------------------------------------------------------------


def read_image(path: Path) -> tuple[np.ndarray | None, str]:
    """Decode an image file as 8-bit BGR (gray and palette images become 3 channels).

    Returns:
        `(image, "")`, or `(None, reason)` if it is missing, empty, truncated or not an image.
    """
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as e:
        return None, e.strerror or "cannot read"
    if data.size == 0:
        return None, "empty file"
    is_jpeg = data.size >= 2 and data[0] == 0xFF and data[1] == 0xD8
    if is_jpeg and b"\xff\xd9" not in data[-_JPEG_TAIL:].tobytes():
        return None, "truncated JPEG"
    image = cv2.imdecode(data, cv2.IMREAD_COLOR)
    if image is None:
        return None, "not a readable image"
    return image, ""

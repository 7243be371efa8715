"""A camera covered for a while: a copy of a sequence with some frames blanked."""

import shutil
from pathlib import Path

import cv2
import numpy as np


def covered_copy(sequence: Path, out: Path, first: int, stop: int) -> Path:
    """Copy the TUM-layout `sequence` to `out` with frames `first`..`stop - 1` (in `rgb.txt`
    order) black; returns `out`."""
    shutil.copytree(sequence, out)
    names = [
        line.split()[1]
        for line in (out / "rgb.txt").read_text().splitlines()
        if not line.startswith("#")
    ]
    for name in names[first:stop]:
        image = cv2.imread(str(out / name))
        cv2.imwrite(str(out / name), np.zeros_like(image))
    return out

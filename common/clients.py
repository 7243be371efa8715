"""`dimslam-camera` (frame publisher) and `dimslam-poses` (pose subscriber)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from dimslam.common.service import not_built_yet

CAMERA_DESCRIPTION = (
    "Publish frames from a dataset folder, a video file or a live camera index to the dimslam "
    "tracker, at the recorded rate or in lockstep with the tracker; intrinsics travel with the "
    "stream."
)
POSES_DESCRIPTION = (
    "Subscribe to the dimslam pose topic and print or write the camera trajectory (TUM format, "
    "or JSON lines)."
)


def _camera_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("source", help="dataset folder, video file or live camera index")
    p.add_argument(
        "--rate", type=float, default=None, help="frames per second (default: recorded rate)"
    )
    p.add_argument(
        "--lockstep",
        action="store_true",
        help="never run more than a few frames ahead of the tracker's published poses",
    )


def _poses_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", help="write the trajectory to this TUM file (default: print)")
    p.add_argument("--json", action="store_true", help="print JSON lines instead of TUM lines")


def camera_main(argv: Sequence[str] | None = None) -> int:
    return not_built_yet("dimslam-camera", CAMERA_DESCRIPTION, argv, _camera_options)


def poses_main(argv: Sequence[str] | None = None) -> int:
    return not_built_yet("dimslam-poses", POSES_DESCRIPTION, argv, _poses_options)


if __name__ == "__main__":
    sys.exit(camera_main())

"""`dimslam-tracker`: the tracking process."""

from __future__ import annotations

import sys
from collections.abc import Sequence

from dimslam.common.service import add_compute_options, not_built_yet

DESCRIPTION = (
    "Tracking process of the dimslam service: subscribes to camera frames, optimizes the poses of "
    "its window on high-gradient pixels against the newest map snapshot from the mapper, and "
    "publishes each pose as soon as it is solved."
)


def main(argv: Sequence[str] | None = None) -> int:
    return not_built_yet("dimslam-tracker", DESCRIPTION, argv, add_compute_options)


if __name__ == "__main__":
    sys.exit(main())

"""`dimslam-mapper`: the mapping process."""

from __future__ import annotations

import sys
from collections.abc import Sequence

from dimslam.common.service import add_compute_options, not_built_yet

DESCRIPTION = (
    "Mapping process of the dimslam service: owns the neural implicit map, runs initialization and "
    "a mapping round every 5 frames (grids, decoder and keyframe poses), publishes versioned map "
    "snapshots and refined keyframe poses, and answers queries for the map, mesh and trajectory."
)


def main(argv: Sequence[str] | None = None) -> int:
    return not_built_yet("dimslam-mapper", DESCRIPTION, argv, add_compute_options)


if __name__ == "__main__":
    sys.exit(main())

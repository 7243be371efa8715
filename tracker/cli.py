"""`dimslam-tracker`: the tracking process."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from dimslam.common.net.service import (
    add_process_options,
    map_lag_rounds,
    positive_seconds,
    service_main,
)
from dimslam.tracker.service import MAPPER_GRACE_S, TrackerService

DESCRIPTION = (
    "Tracking process of the dimslam service: subscribes to camera frames, optimizes the poses of "
    "its window on high-gradient pixels against the newest map snapshot from the mapper, and "
    "publishes each pose as soon as it is solved. It exits when the camera's stream ends."
)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="dimslam-tracker", description=DESCRIPTION)
    p.add_argument(
        "--out",
        type=Path,
        help="folder for trajectory_online.txt (every pose as first published), written at exit",
    )
    p.add_argument(
        "--map-lag",
        type=map_lag_rounds,
        metavar="ROUNDS",
        help="bounded staleness, for offline runs where the mapper is slower than the tracker: "
        "before a new frame, wait while more than ROUNDS mapping batches sent to a live mapper "
        "have no snapshot yet (1: track the next round's frames while the mapper maps one; "
        "0: wait for every round). Default: never wait, as a live camera needs.",
    )
    p.add_argument(
        "--mapper-grace",
        type=positive_seconds,
        default=MAPPER_GRACE_S,
        metavar="S",
        help="with --map-lag: a mapper that leaves with batches unmapped is waited for this "
        "long (it may come back with --resume) before tracking goes on without it",
    )
    add_process_options(p)
    return p


def build(args: argparse.Namespace, *rest) -> TrackerService:
    return TrackerService(*rest, map_lag=args.map_lag, mapper_grace=args.mapper_grace)


def flush(args: argparse.Namespace, service: TrackerService) -> None:
    if args.out is not None:
        service.write(args.out)


def main(argv: Sequence[str] | None = None) -> int:
    return service_main(build_parser(), "tracker", build, flush, argv)


if __name__ == "__main__":
    sys.exit(main())

"""`dimslam-mapper`: the mapping process."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from functools import partial
from pathlib import Path

from dimslam.common import logs
from dimslam.common.cli import run_main
from dimslam.common.service import (
    add_compute_options,
    add_slam_options,
    add_transport_options,
    run_service,
)
from dimslam.mapper.service import MapperService

DESCRIPTION = (
    "Mapping process of the dimslam service: initializes the map from the tracker's first frames, "
    "runs a mapping round (grids, decoder, keyframe poses) on every batch the tracker sends, "
    "publishes a versioned map snapshot and the refined keyframe poses after each round, and "
    "answers queries for the current map, mesh (PLY) and trajectory (TUM)."
)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="dimslam-mapper", description=DESCRIPTION)
    p.add_argument(
        "--out",
        type=Path,
        help="folder for trajectory.txt (final poses), keyframes.txt and map.msgpack (the last "
        "snapshot), written at the end of each stream and at exit",
    )
    p.add_argument("--mesh", action="store_true", help="also write mesh.ply with the outputs")
    p.add_argument(
        "--exit-at-end",
        action="store_true",
        help="exit after the end of the stream (default: keep the map and answer queries)",
    )
    add_compute_options(p)
    add_transport_options(p)
    add_slam_options(p)
    return p


def serve(args: argparse.Namespace) -> int:
    def flush(service: MapperService) -> None:
        if args.out is not None:
            service.write(args.out, args.mesh)

    build = partial(MapperService, exit_at_end=args.exit_at_end)
    return run_service(args, "mapper", build, flush)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logs.configure(args.verbose, args.quiet)
    return run_main(serve, args)


if __name__ == "__main__":
    sys.exit(main())

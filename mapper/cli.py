"""`dimslam-mapper`: the mapping process."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from dimslam.common.net.service import add_process_options, positive_int, service_main
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
    p.add_argument(
        "--checkpoint",
        type=Path,
        metavar="DIR",
        help="write DIR/checkpoint.msgpack (map, every frame's pose, the keyframes' images) "
        "every --checkpoint-every rounds and at exit, atomically",
    )
    p.add_argument(
        "--checkpoint-every",
        type=positive_int,
        default=10,
        metavar="N",
        help="rounds between checkpoints (default: 10)",
    )
    p.add_argument(
        "--resume",
        type=Path,
        metavar="DIR",
        help="start from DIR/checkpoint.msgpack (same --preset and overrides as when it was "
        "written); a tracker still running goes on with it",
    )
    add_process_options(p)
    return p


def build(args: argparse.Namespace, *rest) -> MapperService:
    return MapperService(
        *rest,
        exit_at_end=args.exit_at_end,
        checkpoint=args.checkpoint,
        checkpoint_every=args.checkpoint_every,
        resume=args.resume,
    )


def flush(args: argparse.Namespace, service: MapperService) -> None:
    if args.out is not None:
        service.write(args.out, args.mesh)
    if args.checkpoint is not None:
        service.write_checkpoint(args.checkpoint)


def main(argv: Sequence[str] | None = None) -> int:
    return service_main(build_parser(), "mapper", build, flush, argv)


if __name__ == "__main__":
    sys.exit(main())

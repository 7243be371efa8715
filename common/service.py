"""Command-line options shared by the service processes (tracker, mapper, camera, poses).

The processes exchange frames, poses and map snapshots over Zenoh; every one of them takes
the same session and transport options so a deployment is described the same way everywhere.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from dimslam.common import logs

DEFAULT_SESSION = "default"


def add_transport_options(p: argparse.ArgumentParser) -> None:
    """Session namespace and Zenoh endpoints (design.md section 1, zenoh.md)."""
    g = p.add_argument_group("transport")
    g.add_argument(
        "--session",
        default=DEFAULT_SESSION,
        help="namespace of every key (dimslam/<session>/...) so several runs can share a network "
        f"(default: {DEFAULT_SESSION})",
    )
    g.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="zenoh endpoint to connect to, e.g. tcp/10.0.0.2:7450 (repeatable)",
    )
    g.add_argument(
        "--listen",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="zenoh endpoint to listen on (repeatable; default: loopback only)",
    )
    g.add_argument(
        "--zenoh-config",
        type=Path,
        metavar="FILE",
        help="zenoh JSON5 configuration file; --connect/--listen are applied on top",
    )
    p.add_argument("-v", "--verbose", action="count", default=0, help="more log output")
    p.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only")


def add_compute_options(p: argparse.ArgumentParser) -> None:
    """Where a process computes: one GPU, or the CPU with its own thread budget."""
    g = p.add_argument_group("compute")
    g.add_argument(
        "--gpu",
        type=int,
        default=None,
        metavar="N",
        help="run on cuda:N; without CUDA the process says so once and uses the CPU",
    )
    g.add_argument(
        "--threads",
        type=int,
        default=None,
        help="CPU threads for this process (default: torch's choice), so two processes "
        "on one machine do not fight over cores",
    )


def not_built_yet(
    prog: str,
    description: str,
    argv: Sequence[str] | None,
    add_options: Callable[[argparse.ArgumentParser], None],
) -> int:
    """Entry point of a service process whose loop is not part of this release.

    Parses the process's documented options (`add_options` adds its own, then the transport
    options) so `--help` is already the real one, and then says plainly that the process cannot
    run yet, with what to use instead.
    """
    parser = argparse.ArgumentParser(prog=prog, description=description)
    add_options(parser)
    add_transport_options(parser)
    args = parser.parse_args(argv)
    logs.configure(args.verbose, args.quiet)
    print(
        f"{prog}: the two-process service is not part of this release yet (tracked as issue #4). "
        "Available now: `dimslam synth`, `dimslam dataset`, `dimslam eval`, `dimslam demo`.",
        file=sys.stderr,
    )
    return 2

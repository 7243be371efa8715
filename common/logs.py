"""Logging set-up shared by every entry point: one format, verbosity from -v / -q."""

from __future__ import annotations

import logging
import sys


def configure(verbose: int = 0, quiet: bool = False) -> None:
    """Send log records to stderr; WARNING when quiet, INFO by default, DEBUG with -v."""
    level = logging.WARNING if quiet else logging.DEBUG if verbose > 0 else logging.INFO
    logging.basicConfig(
        level=level,
        stream=sys.stderr,
        format="%(asctime)s %(levelname).1s %(name)s: %(message)s",
        datefmt="%H:%M:%S",
        force=True,
    )

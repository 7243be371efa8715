"""What every command-line entry point does the same way.

Verbosity flags (`-v`, `-q`) and one log format; errors a user can fix (`DimslamError`)
print one line and exit 2, an interrupt exits 130, anything else keeps its traceback.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence

from dimslam.common import logs
from dimslam.common.errors import DimslamError


def add_verbosity(p: argparse.ArgumentParser) -> None:
    """`-v/--verbose` and `-q/--quiet`."""
    p.add_argument("-v", "--verbose", action="count", default=0, help="more log output")
    p.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only")


def run_main(func: Callable[[argparse.Namespace], int], args: argparse.Namespace) -> int:
    """Run an entry point, turning user errors into one line on stderr and exit code 2."""
    try:
        return func(args)
    except DimslamError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


def main(
    parser: argparse.ArgumentParser,
    func: Callable[[argparse.Namespace], int],
    argv: Sequence[str] | None = None,
) -> int:
    """Parse `argv`, set up logging from the verbosity flags, run `func` as `run_main` does."""
    args = parser.parse_args(argv)
    logs.configure(args.verbose, args.quiet)
    return run_main(func, args)

"""Where the tests find the repository and the shared development data, and how they run a
benchmark's command line."""

import importlib
import os
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import pytest

REPO = Path(__file__).resolve().parent.parent
"""The repository root."""

DATA = Path(os.environ.get("DIMSLAM_DATA") or REPO / ".." / "shared" / "data")
"""The shared development sequences: `DIMSLAM_DATA`, else `../shared/data` beside the repo."""


def benchmark(monkeypatch, name: str) -> ModuleType:
    """`benchmarks/<name>.py` as a module (with `benchmarks/` on the path for its own imports)."""
    monkeypatch.syspath_prepend(str(REPO / "benchmarks"))
    return importlib.import_module(name)


def usage_error(monkeypatch, capsys, main: Callable[[], None], argv: list[str]) -> str:
    """Run `main` with `sys.argv` set to `argv`, check that it ends with a usage error (exit
    status 2), and return what it wrote to stderr."""
    monkeypatch.setattr("sys.argv", argv)
    with pytest.raises(SystemExit) as e:
        main()
    assert e.value.code == 2
    return capsys.readouterr().err

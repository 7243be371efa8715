"""Where the tests find the repository and the shared development data."""

import importlib
import os
from pathlib import Path
from types import ModuleType

REPO = Path(__file__).resolve().parent.parent
"""The repository root."""

DATA = Path(os.environ.get("DIMSLAM_DATA") or REPO / ".." / "shared" / "data")
"""The shared development sequences: `DIMSLAM_DATA`, else `../shared/data` beside the repo."""


def benchmark(monkeypatch, name: str) -> ModuleType:
    """`benchmarks/<name>.py` as a module (with `benchmarks/` on the path for its own imports)."""
    monkeypatch.syspath_prepend(str(REPO / "benchmarks"))
    return importlib.import_module(name)

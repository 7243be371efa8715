"""Where the tests find the repository and the shared development data."""

import os
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
"""The repository root."""

DATA = Path(os.environ.get("DIMSLAM_DATA") or REPO / ".." / "shared" / "data")
"""The shared development sequences: `DIMSLAM_DATA`, else `../shared/data` beside the repo."""

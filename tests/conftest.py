"""Test-wide set-up: import dimslam first so its OpenMP setting precedes torch (common/__init__)."""

import dimslam.common  # noqa: F401

"""Test-wide set-up and the three tiers of tests.

- unit (unmarked): in this process, no zenoh session, no subprocess; milliseconds to a second.
- `integration`: zenoh sessions or real processes on loopback.
- `e2e`: a SLAM run, tracking and mapping, on a short sequence.

`make test` runs all of them, `make test-fast` the unit tier. Unit tests slower than
`UNIT_LIMIT_S` are listed at the end of the run (listed, not failed: timings on a shared
machine are noise, and CI never gates on them).

dimslam is imported first so its OpenMP setting precedes torch's (common/__init__).
"""

import dimslam.common  # noqa: F401

UNIT_LIMIT_S = 1.0
TIERS = ("integration", "e2e")

_slow_units: list[tuple[str, float]] = []


def pytest_configure(config):
    config.addinivalue_line("markers", "integration: zenoh sessions or processes on loopback")
    config.addinivalue_line("markers", "e2e: a SLAM run, tracking and mapping")


def pytest_runtest_logreport(report):
    if report.when == "call" and report.duration > UNIT_LIMIT_S:
        if not any(tier in report.keywords for tier in TIERS):
            _slow_units.append((report.nodeid, report.duration))


def pytest_terminal_summary(terminalreporter):
    if _slow_units:
        terminalreporter.section(f"unit tests over {UNIT_LIMIT_S:g} s")
        for nodeid, seconds in sorted(_slow_units, key=lambda x: -x[1]):
            terminalreporter.write_line(f"{seconds:6.2f} s  {nodeid}")

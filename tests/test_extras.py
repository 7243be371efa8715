"""The optional extras stay optional: the service's modules never import them."""

import subprocess
import sys

CORE = [
    "dimslam.common.cli",
    "dimslam.tracker.cli",
    "dimslam.mapper.cli",
    "dimslam.common.net.camera",
    "dimslam.common.net.poses",
    "dimslam.common.net.router",
    "dimslam.common.net.viewer",
]


def test_the_core_imports_neither_rerun_nor_rosbags():
    code = (
        f"import sys\nfor m in {CORE!r}: __import__(m)\n"
        "print(sorted(m for m in ('rerun', 'rosbags', 'evo') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"

"""What the tracker and the mapper share: geometry, I/O, datasets, evaluation."""

import os

# OpenMP threads that spin while waiting starve each other as soon as anything else runs on
# the machine (the other dimslam process, a test runner): one render + backward step measured
# 30x slower (0.75 s instead of 25 ms) on 2 busy cores. Passive waiting costs nothing
# measurable when the cores are free. It must be set before torch loads its OpenMP runtime,
# which importing any dimslam.common module does first; the user's own setting wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

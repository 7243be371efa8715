"""What the tracker and the mapper share: geometry, I/O, datasets, evaluation."""

import ctypes
import os
import sys

# OpenMP threads that spin while waiting starve each other as soon as anything else runs on
# the machine (the other dimslam process, a test runner): one render + backward step measured
# 30x slower (0.75 s instead of 25 ms) on 2 busy cores. Passive waiting costs nothing
# measurable when the cores are free. It must be set before torch loads its OpenMP runtime,
# which importing any dimslam.common module does first; the user's own setting wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def _keep_freed_memory() -> None:
    """Let glibc reuse freed large blocks instead of returning them to the system.

    Every backward pass through the dense grids allocates their full-size gradients (~60 MB
    at the paper's voxel sizes) and every step frees them. glibc serves blocks that large
    with a fresh mmap, so each iteration page-faults the whole gradient in again: 62 ms
    against 19 ms to allocate, fill and add 55 MB on a 2-core CPU. Served from the heap and
    never trimmed, the pages stay mapped and are reused. Elsewhere than glibc, nothing changes.
    """
    if not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return
    m_trim_threshold, m_mmap_threshold = -1, -3  # <malloc.h>
    libc.mallopt(m_mmap_threshold, 1 << 30)
    libc.mallopt(m_trim_threshold, 2**31 - 1)


_keep_freed_memory()

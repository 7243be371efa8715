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


def _tune_malloc() -> None:
    """Let glibc reuse freed large blocks instead of returning them to the system, in at
    most `ARENAS` heaps.

    Every backward pass through the dense grids allocates their full-size gradients (~60 MB
    at the paper's voxel sizes) and every step frees them. glibc serves blocks that large
    with a fresh mmap, so each iteration page-faults the whole gradient in again: 62 ms
    against 19 ms to allocate, fill and add 55 MB on a 2-core CPU. Served from the heap and
    never trimmed, the pages stay mapped and are reused; the services give them back every
    few seconds instead (`net.service.trim_heap`).

    By default glibc gives each thread that allocates a heap of its own, up to 8 per core.
    zenoh's receiving threads take turns decoding messages of several MB, so under a flood
    each left a heap full of holes that trimming could not give back: a tracker fed 100 000
    hostile messages per key kept 97 MiB more after the flood with the default, 5 MiB with
    two heaps (docs/reliability.md). Elsewhere than glibc, nothing changes.
    """
    if not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return
    m_trim_threshold, m_mmap_threshold, m_arena_max = -1, -3, -8  # <malloc.h>
    libc.mallopt(m_mmap_threshold, 1 << 30)
    libc.mallopt(m_trim_threshold, 2**31 - 1)
    if "MALLOC_ARENA_MAX" not in os.environ:  # the user's own setting wins
        libc.mallopt(m_arena_max, ARENAS)


ARENAS = 2
"""glibc heaps (arenas) a dimslam process allocates from, threads included."""

_tune_malloc()

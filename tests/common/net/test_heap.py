"""The service processes give the memory freed on zenoh's threads back (`trim_heap`)."""

import os
import subprocess
import sys

import pytest

# Four threads each allocate 600 blocks of 1-4 MB (messages arriving on zenoh's threads),
# keeping a few blocks and some small objects alive a while. With the heap settings every
# dimslam process has (`dimslam.common`: freed blocks stay in the heap, for the mapper's
# speed, in at most two heaps) the private memory ends 90-105 MiB above where it started and
# `trim_heap` brings it down to ~22 MiB; with a heap per thread (glibc's default) it ends
# ~115 MiB above and keeps ~80 after the trim.
CHURN = """
import random, re, threading
from pathlib import Path
from dimslam.common.net.service import trim_heap

def private_mb():
    status = Path("/proc/self/status").read_text()
    return int(re.search(r"RssAnon:\\s+(\\d+)", status).group(1)) / 1024

kept = []

def churn(seed):
    rng = random.Random(seed)
    held = []
    for i in range(600):
        held.append(bytearray(rng.randint(1 << 20, 4 << 20)))
        small = [bytes(rng.randint(100, 5000)) for _ in range(20)]
        if len(held) > rng.randint(1, 4):
            held.pop(rng.randrange(len(held)))
        if i % 7 == 0:
            kept.append(small[0])

start = private_mb()
threads = [threading.Thread(target=churn, args=(s,)) for s in range(4)]
for t in threads:
    t.start()
for t in threads:
    t.join()
before = private_mb() - start
trim_heap()
print(before, private_mb() - start)
"""


def _churn(arenas: str | None) -> tuple[float, float]:
    """MiB above the start after the churn, and after `trim_heap`; `arenas`: the user's
    MALLOC_ARENA_MAX (None: dimslam's own setting)."""
    env = {k: v for k, v in os.environ.items() if k != "MALLOC_ARENA_MAX"}
    if arenas is not None:
        env["MALLOC_ARENA_MAX"] = arenas
    run = subprocess.run(
        [sys.executable, "-c", CHURN], capture_output=True, text=True, timeout=300, env=env
    )
    assert run.returncode == 0, run.stderr
    before, after = map(float, run.stdout.split())
    return before, after


linux_only = pytest.mark.skipif(
    not sys.platform.startswith("linux"), reason="glibc's malloc, /proc"
)


@linux_only
def test_trimming_gives_back_what_the_threads_freed():
    before, after = _churn(None)
    assert after < 45, f"{before:.0f} MiB above the start, {after:.0f} after trim"
    assert after < 0.5 * before


@linux_only
def test_the_users_arena_setting_wins():
    # A heap per thread, as glibc does by default: much of the freed memory stays.
    before, after = _churn("16")
    assert after > 45, f"{before:.0f} MiB above the start, {after:.0f} after trim"

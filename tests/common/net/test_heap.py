"""The service processes give the memory freed on zenoh's threads back (`trim_heap`)."""

import subprocess
import sys

import pytest

# Four threads each allocate 600 blocks of 1-4 MB (messages arriving on zenoh's threads),
# keeping a few blocks and some small objects alive a while. With the heap settings every
# dimslam process has (`dimslam.common`: freed blocks stay in the heap, for the mapper's
# speed) the private memory ends ~115 MiB above where it started; `trim_heap` gives back
# 35-50 MiB of that here.
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


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc, /proc")
def test_trimming_gives_back_what_the_threads_freed():
    run = subprocess.run([sys.executable, "-c", CHURN], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    before, after = map(float, run.stdout.split())
    assert after < 0.8 * before, f"{before:.0f} MiB above the start, {after:.0f} after trim"

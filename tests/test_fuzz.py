"""Fuzzing the running service: the short version of benchmarks/fuzz.py.

The benchmark runs router, mapper, tracker and camera on a 45-frame scene and sends 400
hostile messages on each key a process subscribes to (frames, map, mapping, poses: random
bytes, truncations, bit flips, other versions, absurd shapes, NaN and non-rigid poses, wrong
types, duplicate and out-of-order numbers). Every process must exit 0, refuse every hostile
message it can tell from a real one, log its rejections in a bounded number of lines per key,
and the run must end with a pose for every frame.
"""

import json
import subprocess
import sys

import pytest
from repo import REPO

from dimslam.common.net.transport import REJECT_KINDS, REJECT_LOG_S

pytestmark = pytest.mark.e2e

FRAMES = 45
MESSAGES = 400
SUBSCRIBER = {"frames": "tracker", "map": "tracker", "mapping": "mapper", "poses": "camera"}


@pytest.fixture(scope="module")
def fuzzed(tmp_path_factory):
    out = tmp_path_factory.mktemp("fuzz")
    argv = [sys.executable, str(REPO / "benchmarks" / "fuzz.py"), "--messages", str(MESSAGES)]
    argv += [
        "--frames",
        str(FRAMES),
        "--no-clean",
        "--out",
        str(out),
        "--json",
        str(out / "f.json"),
    ]
    run = subprocess.run(argv, cwd=REPO, capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    (result,) = json.loads((out / "f.json").read_text())
    return result


def test_no_process_crashes_and_every_frame_gets_its_pose(fuzzed):
    for role, p in fuzzed["processes"].items():
        assert p["exit"] == 0 and not p["crashed"], (role, p)
    assert fuzzed["posed"] == FRAMES and fuzzed["online_frames"] == FRAMES
    assert fuzzed["final_frames"] == FRAMES  # the map was not dropped by a replayed batch 0


def test_every_hostile_message_is_refused(fuzzed):
    sent = {k: sum(v.values()) for k, v in fuzzed["sent"].items()}
    assert sent == dict.fromkeys(SUBSCRIBER, MESSAGES)
    assert fuzzed["decoded"] == {}  # NaN, non-rigid, absurd shapes: all refused by the decoders
    procs = fuzzed["processes"]
    assert procs["tracker"]["rejected"] == sent["frames"] + sent["map"]
    assert procs["mapper"]["rejected"] == sent["mapping"]
    # Old poses are harmless to the camera (it keeps the highest); the rest are refused.
    assert procs["camera"]["rejected"] >= sent["poses"] - fuzzed["sent"]["poses"]["sequence"]


def test_rejections_are_logged_in_a_bounded_number_of_lines_per_key(fuzzed):
    bound = REJECT_KINDS + fuzzed["seconds"] / REJECT_LOG_S + 1
    for key, role in SUBSCRIBER.items():
        lines = {
            k.rsplit("/", 1)[-1]: n for k, n in fuzzed["processes"][role]["reject_lines"].items()
        }
        assert 0 < lines[key] <= bound, (key, lines)

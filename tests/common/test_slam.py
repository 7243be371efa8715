"""`dimslam run` end to end on a tiny synthetic sequence: outputs, options, errors.

Accuracy is not asserted here yet: the tiny preset does not track reliably (docs/status.md);
the ATE-bounded end-to-end test comes with the tuned tracker (issue #3).
"""

import json

import pytest

from dimslam.common.cli import main
from dimslam.common.options import apply_overrides
from dimslam.common.slam import PRESETS
from dimslam.common.trajectory import read_tum


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    out = tmp_path_factory.mktemp("slam") / "seq"
    assert main(["synth", str(out), "--frames", "14", "--size", "96x72", "--seed", "2"]) == 0
    return out


def test_run_writes_every_output(sequence, tmp_path):
    out = tmp_path / "run"
    args = ["run", str(sequence), "--out", str(out), "--preset", "tiny"]
    args += ["--mapper.init_iters", "10", "--mapper.prior_iters", "5", "--tracker.iters", "2"]
    assert main(args) == 0
    traj = read_tum(out / "trajectory.txt")
    assert len(traj) == 14  # one pose per input frame
    gt = read_tum(sequence / "groundtruth.txt")
    assert list(traj.timestamps) == pytest.approx(list(gt.timestamps))  # the frames' own stamps
    assert len(read_tum(out / "keyframes.txt")) >= 1
    config = json.loads((out / "config.json").read_text())
    assert config["tracker"]["iters"] == 2 and config["mapper"]["init_frames"] == 8
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["matched"] == 14 and metrics["ate_rmse_m"] >= 0
    assert "initialized on 8 frames" in (out / "log.txt").read_text()


def test_overrides_are_typed_and_checked():
    cfg = apply_overrides(PRESETS["tiny"], {"tracker.iters": "3", "loss.patch_sizes": "1,5"})
    assert cfg.tracker.iters == 3 and cfg.loss.patch_sizes == (1, 5)
    with pytest.raises(ValueError, match="unknown setting"):
        apply_overrides(PRESETS["tiny"], {"tracker.nope": "1"})
    with pytest.raises(ValueError, match="--tracker.iters"):
        apply_overrides(PRESETS["tiny"], {"tracker.iters": "many"})


def test_bad_override_is_a_one_line_error(sequence, tmp_path, capsys):
    args = ["run", str(sequence), "--out", str(tmp_path / "x"), "--tracker.iters", "many"]
    assert main(args) == 2
    assert "--tracker.iters" in capsys.readouterr().err


def test_too_short_a_sequence_is_refused(sequence, tmp_path, capsys):
    args = ["run", str(sequence), "--out", str(tmp_path / "x"), "--preset", "tiny"]
    assert main([*args, "--max-frames", "2"]) == 2
    assert "too short" in capsys.readouterr().err

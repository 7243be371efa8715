"""`dimslam run` end to end on a tiny synthetic sequence: outputs, options, errors.

The accuracy-bounded test runs the tiny preset on 40 synthetic frames; the others check the
outputs, the settings and the errors a user meets.
"""

import json

import cv2
import pytest
from covered import covered_copy

from dimslam.common.cli import main
from dimslam.common.config import PRESETS
from dimslam.common.eval.mesh_views import BACKGROUND
from dimslam.common.io.trajectory import read_tum
from dimslam.common.options import apply_overrides


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    out = tmp_path_factory.mktemp("slam") / "seq"
    assert main(["synth", str(out), "--frames", "14", "--size", "96x72", "--seed", "2"]) == 0
    return out


@pytest.mark.e2e
def test_run_writes_every_output(sequence, tmp_path):
    out = tmp_path / "run"
    args = one_process(sequence, out)
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


def test_settings_that_only_go_together_apply_in_any_order():
    together = {"map.reclaim_every": "4", "map.fine_band": "0.3", "map.grids": "sparse"}
    for order in (together, dict(reversed(together.items()))):
        cfg = apply_overrides(PRESETS["tiny"], order)
        assert (cfg.map.reclaim_every, cfg.map.fine_band, cfg.map.grids) == (4, 0.3, "sparse")
    with pytest.raises(ValueError, match="reclaim_every needs"):
        apply_overrides(PRESETS["tiny"], {"map.reclaim_every": "4", "map.grids": "sparse"})


def one_process(sequence, out) -> list[str]:
    """`dimslam run` in one process with the tiny preset (what each test adds comes after)."""
    return ["run", "--single-process", str(sequence), "--out", str(out), "--preset", "tiny"]


def test_bad_override_is_a_one_line_error(sequence, tmp_path, capsys):
    assert main([*one_process(sequence, tmp_path / "x"), "--tracker.iters", "many"]) == 2
    assert "--tracker.iters" in capsys.readouterr().err


def test_map_lag_is_refused_in_one_process(sequence, tmp_path, capsys):
    assert main([*one_process(sequence, tmp_path / "x"), "--map-lag", "0"]) == 2
    assert "--map-lag" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()  # refused before anything ran


def test_a_live_view_is_refused_in_one_process(sequence, tmp_path, capsys):
    rrd = tmp_path / "x.rrd"
    assert main([*one_process(sequence, tmp_path / "x"), "--rerun-save", str(rrd)]) == 2
    assert "drop --single-process" in capsys.readouterr().err
    assert not (tmp_path / "x").exists() and not rrd.exists()


def test_too_short_a_sequence_is_refused(sequence, tmp_path, capsys):
    assert main([*one_process(sequence, tmp_path / "x"), "--max-frames", "2"]) == 2
    assert "too short" in capsys.readouterr().err


@pytest.fixture(scope="module")
def forty(tmp_path_factory):
    """40 frames of the built-in scene (seed 0), about 60 cm of handheld motion."""
    seq = tmp_path_factory.mktemp("forty") / "seq"
    assert main(["synth", str(seq), "--frames", "40", "--size", "160x120", "--seed", "0"]) == 0
    return seq


@pytest.mark.e2e
def test_tiny_preset_tracks_a_synthetic_sequence(forty, tmp_path):
    """End to end with an accuracy bound: the tiny preset on a freshly rendered sequence.

    A tracker that has lost its way scores tens of centimetres or loses frames; the bound
    leaves room for run-to-run noise of a working one (1.5 cm measured on 60 frames).
    """
    out = tmp_path / "run"
    assert main(one_process(forty, out)) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["matched"] == 40 and metrics["frames_lost"] == 0
    assert metrics["ate_rmse_m"] < 0.04
    # The map, and the pictures of it a person looks at: each of the 4 views shows some.
    assert "accuracy_cm" in metrics  # the mesh, evaluated against the scene's
    views = cv2.imread(str(out / "mesh_views.png"))
    h, w = views.shape[0] // 2, views.shape[1] // 2
    for tile in (views[:h, :w], views[:h, w:], views[h:, :w], views[h:, w:]):
        assert (tile != BACKGROUND).any(axis=-1).mean() > 0.05


@pytest.mark.e2e
def test_the_bundle_adjustment_during_the_run(forty, tmp_path):
    """`--bundle.every 3`: the keyframes are adjusted each time three more have features,
    the run goes on from the corrected poses and map, and again at the end."""
    out = tmp_path / "run"
    args = ["--bundle.enabled", "true", "--bundle.every", "3", "--no-mesh"]
    assert main([*one_process(forty, out), *args]) == 0
    adjusted = (out / "log.txt").read_text().count("feature bundle adjustment of")
    keyframes = len(read_tum(out / "keyframes.txt"))
    assert adjusted >= 2 and adjusted >= keyframes // 3
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["matched"] == 40 and metrics["frames_lost"] == 0
    assert metrics["ate_rmse_m"] < 0.04


@pytest.mark.e2e
def test_tiny_preset_tracks_three_times_the_motion_per_frame(tmp_path):
    """Fast motion: every third frame of 60 (4.8 cm and 1.9 degrees per frame): every
    frame posed, none lost, within about 2x the accuracy of all 60 frames (2.6 cm measured
    at stride 3, 2.8 cm at stride 1)."""
    seq = tmp_path / "seq"
    assert main(["synth", str(seq), "--frames", "60", "--size", "160x120", "--seed", "0"]) == 0
    out = tmp_path / "run"
    assert main([*one_process(seq, out), "--stride", "3", "--no-mesh"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["matched"] == 20 and metrics["frames_lost"] == 0
    assert json.loads((out / "config.json").read_text())["stride"] == 3
    stamps = read_tum(seq / "groundtruth.txt").timestamps
    assert list(read_tum(out / "trajectory.txt").timestamps) == pytest.approx(stamps[::3])
    assert metrics["ate_rmse_m"] < 0.05


@pytest.mark.e2e
def test_tracking_resumes_after_ten_blank_frames(forty, tmp_path):
    """A camera covered for a third of a second mid-sequence: the blank frames are lost (no
    pose is invented for them), the first frame after the gap relocalizes, the run completes
    with the accuracy of an unbroken one (1.8 cm measured)."""
    seq = covered_copy(forty, tmp_path / "seq", 20, 30)
    stamps = read_tum(forty / "groundtruth.txt").timestamps
    out = tmp_path / "run"
    assert main([*one_process(seq, out), "--no-mesh"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames_lost"] == 10 and metrics["matched"] == 30
    tracked = list(read_tum(out / "trajectory.txt").timestamps)
    assert tracked == pytest.approx([*stamps[:20], *stamps[30:]])
    assert "relocalized at frame 30 after 10 lost frames" in (out / "log.txt").read_text()
    assert metrics["ate_rmse_m"] < 0.04

"""The `dimslam` umbrella command and the declared service entry points, as a user runs them."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dimslam.common.cli import main
from dimslam.common.io.trajectory import Trajectory, read_tum, write_tum

SCRIPTS = ["dimslam", "dimslam-tracker", "dimslam-mapper", "dimslam-camera", "dimslam-poses"]


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("cli") / "scene"
    assert main(["synth", str(out), "--frames", "12", "--size", "64x48", "--seed", "3"]) == 0
    return out


@pytest.mark.integration
@pytest.mark.parametrize("script", SCRIPTS)
def test_every_console_script_has_help(script):
    exe = Path(sys.executable).parent / script
    done = subprocess.run([str(exe), "--help"], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith(f"usage: {script}")


def test_synth_then_dataset_describes_it(scene, capsys):
    assert main(["dataset", str(scene), "--write-gt", str(scene.parent / "gt.txt"), "--check"]) == 0
    out = capsys.readouterr().out
    assert "layout      tum" in out and "frames      12" in out and "image       64x48" in out
    assert "decoded 12 frames, skipped 0" in out
    assert len(read_tum(scene.parent / "gt.txt")) == 12


def test_eval_of_ground_truth_against_itself(scene, tmp_path, capsys):
    gt = read_tum(scene / "groundtruth.txt")
    est = tmp_path / "est.txt"
    write_tum(est, gt)
    figures = tmp_path / "m.json"
    args = ["eval", "--traj", str(est), "--gt", str(scene), "--mesh", str(scene / "mesh.ply")]
    args += ["--json", str(figures), "--plot", str(tmp_path / "p.png"), "--samples", "20000"]
    assert main(args) == 0
    result = json.loads(figures.read_text())
    assert result["matched"] == 12
    assert result["ate_rmse_m"] < 1e-6
    assert result["accuracy_cm"] < 1e-6 and result["completion_cm"] < 1e-6
    assert result["completion_ratio"] == 100.0
    assert result["segment_scale_spread"] is None  # 12 poses: too few for two segments
    assert (tmp_path / "p.png").stat().st_size > 10_000
    out = capsys.readouterr().out
    assert "ATE RMSE" in out and "segment scale spread" not in out


def test_eval_sees_a_drifted_estimate(scene, tmp_path):
    gt = read_tum(scene / "groundtruth.txt")
    poses = gt.poses.copy()
    poses[:, 0, 3] += np.linspace(0, 0.1, len(poses)) ** 2 * 10  # quadratic drift, up to 10 cm
    est = tmp_path / "est.txt"
    write_tum(est, Trajectory(gt.timestamps, poses))
    figures = tmp_path / "m.json"
    args = ["eval", "--traj", str(est), "--gt", str(scene / "groundtruth.txt")]
    assert main([*args, "--align", "se3", "--json", str(figures)]) == 0
    result = json.loads(figures.read_text())
    assert 0.01 < result["ate_rmse_m"] < 0.1 and result["scale"] == 1.0


def test_user_errors_are_one_line_and_exit_2(tmp_path, capsys):
    assert main(["eval", "--traj", str(tmp_path / "none.txt"), "--gt", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "none.txt" in err and "Traceback" not in err
    (tmp_path / "imgs").mkdir()
    import cv2

    cv2.imwrite(str(tmp_path / "imgs" / "a.png"), np.zeros((8, 8, 3), np.uint8))
    assert main(["dataset", str(tmp_path / "imgs")]) == 2
    assert "calib.txt" in capsys.readouterr().err


def test_bad_size_is_rejected_by_the_parser(tmp_path):
    with pytest.raises(SystemExit) as e:
        main(["synth", str(tmp_path / "x"), "--size", "64by48"])
    assert e.value.code == 2

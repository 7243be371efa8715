"""EuRoC specifics: sensor.yaml parsing, body-to-camera ground truth, distortion."""

from __future__ import annotations

import numpy as np
import pytest
from dataset_fixtures import EUROC_SENSOR_YAML, EUROC_T_BS, make_euroc

from dimslam.common.errors import DatasetError
from dimslam.common.io.datasets import detect_layout, open_dataset
from dimslam.common.io.datasets.euroc import yaml_numbers

MH01 = EUROC_SENSOR_YAML.format(
    width=752,
    height=480,
    fu=458.654,
    fv=457.296,
    cu=367.215,
    cv=248.375,
    k1=-0.28340811,
    k2=0.07395907,
    p1=0.00019359,
    p2=1.76187114e-05,
)


def test_yaml_numbers_reads_the_real_sensor_yaml(tmp_path):
    path = tmp_path / "sensor.yaml"
    assert yaml_numbers(path, MH01, "intrinsics", 4) == [458.654, 457.296, 367.215, 248.375]
    dist = yaml_numbers(path, MH01, "distortion_coefficients", 4)
    assert dist == [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
    assert yaml_numbers(path, MH01, "resolution", 2) == [752, 480]
    T_BS = np.array(yaml_numbers(path, MH01, "data", 16, after="T_BS")).reshape(4, 4)
    assert np.array_equal(T_BS, EUROC_T_BS)


@pytest.mark.parametrize(
    "key,after,message",
    [
        ("intrinsics", None, r"no 'intrinsics: \[...\]' entry"),
        ("data", "T_BS", r"no 'T_BS:' entry"),
    ],
)
def test_missing_yaml_key_names_file_and_key(tmp_path, key, after, message):
    path = tmp_path / "sensor.yaml"
    text = MH01.replace(f"{after or key}:", f"renamed_{after or key}:")
    with pytest.raises(DatasetError, match=rf"sensor\.yaml: {message}"):
        yaml_numbers(path, text, key, 16 if after else 4, after=after)


def test_yaml_list_of_the_wrong_length(tmp_path):
    with pytest.raises(DatasetError, match="'resolution' must hold 2 finite numbers"):
        yaml_numbers(tmp_path / "sensor.yaml", "resolution: [752]\n", "resolution", 2)


def test_raw_camera_is_distorted_and_yielded_camera_is_not(tmp_path):
    seq = make_euroc(tmp_path / "MH_01_easy", dist=(-0.28, 0.07, 0.0002, 0.00002))
    reader = open_dataset(seq.root)
    assert reader.raw_camera.dist == (-0.28, 0.07, 0.0002, 0.00002)
    assert reader.camera.dist == ()
    assert reader.camera.fx == reader.raw_camera.fx


def test_body_pose_composed_with_T_BS_and_wxyz_order(tmp_path):
    # A hand-written sample: body at (1, 2, 3), no rotation, written as q = (w=1, x=0, y=0, z=0).
    # Read as x y z w, the same numbers would be a half turn about x.
    seq = make_euroc(tmp_path / "seq", n=2)
    ns = int(round(seq.timestamps[0] * 1e9))
    gt = seq.root / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    gt.write_text("#timestamp,x,y,z,qw,qx,qy,qz\n" + f"{ns},1,2,3,1,0,0,0" + ",0" * 9 + "\n")
    T_wb = np.eye(4)
    T_wb[:3, 3] = [1, 2, 3]
    frames = list(open_dataset(seq.root))
    assert np.allclose(frames[0].T_wc, T_wb @ EUROC_T_BS)
    assert frames[1].T_wc is None  # 50 ms away from the only sample


def test_mav0_folder_itself_opens(tmp_path):
    seq = make_euroc(tmp_path / "seq")
    assert detect_layout(seq.root / "mav0") == "euroc"
    assert len(open_dataset(seq.root / "mav0")) == len(seq.images)


def test_missing_sensor_yaml_names_it(tmp_path):
    seq = make_euroc(tmp_path / "seq")
    (seq.root / "mav0" / "cam0" / "sensor.yaml").unlink()
    with pytest.raises(DatasetError, match=r"cam0/sensor\.yaml: cannot read"):
        open_dataset(seq.root)


@pytest.mark.parametrize(
    "old, new, message",
    [
        ("resolution: [32, 24]", "resolution: [752, 480]", "are for 752x480 images but the images"),
        ("radial-tangential", "equidistant", "distortion model 'equidistant' is not supported"),
    ],
)
def test_a_sensor_yaml_that_does_not_fit_is_an_error(tmp_path, old, new, message):
    seq = make_euroc(tmp_path / "seq")
    yaml = seq.root / "mav0" / "cam0" / "sensor.yaml"
    yaml.write_text(yaml.read_text().replace(old, new))
    with pytest.raises(DatasetError, match=message):
        _ = open_dataset(seq.root).camera


def test_non_finite_ground_truth_names_the_line(tmp_path):
    seq = make_euroc(tmp_path / "seq")
    gt = seq.root / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    lines = gt.read_text().splitlines()
    lines[3] = lines[3].replace(lines[3].split(",")[2], "nan", 1)
    gt.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=r"data\.csv:4: non-finite"):
        open_dataset(seq.root)


def test_malformed_image_index_line(tmp_path):
    seq = make_euroc(tmp_path / "seq")
    with open(seq.root / "mav0" / "cam0" / "data.csv", "a") as f:
        f.write("1403636580000000000\n")
    with pytest.raises(DatasetError, match=r"cam0/data\.csv:8: expected 'timestamp_ns,filename'"):
        open_dataset(seq.root)

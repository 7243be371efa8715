"""Tiny sequences in every file layout, written into a temporary folder.

Each builder writes `n` small frames (frame 0 pure red where the layout is in colour) with
their ground truth, and returns a `Sequence` holding what a reader must give back.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch

from dimslam.common.geometry import pose

WIDTH, HEIGHT = 32, 24
CALIB = (30.0, 31.0, 15.5, 11.5)
RED_BGR = (0, 0, 255)

# The real cam0 sensor.yaml of EuRoC MH_01 (only `resolution` is filled in per test).
EUROC_SENSOR_YAML = """\
# General sensor definitions.
sensor_type: camera
comment: VI-Sensor cam0 (MT9M034)

# Sensor extrinsics wrt. the body-frame.
T_BS:
  cols: 4
  rows: 4
  data: [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975,
         0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768,
        -0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949,
         0.0, 0.0, 0.0, 1.0]

# Camera specific definitions.
rate_hz: 20
resolution: [{width}, {height}]
camera_model: pinhole
intrinsics: [{fu}, {fv}, {cu}, {cv}] #fu, fv, cu, cv
distortion_model: radial-tangential
distortion_coefficients: [{k1}, {k2}, {p1}, {p2}]
"""
EUROC_T_BS = np.array(
    [
        [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975],
        [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768],
        [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949],
        [0.0, 0.0, 0.0, 1.0],
    ]
)


@dataclass
class Sequence:
    """What was written, in frame order.

    Attributes:
        root: the folder to open.
        images: the image file of each frame.
        timestamps: the timestamp a reader must give each frame.
        poses: each frame's `T_wc`, or None where it has no ground truth.
        color: whether frame 0 is pure red (False for grayscale layouts).
    """

    root: Path
    images: list[Path]
    timestamps: list[float]
    poses: list[np.ndarray | None]
    color: bool = True
    extra: dict = field(default_factory=dict)


def image(seed: int, width: int = WIDTH, height: int = HEIGHT, gray: bool = False) -> np.ndarray:
    """A random BGR (or gray) uint8 image; seed 0 is pure red (or mid gray)."""
    if seed == 0:
        if gray:
            return np.full((height, width), 128, np.uint8)
        img = np.zeros((height, width, 3), np.uint8)
        img[:] = RED_BGR
        return img
    rng = np.random.default_rng(seed)
    return rng.integers(0, 256, (height, width) if gray else (height, width, 3), dtype=np.uint8)


def random_poses(n: int, seed: int = 0) -> list[np.ndarray]:
    """`n` random rigid `T_wc` (float64 4x4)."""
    g = torch.Generator().manual_seed(seed)
    xi = torch.randn(n, 6, generator=g, dtype=torch.float64)
    return list(pose.exp_se3(xi).numpy())


def tum_line(t: float, T: np.ndarray) -> str:
    q = pose.matrix_to_quat(torch.from_numpy(T[:3, :3])).numpy()
    return f"{t:.6f} " + " ".join(f"{v:.9f}" for v in (*T[:3, 3], *q))


def write_calib(folder: Path, values=CALIB) -> None:
    (folder / "calib.txt").write_text(" ".join(str(v) for v in values) + "\n")


def make_tum(root: Path, n: int = 6, size=(WIDTH, HEIGHT), calib=CALIB) -> Sequence:
    """TUM at 10 Hz; ground truth 0.019 s from frame 2 (associated), 0.03 s from frame 4 (beyond
    the 0.02 s tolerance: no pose), 0.01 s before or after the others."""
    (root / "rgb").mkdir(parents=True)
    times = [1305031102.175304 + i / 10 for i in range(n)]
    poses = random_poses(n, seed=1)
    offsets = [{2: 0.019, 4: 0.03}.get(i, 0.01 * (-1) ** i) for i in range(n)]
    images = []
    for i, t in enumerate(times):
        path = root / "rgb" / f"{t:.6f}.png"
        cv2.imwrite(str(path), image(i, *size))
        images.append(path)
    lines = ["# color images", "# file: 'x.bag'", "# timestamp filename"]
    lines += [f"{t:.6f} rgb/{p.name}" for t, p in zip(times, images, strict=True)]
    (root / "rgb.txt").write_text("\n".join(lines) + "\n")
    gt = ["# ground truth trajectory", "# timestamp tx ty tz qx qy qz qw"]
    gt += [tum_line(t + o, T) for t, o, T in zip(times, offsets, poses, strict=True)]
    (root / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    if calib is not None:
        write_calib(root, calib)
    expected = [T if abs(o) < 0.02 else None for o, T in zip(offsets, poses, strict=True)]
    return Sequence(root, images, times, expected)


def make_replica(root: Path, n: int = 6, size=(WIDTH, HEIGHT), calib=CALIB) -> Sequence:
    results = root / "results"
    results.mkdir(parents=True)
    poses = random_poses(n, seed=2)
    images = []
    for i in range(n):
        path = results / f"frame{i:06d}.jpg"
        cv2.imwrite(str(path), image(i, *size))
        cv2.imwrite(str(results / f"depth{i:06d}.png"), np.zeros(size[::-1], np.uint16))
        images.append(path)
    (root / "traj.txt").write_text(
        "\n".join(" ".join(f"{v:.12e}" for v in T.ravel()) for T in poses) + "\n"
    )
    if calib is not None:
        write_calib(root, calib)
    return Sequence(root, images, [i / 30 for i in range(n)], poses)


def make_euroc(
    root: Path, n: int = 6, size=(WIDTH, HEIGHT), dist=(0.01, -0.005, 0.0, 0.0)
) -> Sequence:
    """EuRoC: grayscale images; ground truth of the body at 200 Hz with w x y z quaternions."""
    cam0 = root / "mav0" / "cam0"
    (cam0 / "data").mkdir(parents=True)
    stamps_ns = [1403636579763555584 + i * 50_000_000 for i in range(n)]
    images = []
    for i, ns in enumerate(stamps_ns):
        path = cam0 / "data" / f"{ns}.png"
        cv2.imwrite(str(path), image(i, *size, gray=True))
        images.append(path)
    lines = ["#timestamp [ns],filename"] + [f"{ns},{ns}.png" for ns in stamps_ns]
    (cam0 / "data.csv").write_text("\n".join(lines) + "\n")
    fx, fy, cx, cy = CALIB
    (cam0 / "sensor.yaml").write_text(
        EUROC_SENSOR_YAML.format(
            width=size[0],
            height=size[1],
            fu=fx,
            fv=fy,
            cu=cx,
            cv=cy,
            k1=dist[0],
            k2=dist[1],
            p1=dist[2],
            p2=dist[3],
        )
    )
    # Ground truth: the body pose T_wb = T_wc @ T_bs^-1, 3 ms after each image.
    T_wc = random_poses(n, seed=3)
    T_sb = pose.invert(torch.from_numpy(EUROC_T_BS)).numpy()
    gt_dir = root / "mav0" / "state_groundtruth_estimate0"
    gt_dir.mkdir()
    rows = [
        "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], "
        "q_RS_z [], v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], "
        "b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], b_w_RS_S_z [rad s^-1], "
        "b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]"
    ]
    for ns, T in zip(stamps_ns, T_wc, strict=True):
        T_wb = T @ T_sb
        x, y, z, w = pose.matrix_to_quat(torch.from_numpy(T_wb[:3, :3])).numpy()
        values = [*T_wb[:3, 3], w, x, y, z] + [0.0] * 9
        rows.append(f"{ns + 3_000_000}," + ",".join(f"{v:.12f}" for v in values))
    (gt_dir / "data.csv").write_text("\n".join(rows) + "\n")
    return Sequence(root, images, [ns / 1e9 for ns in stamps_ns], T_wc, color=False)


def make_seven_scenes(
    root: Path, n: int = 6, size=(WIDTH, HEIGHT), first: int = 100, K=CALIB
) -> Sequence:
    """7-Scenes numbered from `first`; frame 3 has no pose file; frame 1 is a .jpg."""
    root.mkdir(parents=True, exist_ok=True)
    poses = random_poses(n, seed=4)
    images, expected = [], []
    for i in range(n):
        stem = root / f"frame-{first + i:06d}"
        ext = ".jpg" if i == 1 else ".png"
        path = stem.with_name(stem.name + ".color" + ext)
        cv2.imwrite(str(path), image(i, *size))
        cv2.imwrite(str(stem.with_name(stem.name + ".depth.png")), np.zeros(size[::-1], np.uint16))
        images.append(path)
        if i == 3:
            expected.append(None)
            continue
        np.savetxt(stem.with_name(stem.name + ".pose.txt"), poses[i])
        expected.append(poses[i])
    if K is not None:
        fx, fy, cx, cy = K
        np.savetxt(root / "camera-intrinsics.txt", [[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    return Sequence(root, images, [(first + i) / 30 for i in range(n)], expected)


def make_folder(root: Path, n: int = 6, size=(WIDTH, HEIGHT), calib=CALIB) -> Sequence:
    """Image folder with names that are not numbers: timestamps are index / 30."""
    root.mkdir(parents=True, exist_ok=True)
    images = []
    for i in range(n):
        path = root / f"img_{i}.png"
        cv2.imwrite(str(path), image(i, *size))
        images.append(path)
    if calib is not None:
        write_calib(root, calib)
    return Sequence(root, images, [i / 30 for i in range(n)], [None] * n)


BUILDERS = {
    "tum": make_tum,
    "replica": make_replica,
    "euroc": make_euroc,
    "7scenes": make_seven_scenes,
    "folder": make_folder,
}

"""The built-in synthetic scene: exact depth, view-independent colour, path limits, files."""

from __future__ import annotations

import itertools
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh

from dimslam.common.errors import DimslamError
from dimslam.common.geometry.camera import Camera, read_calib
from dimslam.common.io.synth import SynthScene, default_camera, write_sequence
from dimslam.common.io.trajectory import read_tum


@pytest.fixture(scope="module")
def scene() -> SynthScene:
    return SynthScene(0)


def look_at(eye, target) -> np.ndarray:
    """`T_wc` at `eye` looking at `target`, image x to the right of the view, world z up."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, [0, 0, 1.0])
    right /= np.linalg.norm(right)
    T = np.eye(4)
    T[:3, :3] = np.stack([right, np.cross(forward, right), forward], 1)
    T[:3, 3] = eye
    return T


def world_rays(T_wc: np.ndarray, camera: Camera) -> np.ndarray:
    """`(H * W, 3)` world directions of the pixel-centre rays, scaled to camera z = 1."""
    u, v = np.meshgrid(np.arange(camera.width), np.arange(camera.height))
    rays = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones(u.shape)])
    return rays.reshape(3, -1).T @ T_wc[:3, :3].T


def first_hits(mesh: trimesh.Trimesh, origin: np.ndarray, dirs: np.ndarray):
    """Möller-Trumbore against every triangle: ray parameter `t` and triangle of the first hit."""
    v0, v1, v2 = (mesh.triangles[:, k] for k in range(3))
    e1, e2 = v1 - v0, v2 - v0
    p = np.cross(dirs[:, None], e2[None])
    det = (e1[None] * p).sum(-1)
    safe = np.where(np.abs(det) < 1e-12, 1e-12, det)
    s = origin - v0
    a = (s[None] * p).sum(-1) / safe
    q = np.cross(s, e1)[None]
    b = (dirs[:, None] * q).sum(-1) / safe
    t = (e2[None] * q).sum(-1) / safe
    eps = 1e-9
    ok = (np.abs(det) > 1e-12) & (a >= -eps) & (b >= -eps) & (a + b <= 1 + eps) & (t > 1e-6)
    t = np.where(ok, t, np.inf)
    face = t.argmin(1)
    return t[np.arange(len(t)), face], face


def test_depth_is_the_first_surface_of_the_mesh(scene):
    # An independent ray cast against mesh() must give the rendered z-depth at every pixel, and
    # the surface hit must face the camera (room walls inward, furniture outward).
    mesh = scene.mesh()
    assert np.allclose(mesh.bounds, scene.room)
    assert len(mesh.faces) == 12 + 10 * len(scene.furniture)
    camera = default_camera(48, 36)
    centre = scene.room.mean(0)
    poses = [look_at(centre, box.mean(0)) for box in scene.furniture[:3]]
    poses += list(scene.path(90)[::45])
    # Views where one piece hides part of another: from 1 m behind piece A, away from piece B.
    for a, b in itertools.permutations(scene.furniture.mean(1), 2):
        eye = a + (a - b) / np.linalg.norm(a - b)
        inside = np.all((eye > scene.room[0] + 0.2) & (eye < scene.room[1] - 0.2))
        if inside and all(
            np.linalg.norm(eye - np.clip(eye, *box)) > 0.2 for box in scene.furniture
        ):
            poses.append(look_at(eye, b))
    assert len(poses) > 5
    furniture_pixels = 0
    for T in poses:
        _, depth = scene.render(T, camera)
        dirs = world_rays(T, camera)
        t, face = first_hits(mesh, T[:3, 3], dirs)
        assert np.isfinite(t).all()
        assert np.abs(t - depth.reshape(-1)).max() < 1e-3
        assert ((mesh.face_normals[face] * dirs).sum(1) < 0).all()
        furniture_pixels += (face >= 12).sum()
    assert furniture_pixels > 0.1 * len(poses) * 48 * 36


def test_colour_is_view_independent(scene):
    # A wall seen head-on and at about 27 degrees from the side: every point visible in both
    # views has the same colour in both (bilinear resampling and mip blur aside).
    camera = default_camera(96, 72)
    target = [2.5, 4.0, 1.2]
    T_a, T_b = look_at([2.5, 1.5, 1.4], target), look_at([1.6, 2.2, 1.4], target)
    rgb_a, depth_a = scene.render(T_a, camera)
    rgb_b, depth_b = scene.render(T_b, camera)
    assert rgb_a.dtype == np.float32 and depth_a.dtype == np.float32  # as documented
    points = T_a[:3, 3] + world_rays(T_a, camera) * depth_a.reshape(-1, 1)
    p_b = (points - T_b[:3, 3]) @ T_b[:3, :3]
    u = camera.fx * p_b[:, 0] / p_b[:, 2] + camera.cx
    v = camera.fy * p_b[:, 1] / p_b[:, 2] + camera.cy
    inside = (u > 1) & (u < camera.width - 2) & (v > 1) & (v < camera.height - 2)
    seen = np.zeros_like(inside)
    seen[inside] = (
        np.abs(
            depth_b[v[inside].round().astype(int), u[inside].round().astype(int)] - p_b[inside, 2]
        )
        < 0.01
    )
    assert seen.mean() > 0.4

    def sample(dx: float) -> np.ndarray:
        maps = [c.astype(np.float32).reshape(-1, 1) for c in (u + dx, v)]
        return cv2.remap(rgb_b, *maps, cv2.INTER_LINEAR).reshape(-1, 3)[seen]

    error = np.abs(sample(0.0) - rgb_a.reshape(-1, 3)[seen])
    assert np.median(error) < 0.02
    assert np.abs(error.mean(0)).max() < 0.02
    # The comparison has teeth: three pixels off, the textures disagree.
    assert np.median(np.abs(sample(3.0) - rgb_a.reshape(-1, 3)[seen])) > 2 * np.median(error)


def rotation_degrees(R_a: np.ndarray, R_b: np.ndarray) -> np.ndarray:
    cos = (np.einsum("nji,nji->n", R_a, R_b) - 1) / 2
    return np.degrees(np.arccos(np.clip(cos, -1, 1)))


@pytest.mark.parametrize("seed", [0, 1, 2, 7])
def test_path_is_smooth_slow_and_clear_of_everything(seed):
    scene = SynthScene(seed)
    T = scene.path(900)
    assert T.shape == (900, 4, 4) and T.dtype == np.float64
    R, c = T[:, :3, :3], T[:, :3, 3]
    assert np.allclose(R @ R.transpose(0, 2, 1), np.eye(3), atol=1e-9)
    assert np.allclose(np.linalg.det(R), 1)
    step = np.linalg.norm(np.diff(c, axis=0), axis=1)
    assert 0.005 < step.min() and step.max() < 0.025 and 0.01 < step.mean() < 0.02
    assert rotation_degrees(R[:-1], R[1:]).max() < 1.0
    # Smooth: velocity changes little from one frame to the next (no kinks or reversals).
    assert np.linalg.norm(np.diff(c, 2, axis=0), axis=1).max() < 0.005
    assert (np.minimum(c - scene.room[0], scene.room[1] - c) > 0.5).all()
    for lo, hi in scene.furniture:
        assert (np.linalg.norm(c - np.clip(c, lo, hi), axis=1) > 0.5).all()
    # Looks round the room, mostly level: never at the ceiling or the floor alone.
    forward = R[:, :, 2]
    assert (np.abs(forward[:, 2]) < 0.45).all()
    yaw = np.unwrap(np.arctan2(forward[:, 1], forward[:, 0]))
    assert np.ptp(yaw[:300]) > np.radians(60)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_loop_path_comes_back_to_its_start_looking_the_same_way(seed):
    scene = SynthScene(seed)
    T = scene.loop_path(330)
    R, c = T[:, :3, :3], T[:, :3, 3]
    assert np.allclose(R @ R.transpose(0, 2, 1), np.eye(3), atol=1e-9)
    step = np.linalg.norm(np.diff(c, axis=0), axis=1)
    assert step.max() < 0.025 and rotation_degrees(R[:-1], R[1:]).max() < 2.0
    assert (np.minimum(c - scene.room[0], scene.room[1] - c) > 0.5).all()
    for lo, hi in scene.furniture:
        assert (np.linalg.norm(c - np.clip(c, lo, hi), axis=1) > 0.5).all()
    # One turn is 300 of the 330 frames: there the camera is back where it started, looking
    # (nearly) the same way; halfway it is across the room looking the other way.
    back = 300
    assert np.linalg.norm(c[back] - c[0]) < 0.05
    assert rotation_degrees(R[:1], R[back : back + 1])[0] < 20  # the sway differs
    assert np.linalg.norm(c[back // 2] - c[0]) > 1.0
    assert rotation_degrees(R[:1], R[back // 2 : back // 2 + 1])[0] > 120


@pytest.mark.parametrize("seed", [0, 3])
def test_views_along_the_path_are_textured_and_not_too_close(seed):
    scene = SynthScene(seed)
    camera = default_camera(80, 60)
    for T in scene.path(300)[::30]:
        rgb, depth = scene.render(T, camera)
        assert depth.min() > 0.5
        z = T[2, 3] + (world_rays(T, camera) * depth.reshape(-1, 1))[:, 2]
        assert (z > scene.room[1, 2] - 1e-3).mean() < 0.3  # ceiling
        # No blank surfaces: nearly every 8x8 block has visible texture.
        blocks = rgb[:56, :80].reshape(7, 8, 10, 8, 3).std(axis=(1, 3)).max(-1)
        assert (blocks > 0.01).mean() > 0.9


def read_index(path):
    rows = [ln.split() for ln in path.read_text().splitlines() if not ln.startswith("#")]
    return [float(r[0]) for r in rows], [r[1] for r in rows]


def test_write_sequence_layout_reads_back(tmp_path):
    out = tmp_path / "seq"
    calls = []
    summary = write_sequence(
        out,
        frames=4,
        width=40,
        height=30,
        seed=3,
        noise=0.0,
        progress=lambda i, n: calls.append((i, n)),
    )
    assert calls == [(0, 4), (1, 4), (2, 4), (3, 4)]
    assert (summary.out_dir, summary.frames, summary.width, summary.height) == (out, 4, 40, 30)
    assert summary.seconds > 0 and summary.fps > 0
    names = ["1.000000", "1.033333", "1.066667", "1.100000"]
    assert sorted(p.name for p in out.iterdir()) == sorted(
        ["rgb", "depth", "rgb.txt", "depth.txt", "groundtruth.txt", "calib.txt", "mesh.ply"]
    )
    for folder in ("rgb", "depth"):
        stamps, files = read_index(out / f"{folder}.txt")
        assert np.allclose(stamps, 1 + np.arange(4) / 30, atol=1e-6)
        assert files == [f"{folder}/{n}.png" for n in names]
        assert sorted(p.name for p in (out / folder).iterdir()) == [f"{n}.png" for n in names]
    fx, fy, cx, cy, dist = read_calib(out / "calib.txt")
    camera = default_camera(40, 30)
    assert (fx, fy, cx, cy) == pytest.approx((32.8, 32.8, 19.5, 14.5)) and dist == ()
    scene = SynthScene(3)
    gt = read_tum(out / "groundtruth.txt")
    assert np.allclose(gt.timestamps, 1 + np.arange(4) / 30, atol=1e-6)
    assert np.abs(gt.poses - scene.path(4)).max() < 1e-6
    for i, name in enumerate(names):
        rgb, depth = scene.render(gt.poses[i], camera)
        bgr = cv2.imread(str(out / "rgb" / f"{name}.png"), cv2.IMREAD_UNCHANGED)
        assert bgr.dtype == np.uint8 and bgr.shape == (30, 40, 3)
        assert np.abs(bgr[..., ::-1] / 255.0 - rgb).max() <= 1 / 255 + 1e-6  # RGB order on disk
        stored = cv2.imread(str(out / "depth" / f"{name}.png"), cv2.IMREAD_UNCHANGED)
        assert stored.dtype == np.uint16 and stored.shape == (30, 40)
        assert np.abs(stored / 5000.0 - depth).max() <= 1e-4 + 1e-6
    mesh = trimesh.load(out / "mesh.ply", process=False)
    assert np.allclose(mesh.bounds, scene.room) and len(mesh.faces) == len(scene.mesh().faces)


def test_same_seed_same_bytes_other_seed_other_sequence(tmp_path):
    def write(name, seed, noise):
        write_sequence(tmp_path / name, frames=3, width=32, height=24, seed=seed, noise=noise)
        return {
            p.relative_to(tmp_path / name): p.read_bytes()
            for p in sorted((tmp_path / name).rglob("*"))
            if p.is_file()
        }

    a, b = write("a", 0, 2.0), write("b", 0, 2.0)
    assert a == b
    c = write("c", 1, 2.0)
    assert c[Path("rgb/1.000000.png")] != a[Path("rgb/1.000000.png")]
    path_a, path_c = (read_tum(tmp_path / n / "groundtruth.txt").positions for n in "ac")
    assert np.linalg.norm(path_a - path_c, axis=1).min() > 0.05
    # The noise has the requested sigma, around the noise-free image.
    write("clean", 0, 0.0)
    noisy = cv2.imread(str(tmp_path / "a" / "rgb" / "1.000000.png")).astype(float)
    clean = cv2.imread(str(tmp_path / "clean" / "rgb" / "1.000000.png")).astype(float)
    assert 1.7 < (noisy - clean).std() < 2.3 and abs((noisy - clean).mean()) < 0.2


def test_rewriting_a_previous_output_replaces_its_frames(tmp_path):
    write_sequence(tmp_path, frames=5, width=16, height=12)
    write_sequence(tmp_path, frames=2, width=16, height=12)
    assert len(list((tmp_path / "rgb").iterdir())) == 2
    assert len(read_index(tmp_path / "rgb.txt")[0]) == 2


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"frames": 0}, "frames"),
        ({"frames": 2.5}, "frames"),
        ({"width": 4}, "width"),
        ({"height": 7}, "height"),
        ({"noise": -1.0}, "noise"),
        ({"noise": float("nan")}, "noise"),
        ({"seed": -1}, "seed"),
        ({"path": "spiral"}, "path"),
    ],
)
def test_bad_arguments_are_refused(tmp_path, kwargs, message):
    with pytest.raises(DimslamError, match=message):
        write_sequence(tmp_path / "out", **{"frames": 2, "width": 16, "height": 12, **kwargs})
    assert not (tmp_path / "out").exists()


def test_foreign_output_folders_are_refused(tmp_path):
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(DimslamError, match="not empty"):
        write_sequence(tmp_path, frames=1, width=16, height=12)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]
    with pytest.raises(DimslamError, match="not a folder"):
        write_sequence(tmp_path / "notes.txt", frames=1, width=16, height=12)
    # A TUM-like folder that this module did not write is not overwritten either.
    (tmp_path / "tum").mkdir()
    (tmp_path / "tum" / "rgb.txt").write_text("# color images\n")
    with pytest.raises(DimslamError, match="not empty"):
        write_sequence(tmp_path / "tum", frames=1, width=16, height=12)


def test_render_refuses_a_camera_outside_the_room(scene):
    with pytest.raises(ValueError, match="outside the room"):
        scene.render(look_at([6.0, 2.0, 1.0], [2.5, 2.0, 1.0]), default_camera(16, 12))

"""Mesh extraction on analytic fields with known surfaces: geometry, orientation, colours,
culling, the synthetic room against its exact mesh, clear errors and the PLY round trip."""

import numpy as np
import pytest
import torch
import trimesh

from dimslam.common.errors import DimslamError
from dimslam.common.eval.evaluation import Sim3
from dimslam.common.eval.mesh_metrics import evaluate_mesh
from dimslam.common.geometry.camera import Camera, frustum_mask
from dimslam.common.io.synth import SynthScene, default_camera
from dimslam.common.map import mesh as meshing
from dimslam.common.map.mesh import EmptyMeshError, extract_mesh, fused_occupancy, write_mesh

CAMERA = Camera(64, 48, 50.0, 50.0, 31.5, 23.5)
BOUND = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
CENTRE, RADIUS, VOXEL = np.array([0.1, -0.05, 0.02]), 0.5, 0.05


def look_at(eye, target=(0.0, 0.0, 0.0)) -> np.ndarray:
    """`T_wc` (OpenCV axes) of a camera at `eye` looking at `target`."""
    forward = np.asarray(target, float) - eye
    forward /= np.linalg.norm(forward)
    up = [0.0, 0.0, 1.0] if abs(forward[2]) < 0.9 else [0.0, 1.0, 0.0]
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    T = np.eye(4)
    T[:3, :3] = np.stack([right, np.cross(forward, right), forward], 1)
    T[:3, 3] = eye
    return T


AROUND = np.stack([look_at(2 * e) for e in np.concatenate([np.eye(3), -np.eye(3)])])


def ball(points: torch.Tensor) -> torch.Tensor:
    # Sharp enough to be a surface, soft enough for marching cubes to interpolate.
    r = (points.double() - torch.from_numpy(CENTRE)).norm(dim=-1)
    return torch.sigmoid((RADIUS - r) * (2 / VOXEL)).float()


def position_colour(points: torch.Tensor) -> torch.Tensor:
    return (points + 1) / 2


def test_ball_surface_normals_and_colours():
    mesh = extract_mesh(ball, position_colour, BOUND, VOXEL, AROUND, CAMERA, max_depth=4.0)
    v = mesh.vertices
    assert np.abs(np.linalg.norm(v - CENTRE, axis=1) - RADIUS).max() < 0.05 * VOXEL
    # Closed and outward: every face normal points away from the centre.
    assert mesh.is_watertight
    outward = np.einsum("ij,ij->i", mesh.face_normals, mesh.triangles_center - CENTRE)
    assert (outward > 0).all()
    assert mesh.volume == pytest.approx(4 / 3 * np.pi * RADIUS**3, rel=0.02)
    colours = mesh.visual.vertex_colors
    assert colours.dtype == np.uint8 and (colours[:, 3] == 255).all()
    np.testing.assert_allclose(colours[:, :3], (v + 1) / 2 * 255, atol=0.51)


def test_culling_keeps_the_seen_side_within_max_depth():
    # Seen along a diagonal, with the far plane through the centre: the frustum's axis-aligned
    # box holds all of the ball, so the culling alone must drop the far half.
    eye = CENTRE + 2 * np.ones(3) / np.sqrt(3)
    T_wc = look_at(eye, CENTRE)[None]
    mesh = extract_mesh(ball, position_colour, BOUND, VOXEL, T_wc, CAMERA, max_depth=2.0)
    depth = (mesh.vertices - eye) @ T_wc[0, :3, 2]
    assert 1.5 - 0.01 * VOXEL < depth.min() and depth.max() <= 2.0
    assert frustum_mask(mesh.vertices, T_wc, CAMERA).all()
    hemisphere = 2 * np.pi * RADIUS**2
    assert 0.9 * hemisphere < mesh.area < hemisphere


def test_only_the_box_around_the_frustums_is_evaluated():
    calls = []

    def counted(points: torch.Tensor) -> torch.Tensor:
        calls.append(len(points))
        return ball(points)

    # One camera on +x looking at the ball, the far plane at the centre: the near half remains.
    T_wc = look_at(np.array([2.0, 0.0, 0.0]) + CENTRE, CENTRE)[None]
    mesh = extract_mesh(counted, position_colour, BOUND, VOXEL, T_wc, CAMERA, max_depth=2.0)
    assert mesh.vertices[:, 0].min() >= CENTRE[0] - 1e-6
    assert sum(calls) < 0.5 * 41**3  # the whole bound's grid has 41^3 points


def synth_occupancy(scene: SynthScene, sharpness: float):
    """Occupied outside the room's interior and inside the furniture, as `scene.mesh()`."""
    room = torch.from_numpy(scene.room)
    boxes = torch.from_numpy(scene.furniture)

    def occupancy(points: torch.Tensor) -> torch.Tensor:
        p = points.double()
        # Signed distance to the room's walls, positive outside the room (in the walls).
        q = (p - room.mean(0)).abs() - (room[1] - room[0]) / 2
        phi = q.clamp(min=0).norm(dim=-1) + q.max(-1).values.clamp(max=0)
        for box in boxes:
            q = (p - box.mean(0)).abs() - (box[1] - box[0]) / 2
            inside = -(q.clamp(min=0).norm(dim=-1) + q.max(-1).values.clamp(max=0))
            phi = torch.maximum(phi, inside)
        return torch.sigmoid(phi * sharpness).float()

    return occupancy


def test_synth_room_matches_its_exact_mesh():
    scene = SynthScene(0)
    poses, camera = scene.path(300)[::10], default_camera(64, 48)
    voxel = 0.05
    bound = scene.room + [[-0.2], [0.2]]
    occupancy = synth_occupancy(scene, 2 / voxel)
    mesh = extract_mesh(
        occupancy, lambda p: torch.full_like(p, 0.5), bound, voxel, poses, camera, max_depth=8.0
    )
    # Normals point out of the walls and furniture, into free space.
    step = torch.tensor(mesh.face_normals * voxel / 2)
    centre = torch.tensor(mesh.triangles_center)
    outward = (occupancy(centre + step) < 0.5) & (occupancy(centre - step) > 0.5)
    assert outward.float().mean() > 0.99
    # Vertices on the surface: |signed distance| well under a voxel (corners are chamfered).
    phi = torch.logit(occupancy(torch.tensor(mesh.vertices)).double()) * voxel / 2
    assert phi.abs().max() < 0.25 * voxel
    metrics = evaluate_mesh(mesh, scene.mesh(), Sim3.identity(), poses, camera, samples=40_000)
    # The floor of these figures is the sampling (~1.4 cm at 40,000 points); a mesh shifted by a
    # quarter voxel along each axis scores 2.0 and 2.2 cm.
    assert metrics.accuracy_cm < 1.8 and metrics.completion_cm < 1.8
    assert metrics.completion_ratio > 98


def test_empty_and_saturated_maps_raise_clear_errors():
    for value in (0.0, 1.0):
        with pytest.raises(EmptyMeshError, match="never crosses"):
            extract_mesh(
                lambda p, v=value: torch.full((len(p),), v),
                position_colour,
                BOUND,
                VOXEL,
                AROUND,
                CAMERA,
                max_depth=4.0,
            )
    with pytest.raises(DimslamError, match="not finite"):
        extract_mesh(
            lambda p: torch.full((len(p),), float("nan")),
            position_colour,
            BOUND,
            VOXEL,
            AROUND,
            CAMERA,
            4.0,
        )


def test_a_surface_outside_every_frustum_raises_a_clear_error():
    # The frustum's axis-aligned box reaches into the ball, the frustum itself stops short of it.
    eye = CENTRE + 2 * np.ones(3) / np.sqrt(3)
    T_wc = look_at(eye, CENTRE)[None]
    with pytest.raises(EmptyMeshError, match="within max_depth 1.4"):
        extract_mesh(ball, position_colour, BOUND, VOXEL, T_wc, CAMERA, max_depth=1.4)


def test_absurd_grid_and_blind_cameras_raise_clear_errors():
    calls = []
    with pytest.raises(DimslamError, match="use a voxel of at least"):
        extract_mesh(calls.append, position_colour, BOUND, 1e-3, AROUND, CAMERA, 4.0)
    assert not calls  # refused before any work
    away = look_at(np.array([5.0, 0.0, 0.0]), np.array([10.0, 0.0, 0.0]))[None]
    with pytest.raises(DimslamError, match="see no part of the bound"):
        extract_mesh(ball, position_colour, BOUND, VOXEL, away, CAMERA, 4.0)


def test_a_grid_over_the_budget_is_meshed_coarser_in_budget(monkeypatch, caplog):
    """`extract_mesh_in_budget` meshes at the voxel the budget allows, and says so."""
    monkeypatch.setattr(meshing, "MAX_GRID_CELLS", 20**3)  # 40^3 cells at VOXEL
    with pytest.raises(DimslamError, match="use a voxel of at least"):
        extract_mesh(ball, position_colour, BOUND, VOXEL, AROUND, CAMERA, 4.0)
    mesh = meshing.extract_mesh_in_budget(ball, position_colour, BOUND, VOXEL, AROUND, CAMERA, 4.0)
    assert "meshing at" in caplog.text
    assert np.abs(np.linalg.norm(mesh.vertices - CENTRE, axis=1) - RADIUS).max() < 2 * VOXEL


def test_progress_and_ply_round_trip(tmp_path):
    seen = []
    mesh = extract_mesh(
        ball,
        position_colour,
        torch.from_numpy(BOUND),
        VOXEL,
        torch.from_numpy(AROUND).float(),
        CAMERA,
        4.0,
        chunk=10_000,
        progress=lambda done, total: seen.append((done, total)),
    )
    assert seen[-1][0] == seen[-1][1] and len(seen) == -(-seen[-1][1] // 10_000)
    path = tmp_path / "out" / "mesh.ply"
    write_mesh(mesh, path)
    assert path.read_bytes().startswith(b"ply\nformat binary_little_endian")
    loaded = trimesh.load(path, process=False)
    assert len(loaded.vertices) == len(mesh.vertices) and len(loaded.faces) == len(mesh.faces)
    np.testing.assert_allclose(loaded.vertices, mesh.vertices, atol=1e-6)
    np.testing.assert_array_equal(loaded.visual.vertex_colors, mesh.visual.vertex_colors)


def _sphere_depth(T_wc: np.ndarray) -> torch.Tensor:
    """Exact z-depth of the ball seen from `T_wc`; a ray that misses it sees a far wall (10)."""
    v, u = np.mgrid[0 : CAMERA.height, 0 : CAMERA.width].astype(float)
    d = np.stack([(u - CAMERA.cx) / CAMERA.fx, (v - CAMERA.cy) / CAMERA.fy, np.ones_like(u)], -1)
    d_w = d @ T_wc[:3, :3].T
    o = T_wc[:3, 3] - CENTRE
    a, b, c = (d_w**2).sum(-1), 2 * (d_w @ o), o @ o - RADIUS**2
    disc = b**2 - 4 * a * c
    t = (-b - np.sqrt(np.clip(disc, 0, None))) / (2 * a)
    return torch.from_numpy(np.where(disc > 0, t, 10.0)).float()  # t is z-depth: d has z = 1


def test_fused_occupancy_meshes_the_surface_the_depth_maps_see():
    depths = torch.stack([_sphere_depth(T) for T in AROUND])
    occupancy = fused_occupancy(depths, torch.from_numpy(AROUND), CAMERA, truncation=3 * VOXEL)
    on = torch.from_numpy(CENTRE + np.array([RADIUS, 0, 0])).float()[None]
    inside = torch.from_numpy(CENTRE + np.array([RADIUS - VOXEL, 0, 0])).float()[None]
    outside = torch.from_numpy(CENTRE + np.array([RADIUS + VOXEL, 0, 0])).float()[None]
    assert abs(float(occupancy(on)) - 0.5) < 0.1
    # One voxel is a third of the truncation: sigmoid(4/3) = 0.79 for the views that see it.
    assert float(occupancy(inside)) > 0.7 and float(occupancy(outside)) < 0.3
    centre = torch.tensor([[0.1, -0.05, 0.02]])  # deep behind every view's surface: unknown
    assert torch.isnan(occupancy(centre)).all()
    assert float(occupancy(torch.tensor([[0.9, 0.9, 0.9]]))) < 0.5  # free space in view
    counted = {False: 0, True: 0}

    def mesh_of(coarse: bool) -> trimesh.Trimesh:
        def counting(p: torch.Tensor) -> torch.Tensor:
            counted[coarse] += len(p)
            return occupancy(p)

        args = (position_colour, BOUND, VOXEL, AROUND, CAMERA)
        return extract_mesh(counting, *args, max_depth=4.0, unknown_nan=True, coarse=coarse)

    mesh = mesh_of(coarse=False)
    r = np.linalg.norm(mesh.vertices - CENTRE, axis=1)
    # The fused surface is the ball's, to a voxel; a few faces at the silhouettes stray further
    # (a pixel there holds the depth of the ball's edge for points beside it).
    error = np.abs(r - RADIUS)
    assert np.median(error) < VOXEL / 4 and np.quantile(error, 0.99) < VOXEL
    # Coarse to fine: the same mesh from fewer evaluations of the occupancy.
    fast = mesh_of(coarse=True)
    assert len(fast.faces) == len(mesh.faces)
    np.testing.assert_allclose(np.sort(fast.vertices, 0), np.sort(mesh.vertices, 0), atol=1e-6)
    assert counted[True] < 0.6 * counted[False], counted


def test_fused_occupancy_weighs_each_depth():
    """Two views of the ball from +x, one seeing it a voxel too deep: with equal weights the
    fused surface lies half a voxel deeper, with the deep one at weight 1/4 a fifth of a
    voxel (the weighted mean of the two signed distances), and a weight of 0 leaves it out."""
    T = np.stack([AROUND[0], AROUND[0]])
    near = _sphere_depth(AROUND[0])
    far = torch.where(near < 10.0, near + VOXEL, near)
    depths = torch.stack([near, far])
    surface = CENTRE + np.array([RADIUS, 0, 0])

    def crossing(weights) -> float:
        """Where the occupancy crosses 0.5 along +x (towards the camera) from the true
        surface."""
        occupancy = fused_occupancy(depths, torch.from_numpy(T), CAMERA, 3 * VOXEL, weights)
        steps = np.linspace(-VOXEL, 2 * VOXEL, 301)
        points = torch.from_numpy(surface + steps[:, None] * np.array([1.0, 0, 0])).float()
        return float(steps[int(np.argmax(occupancy(points).numpy() < 0.5))])

    full = torch.ones_like(depths)
    quarter = torch.stack([full[0], 0.25 * full[1]])
    alone = torch.stack([full[0], 0 * full[1]])
    assert abs(crossing(None) + VOXEL / 2) < 0.05 * VOXEL
    assert abs(crossing(quarter) + VOXEL / 5) < 0.05 * VOXEL
    assert abs(crossing(alone)) < 0.05 * VOXEL
    with pytest.raises(ValueError):
        fused_occupancy(depths, torch.from_numpy(T), CAMERA, 3 * VOXEL, torch.ones(2))

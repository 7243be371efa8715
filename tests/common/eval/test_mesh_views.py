"""The mesh pictures: a z-buffer that covers what projects, the nearest face on top, culling."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import trimesh

from dimslam.common.errors import DimslamError
from dimslam.common.eval.mesh_views import (
    BACKGROUND,
    VIEW_WIDTH,
    facing,
    look_at,
    render_mesh,
    write_mesh_views,
)
from dimslam.common.geometry.camera import Camera

CAMERA = Camera(160, 120, 100.0, 100.0, 79.5, 59.5)


def _square(z: float, half: float, rgb: tuple[int, int, int]) -> trimesh.Trimesh:
    """A square facing the camera at the origin (looking along +z), at depth `z`."""
    v = [[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]]
    mesh = trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3]], process=False)
    mesh.visual.vertex_colors = np.array([[*rgb, 255]] * 4, np.uint8)
    return mesh


def _covered(image: np.ndarray) -> np.ndarray:
    return (image != BACKGROUND).any(axis=-1)


def test_a_square_covers_the_pixels_it_projects_to():
    # Half-width 0.4 at depth 2: 100 * 0.4 / 2 = 20 px each side of the centre.
    image = render_mesh(_square(2.0, 0.4, (200, 0, 0)), CAMERA, np.eye(4))
    rows, cols = np.nonzero(_covered(image))
    assert (cols.min(), cols.max(), rows.min(), rows.max()) == (60, 99, 40, 79)
    assert _covered(image).sum() == 40 * 40
    # Seen (nearly) head-on it keeps its colour.
    assert np.abs(image[60, 80].astype(int) - (200, 0, 0)).max() <= 3


def test_the_nearest_face_wins_whichever_comes_first():
    near, far = _square(1.0, 0.1, (0, 255, 0)), _square(2.0, 0.4, (255, 0, 0))
    for mesh in (trimesh.util.concatenate([far, near]), trimesh.util.concatenate([near, far])):
        image = render_mesh(mesh, CAMERA, np.eye(4))
        assert np.argmax(image[60, 80]) == 1  # green: the near square, 10 px each side
        assert np.argmax(image[60, 95]) == 0  # red: outside it, the far one


def test_faces_behind_or_beside_the_camera_are_not_drawn():
    mesh = _square(2.0, 0.4, (200, 0, 0))
    behind = look_at(np.array([0.0, 0.0, 3.0]), np.array([0.0, 0.0, 5.0]), np.array([0, -1.0, 0]))
    beside = look_at(np.zeros(3), np.array([5.0, 0.0, 2.0]), np.array([0, -1.0, 0]))
    for T in (behind, beside):
        assert not _covered(render_mesh(mesh, CAMERA, T)).any()


def test_a_room_seen_from_outside_shows_its_floor_when_culled_as_its_cameras_saw_it():
    """A room (a box whose cameras were inside it) looked at from above: drawn whole, its
    roof (red) hides the rest; culled as the cameras inside saw it, its floor (green) shows."""
    box = trimesh.creation.box(extents=(4.0, 2.0, 4.0))
    corners = box.vertices[box.faces]  # (F, 3, 3): no vertex shared, a colour per face
    faces = np.arange(3 * len(box.faces)).reshape(-1, 3)
    room = trimesh.Trimesh(corners.reshape(-1, 3), faces, process=False)
    height = corners[..., 1].mean(axis=1)  # y down: the floor at +1, the roof at -1
    rgb = np.full((len(box.faces), 3), 128)
    rgb[height > 0.99], rgb[height < -0.99] = (0, 255, 0), (255, 0, 0)
    room.visual.vertex_colors = np.repeat(rgb, 3, axis=0).astype(np.uint8)
    cull = facing(room, np.eye(4))  # from its centre, looking along +z
    above = look_at(np.array([0.0, -8.0, -0.1]), np.zeros(3), np.array([0.0, 0.0, 1.0]))
    centre = (CAMERA.height // 2, CAMERA.width // 2)
    assert np.argmax(render_mesh(room, CAMERA, above)[centre]) == 0  # red roof
    assert np.argmax(render_mesh(room, CAMERA, above, cull)[centre]) == 1  # green floor
    # Culled the other way, the outside is left: the roof again.
    assert np.argmax(render_mesh(room, CAMERA, above, -cull)[centre]) == 0


def test_the_views_make_one_picture_of_four(tmp_path):
    mesh = _square(2.0, 1.0, (90, 120, 200))
    poses = np.stack([np.eye(4)] * 5)
    poses[:, 0, 3] = np.linspace(-0.2, 0.2, 5)
    path = write_mesh_views(mesh, CAMERA, poses, tmp_path / "views" / "mesh_views.png")
    picture = cv2.imread(str(path))
    h, w = CAMERA.resized(VIEW_WIDTH).height, VIEW_WIDTH
    assert picture.shape == (2 * h, 2 * w, 3)
    tiles = [picture[r : r + h, c : c + w] for r in (0, h) for c in (0, w)]
    assert all(_covered(cv2.cvtColor(t, cv2.COLOR_BGR2RGB)).any() for t in tiles)
    with pytest.raises(DimslamError, match="at least one camera pose"):
        write_mesh_views(mesh, CAMERA, np.zeros((0, 4, 4)), tmp_path / "none.png")

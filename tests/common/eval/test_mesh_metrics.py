"""Mesh metrics on small scenes with known answers: perfect copies, known offsets, culling to
the cameras' frustums, determinism, clear errors."""

import numpy as np
import pytest
import torch
import trimesh

from dimslam.common.errors import EvaluationError
from dimslam.common.eval.evaluation import Sim3
from dimslam.common.eval.mesh_metrics import MeshMetrics, evaluate_mesh
from dimslam.common.geometry import pose
from dimslam.common.geometry.camera import Camera

# A camera at the origin looking down +z: at z = 2 it sees |x|, |y| <= 2 exactly
# (the image spans pixel edges -0.5 .. 199.5 and cx = 99.5, fx = 100).

CAM = Camera(200, 200, 100.0, 100.0, 99.5, 99.5)
SAMPLES = 40_000


def quad(x0: float, x1: float, y0: float, y1: float, z: float) -> trimesh.Trimesh:
    vertices = [[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]]
    return trimesh.Trimesh(vertices, [[0, 1, 2], [0, 2, 3]], process=False)


def test_mesh_against_itself_is_perfect():
    mesh = quad(-1, 1, -1, 1, 2.0)
    m = evaluate_mesh(mesh, mesh, Sim3.identity(), None, None, samples=SAMPLES)
    # Both meshes are sampled with the same seed: identical surfaces, identical points.
    assert isinstance(m, MeshMetrics)
    assert m.accuracy_cm < 1e-9 and m.completion_cm < 1e-9
    assert m.completion_ratio == 100.0
    assert not m.culled and m.gt_visible_fraction == 1.0


def test_alignment_is_applied_to_the_estimate():
    mesh = quad(-1, 1, -1, 1, 2.0)
    S = Sim3(
        1.7,
        pose.exp_so3(torch.tensor([0.3, -1.2, 2.0], dtype=torch.float64)).numpy(),
        [0.5, -2.0, 1.0],
    )
    est = mesh.copy()
    est.vertices = S.inverse().apply_points(mesh.vertices)  # the estimate's own frame
    m = evaluate_mesh(est, mesh, S, None, None, samples=SAMPLES)
    assert m.accuracy_cm < 0.8 and m.completion_ratio == 100.0


def test_a_3cm_offset_reads_3cm():
    gt = quad(-1, 1, -1, 1, 2.0)
    est = quad(-1, 1, -1, 1, 2.03)  # moved along the normal: every point is 3 cm off
    m = evaluate_mesh(est, gt, Sim3.identity(), None, None, samples=SAMPLES)
    # Lateral sampling offsets add in quadrature: sqrt(3^2 + ~0.5^2) ~ 3.04 cm.
    assert 2.95 < m.accuracy_cm < 3.2 and 2.95 < m.completion_cm < 3.2
    assert m.completion_ratio == 100.0
    tight = evaluate_mesh(est, gt, Sim3.identity(), None, None, samples=SAMPLES, threshold_m=0.02)
    assert tight.completion_ratio == 0.0 and tight.threshold_cm == pytest.approx(2.0)


def culling_scene() -> trimesh.Trimesh:
    # A 6 x 2 m wall at z = 2, of which the camera sees |x| <= 2, and a 1 m box behind the
    # camera, on its axis: it would project into the image if z > 0 were not tested.
    behind = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    behind.apply_translation((0.0, 0.0, -3.0))
    return trimesh.util.concatenate([quad(-3, 3, -1, 1, 2.0), behind])


def test_culling_removes_surface_no_camera_sees():
    gt = culling_scene()
    seen_part = quad(-2, 2, -1, 1, 2.0)  # a perfect reconstruction of what was seen
    poses = np.eye(4)[None]

    culled = evaluate_mesh(seen_part, gt, Sim3.identity(), poses, CAM, samples=SAMPLES)
    assert culled.culled
    assert culled.completion_ratio == 100.0 and culled.completion_cm < 0.8
    assert culled.gt_visible_fraction == pytest.approx(8.0 / 18.0, abs=0.01)

    whole = evaluate_mesh(seen_part, gt, Sim3.identity(), None, None, samples=SAMPLES)
    # 8 of 18 m^2 within reach, plus a 5 cm rim: ~46%.
    assert not whole.culled and 40.0 < whole.completion_ratio < 50.0

    # The estimate is culled too: surface it has where no camera looked does not count.
    extra = evaluate_mesh(gt, gt, Sim3.identity(), poses, CAM, samples=SAMPLES)
    assert extra.accuracy_cm < 1e-9 and extra.completion_ratio == 100.0


def test_mesh_metrics_are_deterministic_per_seed():
    gt = culling_scene()
    est = quad(-2, 2, -1, 1, 2.01)
    args = (est, gt, Sim3.identity(), np.eye(4)[None], CAM)
    a = evaluate_mesh(*args, samples=5000, seed=1)
    assert a == evaluate_mesh(*args, samples=5000, seed=1)
    assert a != evaluate_mesh(*args, samples=5000, seed=2)
    assert set(a.to_dict()) == {
        "accuracy_cm",
        "completion_cm",
        "completion_ratio",
        "threshold_cm",
        "samples",
        "culled",
        "gt_visible_fraction",
    }


def test_mesh_errors_are_clear():
    gt = quad(-1, 1, -1, 1, 2.0)
    empty = trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=int))
    with pytest.raises(EvaluationError, match="estimated mesh has no surface"):
        evaluate_mesh(empty, gt, Sim3.identity(), None, None, samples=100)
    away = pose.make_pose(torch.eye(3, dtype=torch.float64), torch.tensor([0.0, 0.0, 10.0]))
    with pytest.raises(EvaluationError, match="cameras see almost none of the ground-truth"):
        evaluate_mesh(gt, gt, Sim3.identity(), away.numpy()[None], CAM, samples=1000)

"""The mapper's half of the pipeline: the final trajectory re-anchors every other frame to its
keyframe, and follows the keyframes a loop correction or a global refinement round moves."""

import pytest
import torch
from walls import CAM, textured_wall_image

from dimslam.common.config import PRESETS
from dimslam.common.geometry import pose, sim3
from dimslam.common.map.mesh import EmptyMeshError
from dimslam.common.optim.window import FrameState
from dimslam.common.options import apply_overrides
from dimslam.mapper.backend import BackEnd


def moved(x: float) -> torch.Tensor:
    return pose.make_pose(torch.eye(3), torch.tensor([x, 0.0, 0.0]))


def test_non_keyframes_follow_their_keyframe_in_the_final_trajectory():
    back = BackEnd(PRESETS["tiny"], CAM, torch.device("cpu"), torch.Generator())
    frames = [FrameState(i, i / 30, None, moved(0.1 * i), keyframe=i in (0, 2)) for i in range(4)]
    back.add(frames)
    back.initialized = True  # as after a mapping round over these frames
    back._anchor(frames)
    frames[2].T_wc = moved(0.3)  # a later round moves keyframe 2 by 10 cm
    traj = back.trajectory()
    assert traj.poses[:, 0, 3].tolist() == pytest.approx([0.0, 0.1, 0.3, 0.4], abs=1e-6)
    assert back.trajectory(keyframes_only=True).poses[:, 0, 3].tolist() == pytest.approx(
        [0.0, 0.3], abs=1e-6
    )


def test_before_initialization_there_is_no_trajectory_and_no_mesh():
    back = BackEnd(PRESETS["tiny"], CAM, torch.device("cpu"), torch.Generator())
    back.add([FrameState(0, 0.0, None, torch.eye(4))])
    assert len(back.trajectory()) == 0
    with pytest.raises(EmptyMeshError, match="no map yet"):
        back.extract_mesh()


def test_a_loop_correction_moves_keyframes_and_scales_the_frames_anchored_to_them():
    back = BackEnd(PRESETS["tiny"], CAM, torch.device("cpu"), torch.Generator())
    frames = [FrameState(i, i / 30, None, moved(0.1 * i), keyframe=i in (0, 2)) for i in range(4)]
    back.add(frames)
    back.initialized = True
    back._anchor(frames)
    # The pose graph keeps keyframe 0 and moves keyframe 2 to x = 0.5 at twice the scale.
    nodes = torch.stack([sim3.from_pose(moved(0.0)), sim3.from_pose(moved(0.5), 2.0)]).double()
    back._move(back.keyframes, nodes)
    x = [float(f.T_wc[0, 3]) for f in frames]
    # Frame 1 keeps its offset from keyframe 0; frame 3's offset from keyframe 2 doubles.
    assert x == pytest.approx([0.0, 0.1, 0.5, 0.7], abs=1e-6)
    assert back.trajectory().poses[:, 0, 3].tolist() == pytest.approx(x, abs=1e-6)


def test_a_global_refinement_round_moves_keyframes_and_the_frames_anchored_to_them():
    cfg = apply_overrides(PRESETS["tiny"], {"mapper.global_iters": "4", "mapper.pixels": "64"})
    back = BackEnd(cfg, CAM, torch.device("cpu"), torch.Generator().manual_seed(0))
    frames = [
        FrameState(i, i / 30, textured_wall_image(moved(0.05 * i)), moved(0.05 * i), i % 2 == 0)
        for i in range(6)
    ]
    back.add(frames)
    back.initialized = True
    back._anchor(frames)
    before = [f.T_wc.clone() for f in frames]
    rel = pose.compose(pose.invert(before[2]), before[3])
    back.refine_global()
    assert torch.equal(frames[0].T_wc, before[0])
    assert not torch.equal(frames[2].T_wc, before[2])
    assert torch.allclose(frames[3].T_wc, pose.compose(frames[2].T_wc, rel), atol=1e-5)

"""The mapper's half of the pipeline without mapping work: the final trajectory re-anchors
every other frame to its keyframe."""

import pytest
import torch
from walls import CAM

from dimslam.common.config import PRESETS
from dimslam.common.geometry import pose
from dimslam.common.map.mesh import EmptyMeshError
from dimslam.common.optim.window import FrameState
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

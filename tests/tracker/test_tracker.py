"""Tracker pieces that need no trained map: the motion model and the keyframe rules."""

import torch
from walls import CAM, textured_wall_image, wall

from dimslam.common.geometry import pose
from dimslam.common.map.render import RenderConfig
from dimslam.common.optim.objective import LossConfig
from dimslam.common.optim.window import FrameState, constant_velocity
from dimslam.tracker.tracker import Tracker, TrackerConfig


def frame_at(T: torch.Tensor) -> FrameState:
    return FrameState(0, 0.0, torch.zeros(48, 64, 3), T)


def tracker(**kw) -> Tracker:
    cfg = TrackerConfig(overlap_pixels=400, **kw)
    return Tracker(cfg, LossConfig(), RenderConfig(far=4.0), CAM, torch.Generator().manual_seed(0))


def test_constant_velocity_repeats_the_last_motion():
    step = pose.exp_se3(torch.tensor([0.01, 0.0, 0.02, 0.0, 0.01, 0.0]))
    before = pose.exp_se3(torch.tensor([0.3, -0.1, 0.2, 0.1, 0.0, -0.2]))
    previous = before @ step
    assert torch.allclose(constant_velocity(previous, before), previous @ step, atol=1e-6)


def test_keyframe_by_flow_and_by_lost_overlap():
    kf = frame_at(torch.eye(4))
    t = tracker(keyframe_flow_px=10.0, keyframe_overlap=0.85)
    assert not t.is_keyframe(wall, frame_at(torch.eye(4)), kf)
    # 20 cm sideways at 2 m: 5 px of flow, 92% overlap -> not yet.
    side = pose.make_pose(torch.eye(3), torch.tensor([0.2, 0.0, 0.0]))
    assert not t.is_keyframe(wall, frame_at(side), kf)
    # 60 cm: 15 px of flow -> keyframe by flow.
    far = pose.make_pose(torch.eye(3), torch.tensor([0.6, 0.0, 0.0]))
    assert t.is_keyframe(wall, frame_at(far), kf)
    # Backing away 1 m: most of the new, wider view falls outside the keyframe (overlap about
    # (2/3)^2) while the flow stays under the threshold: a keyframe by the overlap rule only.
    back = pose.make_pose(torch.eye(3), torch.tensor([0.0, 0.0, -1.0]))
    assert tracker(keyframe_flow_px=100.0, keyframe_overlap=0.85).is_keyframe(
        wall, frame_at(back), kf
    )
    assert not tracker(keyframe_flow_px=100.0, keyframe_overlap=0.0).is_keyframe(
        wall, frame_at(back), kf
    )


def test_tracking_recovers_a_pose_from_fixed_frames():
    """The newest frame starts 2 cm and 1 degree off; warping the fixed frame's patches at the
    map's depth into it brings it back."""
    source = pose.exp_se3(torch.tensor([0.02, -0.01, 0.0, 0.0, 0.01, 0.0]))
    truth = pose.exp_se3(torch.tensor([0.08, 0.03, 0.05, 0.02, -0.03, 0.01]))
    guess = pose.retract(truth, torch.tensor([0.015, -0.01, 0.01, 0.01, -0.008, 0.005]))
    fixed = FrameState(0, 0.0, textured_wall_image(source), source, keyframe=True)
    newest = FrameState(1, 0.1, textured_wall_image(truth), guess)

    def error(T: torch.Tensor) -> float:
        return float(pose.log_se3(pose.compose(pose.invert(truth), T)).norm())

    before = error(newest.T_wc)
    result = tracker(pixels=400, iters=60, pose_lr=3e-3, optimize_last=1).track(
        wall, [fixed, newest], []
    )
    assert result.window == (0, 1) and result.stats.iterations == 60
    assert torch.allclose(fixed.T_wc, source, atol=1e-6)  # the fixed frame stays put
    assert error(newest.T_wc) < 0.2 * before

"""The tracker's half of the pipeline without a map: collecting, batching, motion guesses,
and the mapper's refined poses coming back."""

import math
from dataclasses import replace

import pytest
import torch
from walls import CAM, textured_wall_image, wall

from dimslam.common.config import PRESETS
from dimslam.common.geometry import pose
from dimslam.common.optim.window import FrameState
from dimslam.tracker.frontend import FrontEnd


def front() -> FrontEnd:
    return FrontEnd(PRESETS["tiny"], CAM, torch.Generator().manual_seed(0))


def moved(x: float) -> torch.Tensor:
    return pose.make_pose(torch.eye(3), torch.tensor([x, 0.0, 0.0]))


def test_collect_hands_over_the_init_frames_once_complete():
    f = front()
    rgb = torch.zeros(CAM.height, CAM.width, 3)
    n = f.cfg.mapper.init_frames
    assert not any(f.collect(i, i / 30, rgb) for i in range(n - 1))
    assert f.pending == []
    assert f.collect(n - 1, 1.0, rgb)
    batch = f.take_batch()
    assert [s.index for s in batch] == list(range(n)) and f.pending == []
    assert all(torch.equal(s.T_wc, torch.eye(4)) for s in batch)


def test_a_batch_is_due_every_few_frames():
    f = front()
    every = f.cfg.mapper.every
    for i in range(11, 11 + 2 * every):
        f.pending.append(FrameState(i, i / 30, None, torch.eye(4)))
        due = f.batch_due()
        assert due == (i % every == 0), i
        if due:
            assert f.take_batch()[-1].index == i
    # Frames numbered off the rhythm (a continued map) still go after `every` frames.
    f.pending = [FrameState(i, 0.0, None, torch.eye(4)) for i in (101, 102, 103, 104)]
    assert not f.batch_due()
    f.pending.append(FrameState(106, 0.0, None, torch.eye(4)))
    assert f.batch_due()


def test_a_loss_hands_over_what_was_tracked_at_once():
    """A frame lost where the camera ran ahead of the map: the frames tracked before it go
    to the mapper at once, not when the batch would have been complete."""
    f = front()
    f.pending = [FrameState(i, 0.0, None, torch.eye(4)) for i in (11, 12)]
    assert not f.batch_due()  # tracking: the batch is not complete
    f.gap = 1  # the next frame was lost
    assert f.batch_due()
    assert [s.index for s in f.take_batch()] == [11, 12]
    assert not f.batch_due()  # still lost, nothing tracked since


def test_guess_carries_the_motion_on_but_not_across_a_long_gap():
    f = front()
    f.frames = [FrameState(0, 0.0, None, moved(0.0)), FrameState(1, 0.0, None, moved(0.1))]
    assert torch.allclose(f.guess(2), moved(0.2), atol=1e-6)
    assert torch.allclose(f.guess(4), moved(0.4), atol=1e-6)  # 2 frames dropped in between
    assert torch.allclose(f.guess(9), moved(0.1))  # a long gap: no velocity over it
    f.frames[-1].index = 2  # a frame dropped between the last two: 0.05 per frame
    assert torch.allclose(f.guess(4), moved(0.2), atol=1e-6)
    f.frames[-1].index = 5  # the last two frames too far apart: no velocity
    assert torch.allclose(f.guess(6), moved(0.1))
    f.next_guess = moved(1.0)  # a continued map's last pose wins, once
    assert torch.allclose(f.guess(6), moved(1.0))
    assert f.next_guess is None


def test_guesses_follow_where_the_solves_of_lost_frames_ended():
    f = front()
    f.frames = [FrameState(0, 0.0, None, moved(0.0)), FrameState(1, 0.0, None, moved(0.1))]
    f.followed = [(2, moved(0.15))]  # frame 2 lost; its solve ended 5 cm short of the motion
    assert torch.allclose(f.guess(3), moved(0.2), atol=1e-6)
    f.followed.append((3, moved(0.3)))
    assert torch.allclose(f.guess(4), moved(0.45), atol=1e-6)
    assert torch.allclose(f.extrapolate(6, 30), moved(0.75), atol=1e-6)


def test_refined_poses_move_the_later_frames_with_them():
    f = front()
    f.frames = [FrameState(i, 0.0, None, moved(0.1 * i)) for i in range(4)]
    # The mapper refined frames 0 and 1 (frame 1 moved 5 cm) and made frame 1 a keyframe.
    f.apply_poses({0: moved(0.0), 1: moved(0.15)}, keyframes=[1])
    assert f.frames[1].keyframe and not f.frames[2].keyframe
    xs = [float(s.T_wc[0, 3]) for s in f.frames]
    assert xs == pytest.approx([0.0, 0.15, 0.25, 0.35], abs=1e-6)


def test_the_first_frames_are_tracked_against_the_initialization_s_newest_frame_too():
    """While frame 0 is the only keyframe, the newest frame the initialization mapped is a
    reference as well; a keyframe of the tracker's own ends it (`tracker.init_reference`)."""
    f = front()
    rgb = torch.zeros(CAM.height, CAM.width, 3)
    n = f.cfg.mapper.init_frames
    for i in range(n):
        f.collect(i, i / 30, rgb)
    f.take_batch()
    f.frames[0].keyframe = True
    f.frames.append(FrameState(n, n / 30, rgb, torch.eye(4)))  # the frame being tracked
    assert [k.index for k in f._references(f.keyframes)] == [0, n - 1]
    f.frames[-1].keyframe = True  # it became a keyframe: tracked from here on as usual
    f.frames.append(FrameState(n + 1, (n + 1) / 30, rgb, torch.eye(4)))
    assert [k.index for k in f._references(f.keyframes)] == [0, n]
    cfg = f.cfg
    plain = FrontEnd(
        replace(cfg, tracker=replace(cfg.tracker, init_reference=False)),
        CAM,
        torch.Generator().manual_seed(0),
    )
    plain.frames = list(f.frames[: n + 1])
    plain.frames[n].keyframe = False
    plain.init_last = n - 1
    assert [k.index for k in plain._references(plain.keyframes)] == [0]


def test_a_frame_solved_far_from_its_guess_is_solved_again_from_it_by_the_window_objective():
    """`tracker.window_refine_deg`: a frame whose direct solve turned it more than that from
    its motion guess takes the window objective's end from the guess; above the turn the
    direct solve's pose stays, bit for bit as without the option."""
    truth = [pose.exp_se3(torch.tensor([0.02 * i, 0.0, 0.0, 0.0, 0.0, 0.0])) for i in range(4)]
    # The frames before it carry a turn on that the camera does not make: the guess is 1.7
    # degrees off in rotation, where the images pull the solve.
    turn = [pose.exp_se3(torch.tensor([0.0, 0.0, 0.0, 0.0, 0.015 * i, 0.0])) for i in range(4)]
    ends = {}
    for limit in (0.0, 180.0, 0.5):
        cfg = PRESETS["tiny"]
        cfg = replace(cfg, tracker=replace(cfg.tracker, window_refine_deg=limit))
        f = FrontEnd(cfg, CAM, torch.Generator().manual_seed(0))
        for i in range(3):
            T = pose.compose(truth[i], turn[i])
            f.frames.append(FrameState(i, i / 30, textured_wall_image(truth[i]), T, i == 0))
        f.frames[0].T_wc = truth[0]
        f.map_changed(wall, version=1)
        guess = f.guess(3)
        state = f.track(wall, 3, 0.1, textured_wall_image(truth[3]))
        assert state is not None
        turned = pose.angle_between(guess, state.T_wc)
        ends[limit] = (state.T_wc.clone(), float(turned))
        assert f.refined == ([3] if limit == 0.5 else [])
    direct, refined = ends[180.0], ends[0.5]
    assert torch.equal(direct[0], ends[0.0][0])  # as without the option
    assert direct[1] > math.radians(0.5)  # the direct solve left the guess by more
    assert not torch.equal(refined[0], direct[0])  # so the frame was solved again
    assert refined[1] < direct[1]  # from the guess, by a cost that holds nearer to it


def test_a_turn_the_images_see_is_kept_where_only_hidden_turns_are_solved_again():
    """`tracker.window_refine_seen`: a frame that leaves a wrong guess by a turn the images
    see (a hand-held jerk) keeps the direct solve's end, unless the frame before it was
    solved again (a slide goes on); a departure whose translation hides its turn from the
    images (a narrow view's turn-or-slide) measures near 0."""
    truth = [pose.exp_se3(torch.tensor([0.02 * i, 0.0, 0.0, 0.0, 0.0, 0.0])) for i in range(4)]
    turn = pose.exp_se3(torch.tensor([0.0, 0.0, 0.0, 0.0, 0.03, 0.0]))
    # The wall is 2 ahead: turning by a about y and stepping -2a along x keeps its centre.
    slide = pose.make_pose(turn[:3, :3], torch.tensor([-0.06, 0.0, 0.0]))
    for seen, before, refined in ((0.0, [], [3]), (0.5, [], []), (0.5, [2], [2, 3])):
        cfg = PRESETS["tiny"]
        tracking = replace(cfg.tracker, window_refine_deg=0.5, window_refine_seen=seen)
        f = FrontEnd(replace(cfg, tracker=tracking), CAM, torch.Generator().manual_seed(0))
        for i in range(3):
            f.frames.append(FrameState(i, i / 30, textured_wall_image(truth[i]), truth[i], i == 0))
        f.map_changed(wall, version=1)
        f.refined = list(before)
        f.next_guess = pose.compose(truth[3], turn)
        state = f.track(wall, 3, 0.1, textured_wall_image(truth[3]))
        assert state is not None and f.refined == refined
    seen_turn = f._turn_seen(truth[3], pose.compose(truth[3], turn), f.keyframes)
    seen_slide = f._turn_seen(truth[3], pose.compose(truth[3], slide), f.keyframes)
    assert seen_turn > 0.9 and seen_slide < 0.2


def test_a_live_stream_renders_a_new_map_s_newest_keyframe_at_once():
    """`go_live` with `tracker.live_map_renders`: a new map re-renders that many keyframes
    at once, where offline every one of the `references` newest is."""
    cfg = PRESETS["tiny"]
    cfg = replace(cfg, tracker=replace(cfg.tracker, references=3, live_map_renders=1))
    f = FrontEnd(cfg, CAM, torch.Generator().manual_seed(0))
    for i in range(3):
        T = pose.exp_se3(torch.tensor([0.02 * i, 0.0, 0.0, 0.0, 0.0, 0.0]))
        f.frames.append(FrameState(i, i / 30, textured_wall_image(T), T, keyframe=True))
    assert f.map_changed(wall, version=1) == 3
    f.go_live()
    assert f.map_changed(wall, version=2) == 1

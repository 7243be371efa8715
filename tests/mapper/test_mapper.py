"""Mapper choices that need no trained map: which poses a mapping round moves."""

import torch
from walls import CAM, SMALL_MAP, small_mapper, textured_wall_image

from dimslam.common.geometry import pose
from dimslam.common.map.render import RenderConfig, render_pixels
from dimslam.common.optim.window import FrameState
from dimslam.mapper.mapper import Mapper, MapperConfig


def mapper(**kw) -> Mapper:
    return small_mapper(MapperConfig(**kw))


def test_anchored_keyframes_keep_their_poses_while_recent_frames_move():
    poses = [pose.make_pose(torch.eye(3), torch.tensor([0.05 * i, 0.0, 0.0])) for i in range(6)]
    for move in (False, True):
        torch.manual_seed(0)  # the grids' initialization: the same map both ways
        # Indices from 1: frame 0, the gauge, never moves either way.
        frames = [
            FrameState(i + 1, i / 30, textured_wall_image(T), T.clone(), keyframe=i < 3)
            for i, T in enumerate(poses)
        ]
        m = mapper(pixels=64, iters=3, window_keyframes=3, move_keyframes=move)
        done = m.map(frames[3:], frames[:3])
        older = [f for f in frames[:3] if f.index in done.window]
        assert older, "no older keyframe joined the window"
        assert all(f.index in done.window for f in frames[3:])
        moved = [not torch.equal(f.T_wc, T) for f, T in zip(frames, poses, strict=True)]
        assert all(moved[3:])
        assert [moved[f.index - 1] for f in older] == [move] * len(older)


def test_kept_adam_state_carries_over_between_rounds():
    """With `keep_adam` every round steps the same Adam (its step count adds up over two
    rounds); without it, each round gets a new one and the ones handed out stay unused."""
    poses = [pose.make_pose(torch.eye(3), torch.tensor([0.05 * i, 0.0, 0.0])) for i in range(4)]
    for keep in (False, True):
        frames = [
            FrameState(i + 1, i / 30, textured_wall_image(T), T.clone(), keyframe=True)
            for i, T in enumerate(poses)
        ]
        m = mapper(pixels=64, iters=3, window_keyframes=2, keep_adam=keep)
        optimizers = [m._round_optimizer() for _ in range(2)]
        assert (optimizers[0] is optimizers[1]) == keep
        m.map(frames[2:], frames[:2])
        m.map(frames[2:], frames[:2])
        grid = m.field.grid_parameters()[-1]
        steps = [float(o.state[grid]["step"]) for o in optimizers if grid in o.state]
        if keep:
            assert steps == [6.0, 6.0]
        else:
            assert steps == []


def test_global_refinement_moves_keyframes_anywhere_on_the_path_but_frame_0():
    """`post_optimize(poses=True)` (a global refinement round) moves the poses of the
    keyframes in its windows, whichever they are, except frame 0's; map-only it moves none."""
    poses = [pose.make_pose(torch.eye(3), torch.tensor([0.05 * i, 0.0, 0.0])) for i in range(5)]
    for poses_too in (False, True):
        torch.manual_seed(0)
        frames = [
            FrameState(i, i / 30, textured_wall_image(T), T.clone(), keyframe=True)
            for i, T in enumerate(poses)
        ]
        m = mapper(pixels=64)
        m.post_optimize(frames, iters=4, chunk=2, anchors=[frames[0], frames[3]], poses=poses_too)
        moved = [not torch.equal(f.T_wc, T) for f, T in zip(frames, poses, strict=True)]
        assert moved == [False] + [poses_too] * 4


def test_the_initial_plane_stops_the_rays_when_depth_is_normalized():
    """A normalized depth is met at the gauge by rays that barely stop; the plane the map
    starts from stops them unless `prior_stop` is off."""
    render = RenderConfig(
        n_stratified=16, n_importance=8, importance_rounds=1, far=6.0, normalize_depth=True
    )
    uv = torch.rand(200, 2, generator=torch.Generator().manual_seed(1))
    uv = uv * torch.tensor([CAM.width - 1.0, CAM.height - 1.0])
    opacity = {}
    for stop in (True, False):
        torch.manual_seed(0)
        m = small_mapper(MapperConfig(prior_iters=60, prior_stop=stop), SMALL_MAP, render)
        m.fit_prior(FrameState(0, 0.0, None, torch.eye(4)))
        with torch.no_grad():
            out = render_pixels(m.field, CAM, uv, torch.eye(4), render)
        assert torch.allclose(out.depth.median(), torch.tensor(m.cfg.gauge_depth), atol=0.1)
        opacity[stop] = out.opacity.min().item()
    assert opacity[True] > 0.9
    assert opacity[False] < 0.8


def test_frame_0_moves_in_mapping_and_global_rounds_unless_held():
    """`hold_first` (the default) keeps frame 0's pose in mapping and global rounds; without
    it frame 0 moves as any keyframe of the window."""
    poses = [pose.make_pose(torch.eye(3), torch.tensor([0.05 * i, 0.0, 0.0])) for i in range(5)]

    def frames() -> list[FrameState]:
        return [
            FrameState(i, i / 30, textured_wall_image(T), T.clone(), keyframe=i < 2)
            for i, T in enumerate(poses)
        ]

    for hold in (True, False):
        torch.manual_seed(0)
        mapped = frames()
        m = mapper(pixels=64, iters=3, window_keyframes=2, hold_first=hold)
        done = m.map(mapped[2:], mapped[:2])
        assert 0 in done.window
        assert torch.equal(mapped[0].T_wc, poses[0]) == hold
        assert all(not torch.equal(f.T_wc, T) for f, T in zip(mapped[1:], poses[1:], strict=True))

        torch.manual_seed(0)
        refined = frames()
        m = mapper(pixels=64, hold_first=hold)
        m.post_optimize(refined, iters=2, chunk=2, anchors=[refined[0]], poses=True)
        assert torch.equal(refined[0].T_wc, poses[0]) == hold

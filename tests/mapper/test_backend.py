"""The mapper's half of the pipeline: the final trajectory re-anchors every other frame to its
keyframe, and follows the keyframes a loop correction or a global refinement round moves."""

import logging

import pytest
import torch
from walls import CAM, textured_wall_image, wall

from dimslam.common.config import PRESETS
from dimslam.common.eval.evaluation import umeyama
from dimslam.common.geometry import pose, sim3
from dimslam.common.io.datasets import open_dataset
from dimslam.common.io.synth import write_sequence
from dimslam.common.map.mesh import EmptyMeshError
from dimslam.common.optim.window import FrameState, image_tensor
from dimslam.common.options import apply_overrides
from dimslam.mapper.backend import BackEnd
from dimslam.tracker.tracker import Tracker


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


def test_the_initialization_frames_become_keyframes_by_the_tracker_rule():
    """With `mapper.init_keyframes`, the initialization's frames become keyframes where the
    flow from the last one passes `keyframe_flow_px`: a camera sliding 9 cm a frame before a
    wall 2 m away moves its pixels 2.25 px a frame, 10 px in 4.4 frames; the frames between
    them anchor to the keyframe before."""
    settings = {"tracker.keyframe_flow_px": "10", "tracker.keyframe_overlap": "0"}
    cfg = apply_overrides(PRESETS["tiny"], {"mapper.init_keyframes": "true", **settings})
    back = BackEnd(cfg, CAM, torch.device("cpu"), torch.Generator())
    back.mapper.field = wall  # the map the initialization would have made
    frames = [FrameState(i, i / 30, None, moved(0.09 * i)) for i in range(13)]
    frames[0].keyframe = True  # as `Mapper.initialize` leaves it
    back.add(frames)
    for f in back._init_marked():
        f.keyframe = True
    assert [f.index for f in back.keyframes] == [0, 5, 10]
    back._anchor(frames)
    assert {i: kf.index for i, (kf, _) in back.anchors.items()} == {
        i: 5 * (i // 5) for i in range(13) if i % 5
    }


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


def test_a_keyframe_takes_the_refined_end_from_the_motion_where_the_two_ends_differ():
    """A keyframe is refined by the window objective from its tracked pose and from the motion
    of the frames before it carried on. Where the two ends lie apart (here a few steps leave
    them apart, as two minima would) and the motion's scores lower, the keyframe takes it, the
    frame after it keeps its motion relative to it and the frames before it stay; where the
    ends agree the tracked pose stays as it was."""
    cfg = apply_overrides(
        PRESETS["tiny"],
        {
            "mapper.refine_keyframes": "5",
            "mapper.refine_apart_deg": "0.2",
            "tracker.pixels": "400",
            "tracker.pose_lr": "1e-3",
        },
    )
    back = BackEnd(cfg, CAM, torch.device("cpu"), torch.Generator().manual_seed(0))
    back.mapper.field = wall  # an exact map
    truth = [
        pose.exp_se3(torch.tensor([0.02 * i, 0.01 * i, 0.01 * i, 0.0, 0.005 * i, 0.0]))
        for i in range(6)
    ]
    off = pose.exp_se3(torch.tensor([0.015, -0.01, 0.01, 0.01, -0.008, 0.005]))
    frames = [
        FrameState(i, i / 30, textured_wall_image(T), T.clone(), keyframe=i in (0, 4))
        for i, T in enumerate(truth)
    ]

    for k in (4, 5):  # tracked with the same error from frame 4 on
        frames[k].T_wc = pose.compose(
            truth[4], pose.compose(off, pose.compose(pose.invert(truth[4]), truth[k]))
        )
    back.add(frames)
    back.initialized = True

    def error(k: int) -> float:
        return float(pose.log_se3(pose.compose(pose.invert(truth[k]), frames[k].T_wc)).norm())

    before = error(4)
    relative = pose.compose(pose.invert(frames[4].T_wc), frames[5].T_wc)
    back._refine_keyframes(frames[3:])
    assert error(4) < 0.5 * before
    after = pose.compose(pose.invert(frames[4].T_wc), frames[5].T_wc)
    assert torch.allclose(after, relative, atol=1e-5)
    assert all(torch.allclose(frames[k].T_wc, truth[k], atol=1e-6) for k in range(4))
    # Tracked right, the two ends agree: the tracked pose stays exactly.
    for k in (4, 5):
        frames[k].T_wc = truth[k].clone()
    back._refine_keyframes(frames[3:])
    assert all(torch.equal(frames[k].T_wc, truth[k]) for k in (4, 5))
    # Ends apart but the tracked one scores lower: it stays (larger steps from a wrong motion).
    back.cfg = apply_overrides(cfg, {"mapper.refine_apart_deg": "0.0"})
    frames[3].T_wc = pose.compose(truth[3], pose.invert(off))  # the motion now points off
    back._refine_keyframes(frames[3:])
    assert all(torch.equal(frames[k].T_wc, truth[k]) for k in (4, 5))
    frames[3].T_wc = truth[3].clone()
    # One objective scores every end; the frame keeps its pose as given.
    refiner = Tracker(cfg.tracker, cfg.loss, cfg.render, CAM, torch.Generator().manual_seed(0))
    ends = refiner.refine(wall, frames[:5], [], 0, [truth[4], pose.compose(truth[4], off)])
    assert ends[0][1] < ends[1][1]
    assert torch.equal(frames[4].T_wc, truth[4])
    # Off: nothing moves.
    back.cfg = PRESETS["tiny"]
    kept = [f.T_wc.clone() for f in frames]
    back._refine_keyframes(frames[3:])
    assert all(torch.equal(f.T_wc, T) for f, T in zip(frames, kept, strict=True))


def _drifted(tmp_path, **settings: str):
    """The built-in scene's first 22 frames, keyframes every 3rd, tracked with each step 3 %
    shorter than the one before (a scale drift: the last is half its length), and a back end
    with the bundle adjustment (`settings` on top of the cpu preset)."""
    write_sequence(tmp_path / "seq", frames=22, width=320, height=240, noise=0.0)
    reader = open_dataset(tmp_path / "seq")
    cfg = apply_overrides(
        PRESETS["cpu"], {"bundle.enabled": "true", "bundle.refit_iters": "0", **settings}
    )
    back = BackEnd(cfg, reader.camera, torch.device("cpu"), torch.Generator())
    truth = torch.stack([torch.from_numpy(f.T_wc) for f in reader]).float()
    drifted = truth.clone()
    shrink = 0.97 ** torch.arange(1, len(truth))
    true_steps = truth[1:, :3, 3] - truth[:-1, :3, 3]
    drifted[1:, :3, 3] = truth[0, :3, 3] + (shrink[:, None] * true_steps).cumsum(0)
    frames = [
        FrameState(
            f.index, f.timestamp, image_tensor(f.rgb, "cpu"), drifted[f.index], f.index % 3 == 0
        )
        for f in reader
    ]
    return back, frames, truth, drifted


def _assert_one_scale(back, truth, drifted):
    """The keyframes' steps back at one scale, and the frames between them too."""

    def steps(T):
        return (T[3::3, :3, 3] - T[:-3:3, :3, 3]).norm(dim=1)

    final = torch.from_numpy(back.trajectory().poses).float()
    ratio = steps(final) / steps(truth)
    drift = steps(drifted) / steps(truth)
    assert drift.max() / drift.min() > 1.5  # what the adjustment starts from
    assert ratio.max() / ratio.min() < 1.05  # one scale along the whole path
    true_steps = (truth[1:, :3, 3] - truth[:-1, :3, 3]).norm(dim=1)
    every = (final[1:, :3, 3] - final[:-1, :3, 3]).norm(dim=1) / true_steps
    assert every.std() < 0.1 * every.mean()  # the frames between keyframes too


def test_the_feature_bundle_adjustment_undoes_a_scale_drift_and_the_frames_follow(tmp_path):
    back, frames, truth, drifted = _drifted(tmp_path)
    back.add(frames)
    back.initialized = True
    back._anchor(frames)
    back._describe(frames)
    back.adjust_keyframes()
    _assert_one_scale(back, truth, drifted)


@pytest.mark.parametrize("every", [True, False])
def test_every_frame_held_places_the_frames_between_keyframes(tmp_path, every):
    """`bundle.every_frame`: the flow is observed at every frame and the adjustment holds
    them all, ORB still describing the keyframes alone: frame 7 (between keyframes 6 and 9),
    tracked 1 cm off, comes back to the path, and the drift goes as with the keyframes
    alone. Without it frame 7 follows keyframe 6 with its error."""
    settings = {"bundle.every_frame": "true" if every else "false"}
    back, frames, truth, drifted = _drifted(tmp_path, **settings)
    frames[7].T_wc = frames[7].T_wc.clone()
    frames[7].T_wc[0, 3] += 0.01
    back.add(frames)
    back.initialized = True
    back._anchor(frames)
    back._describe(frames)
    back.adjust_keyframes()
    assert sorted(back.tracks.keyframes) == list(range(0, 22, 3))
    assert back.extra == ({i for i in range(22) if i % 3} if every else set())
    final = back.trajectory().poses
    fit = umeyama(final[:, :3, 3], truth[:, :3, 3].double().numpy())
    error = torch.from_numpy(fit.apply_poses(final)[:, :3, 3]) - truth[:, :3, 3].double()
    if every:  # 3 mm (the other frames 0.2-1 mm)
        _assert_one_scale(back, truth, drifted)
        assert float(error[7].norm()) < 0.005
    else:  # 12 mm
        assert float(error[7].norm()) > 0.009


@pytest.mark.parametrize("extra", [True, False])
def test_the_initialization_frames_the_rule_marks_join_the_adjustment(tmp_path, extra):
    """`bundle.init_frames`: frames 3, 6 and 9 of the drifted path, not keyframes (the
    initialization left frame 0 the only one before 12), join the adjustment, and the frames
    after each follow it: the first 12 frames come back to the path's one scale. They stay
    what they were: not keyframes, anchored to keyframe 0 for later corrections. Without
    them, frames 1-11 are carried rigidly from frame 0 and keep the drift."""
    back, frames, truth, drifted = _drifted(tmp_path)
    for f in frames[3:12:3]:
        f.keyframe = False
    back.add(frames)
    back.initialized = True
    back._anchor(frames)
    back.extra = {3, 6, 9} if extra else set()
    back._describe(frames)
    back.adjust_keyframes()
    assert [f.index for f in back.keyframes] == [0, 12, 15, 18, 21]
    assert {i: kf.index for i, (kf, _) in back.anchors.items() if i < 12} == {
        i: 0 for i in range(1, 12)
    }
    final = torch.from_numpy(back.trajectory().poses).float()
    steps = (final[3::3, :3, 3] - final[:-3:3, :3, 3]).norm(dim=1)
    ratio = steps / (truth[3::3, :3, 3] - truth[:-3:3, :3, 3]).norm(dim=1)
    if extra:
        assert ratio.max() / ratio.min() < 1.05
    else:
        assert ratio[:4].max() / ratio[:4].min() > 1.2  # frames 0-12: the drift kept


def test_a_slide_the_features_contradict_is_adjusted_from_the_motion_before_it(tmp_path, caplog):
    """The built-in scene's first 40 frames, keyframes every 2nd, tracked from frame 24 on
    moving backwards (each step's translation turned about): with `bundle.slides` the
    features' matrices point against it, and the adjusted path goes forwards again; without
    it the adjustment keeps the slide."""
    write_sequence(tmp_path / "seq", frames=40, width=320, height=240, noise=0.0)
    reader = open_dataset(tmp_path / "seq")
    truth = torch.stack([torch.from_numpy(f.T_wc) for f in reader]).double()
    tracked = truth.clone()
    for i in range(24, len(truth)):
        step = pose.invert(truth[i - 1]) @ truth[i]
        step[:3, 3] = -step[:3, 3]
        tracked[i] = tracked[i - 1] @ step

    def adjusted(slides: str) -> torch.Tensor:
        cfg = apply_overrides(
            PRESETS["cpu"],
            {"bundle.enabled": "true", "bundle.refit_iters": "0", "bundle.slides": slides},
        )
        back = BackEnd(cfg, reader.camera, torch.device("cpu"), torch.Generator())
        frames = [
            FrameState(
                f.index,
                f.timestamp,
                image_tensor(f.rgb, "cpu"),
                tracked[f.index].float(),
                f.index % 2 == 0,
            )
            for f in reader
        ]
        back.add(frames)
        back.initialized = True
        back._anchor(frames)
        back._describe(frames)
        back.adjust_keyframes()
        return torch.from_numpy(back.trajectory().poses)

    def tail_error(T: torch.Tensor) -> float:
        """The last frames' error after the path's similarity to the truth (cm)."""
        fit = umeyama(T[:, :3, 3].numpy(), truth[:, :3, 3].numpy())
        placed = torch.from_numpy(fit.apply_poses(T.numpy()))
        return 100 * float((placed[30:, :3, 3] - truth[30:, :3, 3]).norm(dim=1).max())

    with caplog.at_level(logging.INFO, logger="dimslam.mapper.backend"):
        repaired = adjusted("true")
    assert "the features contradict the tracked motion" in caplog.text
    # the cpu preset's: the steps' turns and directions as one variance component
    assert "the prior's turns and directions weighed by the residuals" in caplog.text
    assert tail_error(repaired) < 0.2 * tail_error(adjusted("false"))


def test_frames_a_round_did_not_map_follow_their_keyframes(tmp_path):
    """A mapper that fell behind (17 frames in one hand-over) maps only the newest
    `mapper.every`, and a stop leaves the last frames without a round: all of them still
    anchor to their keyframes, so that a later correction of a keyframe carries them."""
    back, frames, _, _ = _drifted(tmp_path, **{"mapper.iters": "1", "mapper.pose_lr": "0"})
    back.add(frames[:17])
    back.initialized = True  # as after the initialization on frames before these
    result = back.step()
    assert result.window[-5:] == (12, 13, 14, 15, 16)
    assert set(back.anchors) == {i for i in range(17) if i % 3}
    back.add(frames[17:])  # handed over at a stop: no round
    back.finish()
    assert set(back.anchors) == {i for i in range(22) if i % 3}
    before = torch.from_numpy(back.trajectory().poses)
    frames[6].T_wc = pose.compose(moved(0.1), frames[6].T_wc)  # a correction moves keyframe 6
    frames[18].T_wc = pose.compose(moved(0.1), frames[18].T_wc)  # and keyframe 18
    shift = torch.from_numpy(back.trajectory().poses)[:, 0, 3] - before[:, 0, 3]
    assert shift[[6, 7, 8, 18, 19, 20]].tolist() == pytest.approx([0.1] * 6, abs=1e-5)
    assert shift[[5, 9, 17, 21]].abs().max() < 1e-6


def test_a_round_on_live_frames_is_short_and_refines_nothing_globally():
    """Frames from a live camera get `mapper.live_iters` iterations, no global refinement
    round and no feature description, so that the map keeps up with the camera; the same
    round offline gets `iters` and describes its keyframes."""
    cfg = apply_overrides(
        PRESETS["tiny"],
        {
            "bundle.enabled": "true",
            "mapper.iters": "3",
            "mapper.live_iters": "1",
            "mapper.global_every": "1",
            "mapper.global_iters": "2",
            "mapper.pixels": "64",
        },
    )
    back = BackEnd(cfg, CAM, torch.device("cpu"), torch.Generator().manual_seed(0))
    frames = [
        FrameState(i, i / 30, textured_wall_image(moved(0.05 * i)), moved(0.05 * i), i % 2 == 0)
        for i in range(6)
    ]
    back.add(frames)
    back.initialized = True  # as after the initialization
    back.rounds = 1  # a global round is due after every mapping round
    assert back.step(live=True).stats.iterations == 1
    assert "global" not in back.phase_seconds
    assert back.tracks is not None and not back.tracks.keyframes
    assert back.step().stats.iterations == 3
    assert "global" in back.phase_seconds
    assert back.tracks.keyframes  # the offline round's keyframes are described
    # Off (0): a live round is an offline one.
    back.cfg = apply_overrides(cfg, {"mapper.live_iters": "0"})
    back.mapper.cfg = back.cfg.mapper
    assert back.step(live=True).stats.iterations == 3


@pytest.mark.parametrize("live", [True, False])
def test_a_live_run_describes_its_keyframes_at_the_end_and_adjusts_them(tmp_path, live):
    """`bundle.live`: live rounds describe no ORB features but follow the flow through
    their frames, observed at every one; the end of the run describes every keyframe from
    the images a live mapper keeps (the keyframes' alone here) and adjusts every frame the
    flow observed with the live path's prior: the drifted path comes back to one scale,
    frame by frame. Off, the adjustment is skipped (too few keyframes described) and every
    pose stays as tracked."""
    back, frames, truth, drifted = _drifted(
        tmp_path, **{"bundle.live": str(live).lower(), "bundle.flow": "300"}
    )
    back.add(frames)
    back.initialized = True
    back.short_rounds = 3
    if live:
        back._observe_live(frames)  # what the live rounds did
        assert back.extra == {f.index for f in frames if not f.keyframe}
    for f in frames:
        if not f.keyframe:
            f.rgb = None  # released, as after a live round
    assert back.finish()
    described = sorted(back.tracks.keyframes)
    if live:
        assert described == [f.index for f in frames if f.keyframe]
        _assert_one_scale(back, truth, drifted)
        final = torch.from_numpy(back.trajectory().poses).float()
        steps = (final[1:, :3, 3] - final[:-1, :3, 3]).norm(dim=1)
        ratio = steps / (truth[1:, :3, 3] - truth[:-1, :3, 3]).norm(dim=1)
        # Every frame's step at one scale (1.11; 1.54 with the keyframes alone held).
        assert float(ratio.max() / ratio.min()) < 1.2
    else:
        assert described == []
        assert all(torch.equal(f.T_wc, drifted[f.index]) for f in frames)


def test_keyframes_the_features_never_described_follow_the_adjustment(tmp_path):
    """A mapper behind a live camera describes only the keyframes of its rounds: one between
    two described keyframes moves as they did, interpolated by its place between them, one
    after the last described moves with it, so that the adjusted path stays in one piece."""
    back, frames, truth, drifted = _drifted(tmp_path)
    back.add(frames)
    back.initialized = True
    back._anchor(frames)
    back._describe([f for f in frames if f.index % 6 == 0])  # keyframes 0, 6, 12, 18
    before = {f.index: f.T_wc.clone() for f in frames if f.keyframe}
    back.adjust_keyframes()
    # Keyframe 21, after the last described, keeps its pose relative to 18 (offset scaled).
    rel_before = pose.compose(pose.invert(before[18]), before[21])
    rel_after = pose.compose(pose.invert(frames[18].T_wc), frames[21].T_wc)
    assert torch.allclose(rel_after[:3, :3], rel_before[:3, :3], atol=1e-5)
    scale = rel_after[:3, 3].norm() / rel_before[:3, 3].norm()
    assert torch.allclose(rel_after[:3, 3], scale * rel_before[:3, 3], atol=1e-5)

    def ratios(T, every):  # each step between every `every`-th frame, against the truth
        steps = (T[every::every, :3, 3] - T[:-every:every, :3, 3]).norm(dim=1)
        return steps / (truth[every::every, :3, 3] - truth[:-every:every, :3, 3]).norm(dim=1)

    final = torch.from_numpy(back.trajectory().poses).float()
    spread = [float(r.max() / r.min()) for r in (ratios(final, 6), ratios(drifted, 6))]
    assert spread[0] < 1.05 < 1.3 < spread[1]  # the described keyframes at one scale
    # Every keyframe's step up to the last described one: at one scale within 15 %.
    steps, drifted_steps = ratios(final, 3)[:-1], ratios(drifted, 3)[:-1]
    assert (
        float(steps.max() / steps.min())
        < 1.15
        < 1.5
        < float(drifted_steps.max() / drifted_steps.min())
    )

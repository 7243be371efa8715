"""Loop closure on the built-in scene: keyframes round a loop with drift injected, real images."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from dimslam.common.geometry import sim3
from dimslam.common.io.synth import SynthScene, default_camera
from dimslam.common.map.render import RenderConfig
from dimslam.common.optim.window import FrameState
from dimslam.mapper.loop import LoopCloser, LoopConfig, covered, describe, match
from dimslam.tracker.tracker import TrackerConfig

FRAMES, EVERY = 150, 5
GAP = LoopConfig(min_gap=100)
"""The loop is 150 frames long: old keyframes are those 100 frames back or more."""
SHRINK, YAW = 0.985, math.radians(0.4)
"""Injected drift per keyframe: translations shrink by 1.5 % (the map's scale with them) and
the heading turns 0.4 degrees."""


@pytest.fixture(scope="module")
def loop_keyframes():
    """Keyframes every 5 frames of a 150-frame loop round the room (ground truth, images and
    depth) and a drifted estimate of them: `(truth, frames, scales, depths)`."""
    scene = SynthScene(0)
    camera = default_camera(160, 120)
    truth = scene.loop_path(FRAMES)[::EVERY]
    frames, scales, depths = [], [], []
    estimate = truth[0]
    turn = np.eye(4)
    turn[:3, :3] = [
        [math.cos(YAW), 0, math.sin(YAW)],
        [0, 1, 0],
        [-math.sin(YAW), 0, math.cos(YAW)],
    ]
    for k, T in enumerate(truth):
        if k:
            step = np.linalg.inv(truth[k - 1]) @ T
            step[:3, 3] *= SHRINK**k
            estimate = estimate @ turn @ step
        rgb, depth = scene.render(T, camera)
        frames.append(
            FrameState(
                k * EVERY,
                k / 6.0,
                torch.from_numpy(np.ascontiguousarray(rgb)).float(),
                torch.from_numpy(estimate).float(),
                keyframe=True,
            )
        )
        scales.append(SHRINK**k)
        depths.append(depth)
    return truth, frames, scales, depths, camera


def _closer(cfg: LoopConfig, camera) -> LoopCloser:
    return LoopCloser(cfg, camera, RenderConfig(), TrackerConfig(), 2.0, torch.device("cpu"))


def _depth_fn(frames, scales, depths):
    """The depth a drifted map would render: the true depth in the keyframe's local scale."""
    at = {f.index: k for k, f in enumerate(frames)}

    def depth(frame: FrameState, uv: np.ndarray) -> np.ndarray:
        k = at[frame.index]
        u, v = np.round(uv).astype(int).T
        return depths[k][v, u].astype(np.float64) * scales[k]

    return depth


def _error(a: np.ndarray, b: np.ndarray, truth_a: np.ndarray, truth_b: np.ndarray) -> float:
    """Translation error of `b` seen from `a` against the truth, metres."""
    rel = np.linalg.inv(a) @ b
    return float(np.linalg.norm(rel[:3, 3] - (np.linalg.inv(truth_a) @ truth_b)[:3, 3]))


def test_revisited_place_matches_and_a_distant_one_does_not(loop_keyframes):
    _, frames, _, _, _ = loop_keyframes
    codes = [describe(f.index, f.rgb, 800) for f in frames]
    assert min(len(c.points) for c in codes) > 100
    back = len(match(codes[-1], codes[0])[0])  # the end sees again what the start saw
    across = len(match(codes[-1], codes[len(codes) // 2])[0])  # the far side of the room
    assert back >= 40 and back > 4 * across, (back, across)


def test_loop_is_found_and_corrected(loop_keyframes):
    truth, frames, scales, depths, camera = loop_keyframes
    closer = _closer(GAP, camera)
    depth = _depth_fn(frames, scales, depths)
    for f in frames:
        closer.add(f, depth)
    # The first keyframe back at the start finds the loop; the next one confirms it.
    assert closer.detect(frames[-2], frames) is None and closer.last is not None
    loop = closer.detect(frames[-1], frames)
    assert loop is not None and loop.old <= 20, loop
    # The measured scale between the places is the drift injected between them.
    k_old = loop.old // EVERY
    assert float(sim3.scale_of(loop.S_old_new)) == pytest.approx(
        scales[k_old] / scales[-1], rel=0.03
    )
    assert not closer.agrees(loop)
    estimate = np.stack([f.T_wc.double().numpy() for f in frames])
    before = _error(estimate[k_old], estimate[-1], truth[k_old], truth[-1])
    result = closer.correct(frames, loop)
    corrected = np.stack([sim3.to_pose(n)[0].numpy() for n in result.nodes])
    after = _error(corrected[k_old], corrected[-1], truth[k_old], truth[-1])
    assert after <= before / 5, (before, after)
    # The whole path comes closer to the truth, not only the loop's two ends.
    drift = np.linalg.norm(estimate[:, :3, 3] - truth[:, :3, 3], axis=1).mean()
    fixed = np.linalg.norm(corrected[:, :3, 3] - truth[:, :3, 3], axis=1).mean()
    assert fixed < drift / 2, (drift, fixed)
    # Keyframe 0 holds the gauge.
    assert torch.allclose(result.nodes[0], sim3.from_pose(frames[0].T_wc.double()), atol=1e-9)
    # The scale drift is spread along the path: later keyframes grow back.
    grown = sim3.scale_of(result.nodes)
    assert float(grown[-1]) > float(grown[len(grown) // 2]) > 1.0


def test_no_loop_among_recent_keyframes(loop_keyframes):
    _, frames, scales, depths, camera = loop_keyframes
    closer = _closer(LoopConfig(min_gap=10_000), camera)
    depth = _depth_fn(frames, scales, depths)
    for f in frames:
        closer.add(f, depth)
    assert closer.detect(frames[-1], frames) is None


def test_consistent_poses_agree(loop_keyframes):
    """Undrifted keyframes: the loop is found and agrees with the poses (nothing to move)."""
    truth, frames, _, depths, camera = loop_keyframes
    exact = [
        FrameState(f.index, f.timestamp, f.rgb, torch.from_numpy(T).float(), keyframe=True)
        for f, T in zip(frames, truth, strict=True)
    ]
    closer = _closer(GAP, camera)
    for f in exact:
        closer.add(f, _depth_fn(exact, [1.0] * len(exact), depths))
    loop = closer.detect(exact[-1], exact)
    assert loop is not None and closer.agrees(loop), loop


def test_covered_share_of_the_image():
    camera = default_camera(160, 120)
    corners = np.array([[0, 0], [80, 0], [80, 60], [0, 60], [40, 30]], float)
    assert covered(corners, camera) == pytest.approx(0.25)
    assert covered(corners[:2], camera) == 0.0


def test_loop_seen_through_a_sliver_is_refused(loop_keyframes):
    """The new keyframe keeps only its features in a band 8 px wide: the PnP inliers cover
    under `min_area` of the image, and the loop they would measure is refused."""
    _, frames, scales, depths, camera = loop_keyframes
    depth = _depth_fn(frames, scales, depths)
    found = {}
    for min_area in (0.0, LoopConfig.min_area):
        closer = _closer(dataclasses.replace(GAP, min_inliers=12, min_area=min_area), camera)
        for f in frames:
            closer.add(f, depth)
        code = closer.codes[frames[-1].index]
        band = np.abs(code.points[:, 0] - camera.width / 2) < 4
        closer.codes[code.index] = dataclasses.replace(
            code,
            points=code.points[band],
            descriptors=code.descriptors[band],
            depth=code.depth[band],
        )
        found[min_area] = closer._find(frames[-1], frames)
    assert found[0.0] is not None and found[0.0].inliers >= 12, found
    assert found[LoopConfig.min_area] is None

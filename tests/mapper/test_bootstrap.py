"""Starting poses from tracked corners (`mapper/bootstrap.py`) on the built-in scene, and the
initialization that falls back on them when its own fit is poor."""

import logging

import cv2
import numpy as np
import pytest
import torch
from walls import SMALL_MAP, SMALL_RENDER

from dimslam.common.io.synth import SynthScene, default_camera
from dimslam.common.optim.objective import LossConfig
from dimslam.common.optim.window import FrameState
from dimslam.mapper.bootstrap import MIN_PARALLAX_DEG, bootstrap
from dimslam.mapper.mapper import Mapper, MapperConfig


@pytest.fixture(scope="module")
def fast_views():
    """13 views of the built-in room, every 3rd of its path: 4.4 cm and 1.6 degrees apart."""
    scene = SynthScene(0)
    camera = default_camera(320, 240)
    path = scene.path(39)[::3]
    images = [
        np.clip(scene.render(T, camera)[0] * 255 + 0.5, 0, 255).astype(np.uint8) for T in path
    ]
    return images, camera, [np.linalg.inv(path[0]) @ T for T in path]


def test_poses_from_corners_follow_a_fast_camera(fast_views):
    images, camera, truth = fast_views
    seed = bootstrap(images, camera.K, 2.0)
    assert seed is not None
    assert seed.pair[0] == 0 and seed.parallax_deg >= MIN_PARALLAX_DEG
    np.testing.assert_allclose(seed.poses[0], np.eye(4), atol=1e-9)
    turn = [
        np.degrees(np.linalg.norm(cv2.Rodrigues(P[:3, :3].T @ G[:3, :3])[0]))
        for P, G in zip(seed.poses, truth, strict=True)
    ]
    assert max(turn) < 1.5  # measured 0.8 (the path turns 19.7 degrees)
    # The scale is the gauge's, not the world's: compare after the best scale.
    est = seed.poses[:, :3, 3]
    true = np.array([G[:3, 3] for G in truth])
    scale = (est * true).sum() / (est * est).sum()
    path = np.linalg.norm(np.diff(true, axis=0), axis=1).sum()
    assert np.abs(est * scale - true).max() < 0.1 * path  # measured 2.0 cm of 53


def test_no_poses_without_parallax_or_texture(fast_views):
    images, camera, _ = fast_views
    assert bootstrap([images[0]] * 13, camera.K, 2.0) is None  # a camera standing still
    blank = np.full_like(images[0], 128)
    assert bootstrap([blank] * 13, camera.K, 2.0) is None


def _initialize(views, caplog, max_warp: float):
    images, camera, _ = views
    m = Mapper(
        MapperConfig(
            pixels=128,
            init_frames=8,
            init_grow_iters=4,
            init_iters=8,
            prior_iters=8,
            init_max_warp=max_warp,
        ),
        SMALL_MAP,
        LossConfig(patch_sizes=(1, 5), min_views=1, smooth_blocks=4),
        SMALL_RENDER,
        0.0,
        50,
        camera,
        torch.device("cpu"),
        torch.Generator().manual_seed(0),
    )
    frames = [
        FrameState(i, i / 10, torch.from_numpy(im).float() / 255, torch.eye(4))
        for i, im in enumerate(images[:8])
    ]
    with caplog.at_level(logging.INFO, logger="dimslam.mapper.mapper"):
        m.initialize(frames)
    return m, frames


def test_an_initialization_over_its_warp_limit_starts_again_and_keeps_the_better_fit(
    fast_views, caplog
):
    m, frames = _initialize(fast_views, caplog, 1e-6)
    restarted = [r for r in caplog.records if "starting again" in r.getMessage()]
    assert len(restarted) == 1
    first = restarted[0].args[0]
    outcome = [r for r in caplog.records if r.getMessage().startswith("restart ")]
    assert len(outcome) == 1
    second = outcome[0].args[0]
    # What is kept is what fits better, and the check measures the same again.
    assert m.check(frames) == pytest.approx(min(first, second))
    assert ("kept" in outcome[0].getMessage()) == (second < first)
    assert frames[0].keyframe and torch.equal(frames[0].T_wc, torch.eye(4))


def test_an_initialization_within_its_limit_is_not_repeated(fast_views, caplog):
    _initialize(fast_views, caplog, 0.0)
    assert not [r for r in caplog.records if "starting again" in r.getMessage()]

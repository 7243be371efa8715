"""Feature bundle adjustment of the keyframes: tracks, triangulation, the solver, the prior."""

import math

import numpy as np
import pytest
import torch
from repo import benchmark, usage_error

from dimslam.common.geometry import pose
from dimslam.common.io.datasets import open_dataset
from dimslam.common.io.synth import write_sequence
from dimslam.common.io.trajectory import Trajectory
from dimslam.mapper.backend import brought_back
from dimslam.mapper.bundle import (
    FLOW_REALIGN_WINDOW,
    FLOW_WINDOW,
    BundleConfig,
    Features,
    FeatureTracks,
    FlowTracks,
    Observations,
    _reduced,
    _schur_pairs,
    adjust,
    adjust_tracks,
    bundle_adjust,
    describe,
    feature_directions,
    grey_image,
    held_pair,
    links,
    observed,
    odometry_prior,
    prior_for,
    reprojection,
    slid_start,
    slides,
    triangulate,
    variance_factors,
)

K = torch.tensor([[260.0, 0, 160], [0, 260.0, 120], [0, 0, 1]], dtype=torch.float64)


def _scene(cameras=8, points=300, seed=0):
    """Cameras stepping sideways and turning a little, looking at points 2-4 units ahead;
    every camera sees every point (exact pixels)."""
    g = torch.Generator().manual_seed(seed)
    twists = torch.zeros(cameras, 6, dtype=torch.float64)
    twists[:, 0] = torch.arange(cameras) * 0.1
    twists[:, 4] = torch.arange(cameras) * 0.03
    T_wc = pose.exp_se3(twists)
    X = torch.rand(points, 3, generator=g, dtype=torch.float64) * torch.tensor([3.0, 2.0, 2.0])
    X = X + torch.tensor([-1.0, -1.0, 2.0])
    k = torch.arange(cameras).repeat_interleave(points)
    p = torch.arange(points).repeat(cameras)
    obs = Observations(k, p, torch.zeros(len(k), 2, dtype=torch.float64), torch.ones(len(k)))
    r, _ = reprojection(pose.invert(T_wc), X, K, obs)
    obs.uv = r  # residuals against (0, 0) are the pixels themselves
    return T_wc, X, obs


def _perturbed(T_wc, scale=0.01, seed=1, held=slice(0, 2)):
    noise = torch.randn(len(T_wc), 6, generator=torch.Generator().manual_seed(seed))
    noise = noise.double() * scale
    noise[held] = 0  # the two held poses fix the gauge and the scale
    return pose.exp_se3(noise) @ pose.invert(T_wc)


def test_triangulation_recovers_exact_points():
    T_wc, X, obs = _scene()
    assert torch.allclose(triangulate(pose.invert(T_wc), K, obs), X, atol=1e-6)


def test_bundle_adjustment_takes_perturbed_poses_back():
    T_wc, X, obs = _scene()
    T_cw = _perturbed(T_wc)
    start, _ = reprojection(T_cw, triangulate(T_cw, K, obs), K, obs)
    T_ba, X_ba, cost = bundle_adjust(T_cw, triangulate(T_cw, K, obs), K, obs, 2, 30)
    assert float(start.norm(dim=1).mean()) > 0.5  # the perturbation is seen
    assert cost < 1e-8
    assert torch.allclose(pose.invert(T_ba)[:, :3, 3], T_wc[:, :3, 3], atol=1e-6)
    assert torch.allclose(X_ba, X, atol=1e-6)


def test_outliers_are_judged_at_the_poses_and_left_out():
    T_wc, X, obs = _scene()
    wrong = torch.arange(0, len(obs.k), 37)  # every 37th observation 20 px off
    obs.uv[wrong] += 20.0
    result = adjust(T_wc, K, obs, 3.0, 20, None)
    assert result.points == X.shape[0] - len(torch.unique(obs.p[wrong]))
    assert torch.allclose(result.T_wc[:, :3, 3], T_wc[:, :3, 3], atol=1e-5)


def test_odometry_prior_frees_the_step_length_and_holds_its_direction():
    T_wc, _, _ = _scene()
    prior = odometry_prior(T_wc, 0.2, 0.02)
    assert float(prior(pose.invert(T_wc)).abs().max()) < 1e-9
    longer = T_wc.clone()
    longer[:, :3, 3] *= 1.5  # every step half as long again, same directions and turns
    assert float(prior(pose.invert(longer)).abs().max()) < 1e-9
    slid = T_wc.clone()
    slid[3:, 1, 3] += 0.05  # one step that also goes down
    assert float(prior(pose.invert(slid)).abs().max()) > 1.0


def test_the_adjustment_holds_any_pair_it_is_given():
    """Poses 4 and 5 held (a mask) instead of the first two: they stay, the rest come back."""
    T_wc, X, obs = _scene()
    T_cw = _perturbed(T_wc, held=slice(4, 6))
    held = torch.zeros(len(T_wc), dtype=torch.bool)
    held[4:6] = True
    T_ba, _, cost = bundle_adjust(T_cw, triangulate(T_cw, K, obs), K, obs, held, 30)
    assert torch.equal(T_ba[4:6], T_cw[4:6])
    assert cost < 1e-8
    assert torch.allclose(pose.invert(T_ba)[:, :3, 3], T_wc[:, :3, 3], atol=1e-6)


def test_the_gauge_is_the_first_pair_or_the_best_linked_one():
    _, _, obs = _scene(cameras=8, points=40)
    extra = torch.arange(40, 60)  # 20 more points that only keyframes 5 and 6 share
    k = torch.cat([obs.k, torch.full((20,), 5), torch.full((20,), 6)])
    p = torch.cat([obs.p, extra, extra])
    uv = torch.zeros(len(k), 2, dtype=torch.float64)
    linked = Observations(k, p, uv, torch.ones(len(k)))
    assert held_pair(linked, 8, "first").nonzero()[:, 0].tolist() == [0, 1]
    assert held_pair(linked, 8, "linked").nonzero()[:, 0].tolist() == [5, 6]
    # Not across a step the prior leaves free (a slide's guessed motion): the first of
    # the pairs left, all equally linked.
    free = torch.tensor([False] * 5 + [True, False])
    assert held_pair(linked, 8, "linked", free).nonzero()[:, 0].tolist() == [0, 1]
    with pytest.raises(ValueError, match="first or linked"):
        held_pair(linked, 8, "middle")


@pytest.mark.parametrize(("gauge", "held"), [("first", 0), ("linked", 4)])
def test_a_broken_first_pose_comes_back_where_the_best_linked_pair_is_held(gauge, held):
    """Pose 0 starts 5 cm off: holding it (the first pair) keeps it there; holding the pair
    that 20 more points link brings it back, and the adjustment says which pair it held."""
    T_wc, X, obs = _scene()
    more = torch.rand(20, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    X = torch.cat([X, more * 2 + torch.tensor([-1.0, -1.0, 2.5])])
    k = torch.cat([obs.k, torch.tensor([4, 5, 6]).repeat_interleave(20)])
    p = torch.cat([obs.p, torch.arange(300, 320).repeat(3)])
    obs = Observations(k, p, torch.zeros(len(k), 2, dtype=torch.float64), torch.ones(len(k)))
    obs.uv, _ = reprojection(pose.invert(T_wc), X, K, obs)
    broken = T_wc.clone()
    broken[0, 0, 3] -= 0.05
    result = adjust(broken, K, obs, 3.0, 30, None, gauge=gauge)
    off = float((result.T_wc[0, :3, 3] - T_wc[0, :3, 3]).norm())
    assert result.held == held
    assert (off > 0.04) if gauge == "first" else (off < 1e-5)


@pytest.mark.parametrize(("length", "held"), [(None, 2), (0.05, 2), (0.05, [3, 4])])
def test_the_priors_jacobian_by_colours_is_autograds(length, held):
    T_wc, _, _ = _scene(cameras=9)
    prior = odometry_prior(T_wc, 0.2, 0.02, length, torch.tensor([0, 5, 20, 0, 0, 9, 30, 1]), 10)
    T_cw = _perturbed(T_wc, 0.05)  # away from the prior's zero, where its Jacobian is plain
    fixed = torch.arange(9) < 2 if held == 2 else torch.isin(torch.arange(9), torch.tensor(held))

    def moved(step):
        T = T_cw.clone()
        T[~fixed] = pose.exp_se3(step.reshape(7, 6)) @ T_cw[~fixed]
        return prior(T)

    expected = torch.autograd.functional.jacobian(moved, torch.zeros(42, dtype=torch.float64))
    r, J = prior.jacobian(T_cw, held if held == 2 else fixed)
    assert torch.allclose(r, prior(T_cw))
    assert float(expected.abs().max()) > 1.0
    assert torch.allclose(J, expected, atol=1e-6)


def test_a_prior_on_some_poses_has_their_columns_of_the_whole_jacobian():
    """`Prior.on`: the keyframes' odometry (poses 0, 3, 4, 7, 8 of 9) over every pose, pose
    4 held: the Jacobian's columns are those of the poses it reads, zero for the others."""
    T_wc, _, _ = _scene(cameras=9)
    at = torch.tensor([0, 3, 4, 7, 8])
    prior = odometry_prior(T_wc[at], 0.2, 0.02, 0.05, torch.tensor([0, 5, 20, 0]), 10).on(at)
    T_cw = _perturbed(T_wc, 0.05)
    fixed = torch.arange(9) == 4

    def moved(step):
        T = T_cw.clone()
        T[~fixed] = pose.exp_se3(step.reshape(8, 6)) @ T_cw[~fixed]
        return prior(T)

    expected = torch.autograd.functional.jacobian(moved, torch.zeros(48, dtype=torch.float64))
    r, J = prior.jacobian(T_cw, fixed)
    assert torch.allclose(r, prior(T_cw)) and len(r) == len(prior.first)
    assert float(expected.abs().max()) > 1.0
    assert torch.allclose(J, expected, atol=1e-6)
    # poses 1, 2, 5, 6 are the system's blocks 1, 2, 4, 5 (pose 4 held has none)
    assert float(J.reshape(len(r), 8, 6)[:, [1, 2, 4, 5]].abs().max()) == 0


def test_the_odometry_prior_places_a_pose_no_feature_sees():
    T_wc, X, obs = _scene()
    blind = obs.k != 5
    obs = Observations(obs.k[blind], obs.p[blind], obs.uv[blind], obs.sigma[blind])
    twist = torch.zeros(len(T_wc), 6, dtype=torch.float64)
    twist[5] = torch.tensor([0.02, -0.01, 0.01, 0.02, 0.0, -0.01])
    T_cw = pose.exp_se3(twist) @ pose.invert(T_wc)
    prior = odometry_prior(T_wc, 0.2, 0.02)
    T_ba, _, _ = bundle_adjust(T_cw, X, K, obs, 2, 30, prior=prior)
    assert torch.allclose(pose.invert(T_ba)[5], T_wc[5], atol=1e-5)


def test_a_stretch_no_feature_sees_keeps_the_scale_of_its_neighbours():
    """Cameras 0-4 see one set of points, 7-11 another, 5 and 6 none: the features alone
    cannot tell the second part's scale from the first's, the step lengths held across the
    unlinked steps can."""
    T_wc, X, obs = _scene(cameras=12, points=200)
    seen = ((obs.k <= 4) & (obs.p < 100)) | ((obs.k >= 7) & (obs.p >= 100))
    obs = Observations(obs.k[seen], obs.p[seen], obs.uv[seen], obs.sigma[seen])
    assert links(obs, 12).tolist() == [100] * 4 + [0] * 3 + [100] * 4
    start = T_wc.clone()
    start[5:, :3, 3] = T_wc[4, :3, 3] + 1.3 * (T_wc[5:, :3, 3] - T_wc[4, :3, 3])
    T_cw = pose.invert(start)
    X_start = triangulate(T_cw, K, obs)

    def adjusted(cfg):
        T_ba, _, _ = bundle_adjust(T_cw, X_start, K, obs, 2, 40, prior=prior_for(T_wc, obs, cfg))
        return (pose.invert(T_ba)[:, :3, 3] - T_wc[:, :3, 3]).norm(dim=1).max()

    assert float(adjusted(BundleConfig(linked=0))) > 0.1  # the second part stays 1.3x
    assert float(adjusted(BundleConfig())) < 1e-3


def test_length_linked_holds_the_ratios_loosely_where_features_link_the_steps():
    """Linked steps' lengths are the features' alone by default; with `length_linked` their
    ratios are held as an unlinked step's would be at that standard error, and an unlinked
    step keeps its own tighter `length`."""
    T_wc, _, _ = _scene(cameras=10)
    stretched = T_wc.clone()
    stretched[5:, :3, 3] = T_wc[4, :3, 3] + 1.2 * (T_wc[5:, :3, 3] - T_wc[4, :3, 3])
    T_cw = pose.invert(stretched)  # step 4 -> 5 and on a fifth longer, the same directions
    linked = torch.full((9,), 100)
    free = odometry_prior(T_wc, 0.2, 0.02, 0.05, linked, 10)
    assert float(free(T_cw).abs().max()) < 1e-9
    held = odometry_prior(T_wc, 0.2, 0.02, 0.05, linked, 10, length_linked=0.2)
    as_unlinked = odometry_prior(T_wc, 0.2, 0.02, 0.2, torch.zeros(9, dtype=torch.long), 10)
    assert torch.allclose(held(T_cw), as_unlinked(T_cw))
    alone = odometry_prior(T_wc, 0.2, 0.02, length_linked=0.2)  # no `length`, no links
    assert torch.allclose(alone(T_cw), held(T_cw))
    assert float(held(T_cw).abs().max()) > 0.5
    linked[4] = 0
    tighter = odometry_prior(T_wc, 0.2, 0.02, 0.05, linked, 10, length_linked=0.2)
    assert float(tighter(T_cw).abs().max()) == pytest.approx(4 * float(held(T_cw).abs().max()))
    _, _, obs = _scene(cameras=10)
    by_config = prior_for(T_wc, obs, BundleConfig(length_linked=0.2))
    assert torch.allclose(by_config(T_cw), held(T_cw))
    everywhere = prior_for(T_wc, obs, BundleConfig(linked=0, length_linked=0.2))
    assert torch.allclose(everywhere(T_cw), held(T_cw))  # linked 0: no step held tighter


def _noisy_steps(T_wc, turn_deg, move, seed=3):
    """`T_wc`'s path with each step's turn off by `turn_deg` and its translation by `move`
    (standard errors per axis): a tracker's odometry."""
    g = torch.Generator().manual_seed(seed)
    tracked = T_wc.clone()
    for k in range(1, len(T_wc)):
        noise = torch.cat(
            [
                move * torch.randn(3, generator=g, dtype=torch.float64),
                math.radians(turn_deg) * torch.randn(3, generator=g, dtype=torch.float64),
            ]
        )
        step = pose.invert(T_wc[k - 1]) @ T_wc[k]
        tracked[k] = tracked[k - 1] @ step @ pose.exp_se3(noise)
    return tracked


def _weighing_case():
    """A path of 20 keyframes, its features with 0.5 px of noise, and tracked steps whose
    turns are 0.3 degrees off and whose translations 3 mm."""
    T_wc, _, obs = _scene(cameras=20, points=300)
    noise = torch.randn(obs.uv.shape, generator=torch.Generator().manual_seed(2))
    obs.uv = obs.uv + 0.5 * noise.double()
    return T_wc, obs, _noisy_steps(T_wc, 0.3, 0.003)


def _step_errors(T_wc, truth):
    """The median turn (radians) and direction (unit vectors' difference) errors of the
    steps of `T_wc` against those of `truth`."""
    steps = pose.compose(pose.invert(T_wc[:-1]), T_wc[1:])
    true = pose.compose(pose.invert(truth[:-1]), truth[1:])
    turn = pose.log_so3(true[:, :3, :3].transpose(1, 2) @ steps[:, :3, :3]).norm(dim=1)
    unit = torch.nn.functional.normalize
    direction = (unit(steps[:, :3, 3], dim=1) - unit(true[:, :3, 3], dim=1)).norm(dim=1)
    return float(turn.median()), float(direction.median())


def test_weighing_finds_how_much_the_prior_holds_the_turns_too_tightly():
    """Features with 0.5 px of noise, tracked steps whose turns are 0.3 degrees off and
    whose directions 0.025-0.03 (translations of 3 mm on steps of 10-12 cm), a prior that
    says 0.05 degrees and 0.02: relative to the reprojection errors (0.5^2 for a pixel's
    weight of 1) the turns' variance is 36 / 0.25 = 144 times what the prior says, the
    directions' 6-9 times (19 steps: a sample's variance is within a third of it). The
    estimate finds both; the rounds of `weigh` weigh the turns again (`WEIGHED`), and the
    poses they end on turn between keyframes nearer the truth than those the tight prior
    holds."""
    T_wc, obs, tracked = _weighing_case()
    prior = odometry_prior(tracked, 0.05, 0.02)
    held = adjust(tracked, K, obs, 3.0, 30, prior)
    assert held.factors == ()
    T_cw, gauge = pose.invert(held.T_wc), held_pair(obs, 20, "first")
    X = triangulate(T_cw, K, obs)
    _, X, _ = bundle_adjust(T_cw, X, K, obs, len(T_cw), 10)  # the points at the poses
    factors, observed = variance_factors(T_cw, X, K, obs, gauge, prior)
    assert 0.2 < observed < 0.3  # 0.5 px of noise per coordinate
    assert factors[0] > 20 and factors[1] > 3  # both held too tightly

    weighed = adjust(tracked, K, obs, 3.0, 30, prior, weigh=3)
    turns, directions = weighed.factors
    assert 90 < turns < 200 and directions == 1
    assert 0.45 < weighed.reprojection < 0.55

    assert _step_errors(weighed.T_wc, T_wc)[0] < 0.5 * _step_errors(held.T_wc, T_wc)[0]
    # Once weighed, a further estimate finds the turns about right.
    T_cw = pose.invert(weighed.T_wc)
    X = triangulate(T_cw, K, obs)
    _, X, _ = bundle_adjust(T_cw, X, K, obs, len(T_cw), 10)
    again, _ = variance_factors(
        T_cw, X, K, obs, gauge, prior.weighed(torch.tensor(weighed.factors))
    )
    assert 0.7 < float(again[0]) < 1.3


def test_the_directions_weighed_with_the_turns_as_one_step():
    """Pooled (`bundle.weigh_steps`), a step's turn and direction have one variance factor,
    between what the turns alone need (about 115 here) and the directions alone (3-20): the
    directions, held as configured when the turns alone are weighed, then follow the
    features and end nearer the truth (0.013 against 0.019), the turns as near as alone."""
    T_wc, obs, tracked = _weighing_case()
    alone = adjust(tracked, K, obs, 3.0, 30, odometry_prior(tracked, 0.05, 0.02), weigh=3)
    pooled = odometry_prior(tracked, 0.05, 0.02, pooled=True)
    assert set(pooled.group.tolist()) == {0, -1}  # no group of directions of their own
    steps = adjust(tracked, K, obs, 3.0, 30, pooled, weigh=3)
    (factor,) = steps.factors
    assert 20 < factor < alone.factors[0]
    turn, direction = _step_errors(steps.T_wc, T_wc)
    turn_alone, direction_alone = _step_errors(alone.T_wc, T_wc)
    assert direction < 0.8 * direction_alone and turn < 1.1 * turn_alone
    cfg = BundleConfig(weigh=3, weigh_steps=True)
    _, _, seen = _scene(cameras=20)
    assert set(prior_for(tracked, seen, cfg).group.tolist()) == {0, 2, -1}  # and lengths


def test_a_free_step_is_not_held_by_the_prior():
    """The steps `free` (a slide found by the features) keep no turn, direction or length."""
    T_wc, _, _ = _scene(cameras=10)
    twist = torch.tensor([0.05, 0.02, -0.03, 0.01, -0.04, 0.02], dtype=torch.float64)
    about = T_wc[4] @ pose.exp_se3(twist) @ pose.invert(T_wc[4])
    moved = T_wc.clone()
    moved[5:] = about @ T_wc[5:]  # step 4 -> 5 changed, every other step as it was
    free = torch.zeros(9, dtype=torch.bool)
    free[4] = True
    for length in (None, 0.05):
        shared = torch.zeros(9, dtype=torch.long) if length else None
        held = odometry_prior(T_wc, 0.2, 0.02, length, shared)
        loose = odometry_prior(T_wc, 0.2, 0.02, length, shared, free=free)
        assert float(held(pose.invert(moved)).abs().max()) > 1.0
        assert float(loose(pose.invert(moved)).abs().max()) < 1e-9


def test_a_live_path_holds_only_the_steps_no_feature_links():
    """`BundleConfig.live_path`: a step that `linked` points or more link is left to the
    features (turn, direction and length free), one that none links is held as tracked."""
    T_wc, _, _ = _scene(cameras=10)
    twist = torch.tensor([0.05, 0.02, -0.03, 0.01, -0.04, 0.02], dtype=torch.float64)
    cfg = BundleConfig(length_linked=0.2, weigh=3, weigh_steps=True).live_path()
    assert (cfg.steps_linked, cfg.length_linked, cfg.weigh) == (False, 0.0, 0)
    shared = torch.full((9,), 50)
    shared[6] = 0  # step 6 -> 7: no point links it
    prior = odometry_prior(
        T_wc, cfg.turn_deg, cfg.direction, cfg.length, shared, cfg.linked, unlinked_only=True
    )
    for step, held in ((3, False), (6, True)):
        about = T_wc[step] @ pose.exp_se3(twist) @ pose.invert(T_wc[step])
        moved = T_wc.clone()
        moved[step + 1 :] = about @ T_wc[step + 1 :]  # that step changed, every other as it was
        residual = float(prior(pose.invert(moved)).abs().max())
        assert residual > 1.0 if held else residual < 1e-9
    # Offline every step's turn and direction are held, linked or not.
    offline = odometry_prior(T_wc, 0.1, 0.03, 0.05, shared, 10)
    about = T_wc[3] @ pose.exp_se3(twist) @ pose.invert(T_wc[3])
    moved = T_wc.clone()
    moved[4:] = about @ T_wc[4:]
    assert float(offline(pose.invert(moved)).abs().max()) > 1.0


def test_a_slide_is_many_keyframes_against_the_tracked_motion_not_one():
    cosine, inliers = np.ones(24), np.full(24, 300)
    cosine[:3] = np.nan  # no keyframe 3 before them
    cosine[4] = -0.9  # one wrong matrix
    cosine[[10, 11, 13, 14, 15]] = -0.8  # 5 of 7 against, keyframe 12 agrees
    cosine[18:] = -0.9
    inliers[18:] = 50  # too few inliers to say anything
    assert slides(cosine, inliers) == [(10, 15)]
    assert slides(np.ones(5), np.full(5, 300)) == []
    # It reaches over the keyframes next to it that do not clearly confirm the tracked
    # motion, whatever their inliers, and to the end where fewer than 7 keyframes are left.
    cosine[[8, 9]], inliers[9] = 0.3, 20
    assert slides(cosine, inliers) == [(8, 15)]
    cosine[16:18] = -0.2
    assert slides(cosine, inliers) == [(8, 23)]


def test_the_features_see_a_slide_and_the_adjustment_undoes_it():
    """A steady walk whose tracked motion from camera 8 on slides (it moves back and turns
    half as much again): the essential matrices between cameras 3 apart point against it,
    the start follows the motion before the slide (the truth: the walk is steady), and
    the adjustment from there, with no prior on the slid steps, ends on the truth; from the
    tracked poses with the prior it does not."""
    T_wc, X, obs = _scene(cameras=16, points=300)
    step = pose.invert(T_wc[0]) @ T_wc[1]
    slid_step = pose.exp_se3(torch.tensor([-0.1, 0.0, 0.0, 0.0, 0.045, 0.0], dtype=torch.float64))
    assert float(step[0, 3]) > 0.09  # the true step goes along +x
    tracked = T_wc.clone()
    for k in range(9, 16):
        tracked[k] = tracked[k - 1] @ slid_step
    cosine, inliers = feature_directions(tracked, K, obs)
    assert (cosine[3:9] > 0.99).all() and (cosine[12:] < -0.9).all()
    assert (inliers[3:] >= 250).all()
    stretches = slides(cosine, inliers)
    assert len(stretches) == 1 and stretches[0][1] == 15
    start, free = slid_start(tracked, list(range(16)), stretches)
    assert torch.allclose(start, T_wc, atol=1e-9)
    trusted = stretches[0][0] - 3
    assert free.tolist() == [trusted <= k < 15 for k in range(15)]
    cfg = BundleConfig(linked=0)
    ends = adjust(start, K, obs, 3.0, 30, prior_for(start, obs, cfg, free))
    assert torch.allclose(ends.T_wc[:, :3, 3], T_wc[:, :3, 3], atol=1e-5)
    kept = adjust(tracked, K, obs, 3.0, 30, prior_for(tracked, obs, cfg))
    assert float((kept.T_wc[:, :3, 3] - T_wc[:, :3, 3]).norm(dim=1).max()) > 0.1


def test_tracks_link_the_features_of_a_rendered_walk(tmp_path):
    """The built-in scene's first frames: features chain into tracks over several keyframes,
    and at the true poses they reproject within a pixel or two."""
    out = tmp_path / "seq"
    write_sequence(out, frames=12, width=320, height=240, noise=0.0)

    reader = open_dataset(out)
    frames = list(reader)[::3]
    cam = reader.camera
    Kc = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1]])
    tracks = FeatureTracks(Kc, 1500, 8)
    for f in frames:
        tracks.add(f.index, grey_image(f.rgb))
    obs = tracks.observations([f.index for f in frames])
    assert obs.points > 100 and int(torch.bincount(obs.p).max()) == len(frames)
    T_cw = pose.invert(torch.from_numpy(np.stack([f.T_wc for f in frames])))
    r, _ = reprojection(
        T_cw, triangulate(T_cw, torch.from_numpy(Kc), obs), torch.from_numpy(Kc), obs
    )
    assert float(r.norm(dim=1).median()) < 0.5


def _blobs(shift, seed=0):
    """A 320x240 image of 60 smooth Gaussian blobs (no corner a FAST test sees), moved by
    `shift` pixels."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform([-40, -40], [360, 280], (60, 2)) + shift
    level = rng.uniform(0.2, 1.0, 60)
    yy, xx = np.mgrid[0:240, 0:320].astype(np.float64)
    image = np.zeros((240, 320))
    for (cx, cy), a in zip(centres, level, strict=True):
        image += a * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * 14.0**2))
    return np.clip(image / image.max() * 230 + 10, 0, 255).round().astype(np.uint8)


@pytest.mark.parametrize("realign", [False, True])
def test_flow_follows_smooth_blobs_that_orb_cannot_see(realign):
    """Room5's wall, reduced: ORB finds almost nothing on smooth blobs, the flow follows
    them from frame to frame to a hundredth of a pixel, observed at the keyframes (aligned
    again with their first keyframe at each, or not)."""
    step = np.array([1.3, 0.7])
    assert len(describe(_blobs(0 * step), 1500).points) < 20
    flow = FlowTracks(200, realign)
    for i in range(9):
        flow.add(i, _blobs(i * step), keyframe=i % 4 == 0)
    flow.add(3, _blobs(20 * step), keyframe=True)  # older than the last: ignored
    obs = flow.observations([0, 4, 8], 3)
    assert obs.points > 100 and len(obs.k) == 3 * obs.points
    assert torch.equal(obs.sigma, torch.ones(len(obs.k), dtype=torch.float64))
    start = torch.zeros(obs.points, 2, dtype=torch.float64)
    start[obs.p[obs.k == 0]] = obs.uv[obs.k == 0]
    moved = obs.uv - start[obs.p]
    error = (moved - obs.k[:, None] * 4 * torch.from_numpy(step)).norm(dim=1)
    assert float(error.median()) < 0.05
    assert flow.observations([0, 4], 3).points == 0  # seen by two keyframes only
    assert flow.observations([100], 1).points == 0


def test_flow_and_orb_tracks_are_one_set_of_points(tmp_path):
    """The built-in scene's first frames, every one followed, every 3rd a keyframe: the
    flow's tracks reproject within half a pixel at the true poses, and beside the ORB
    tracks they are points of their own."""
    out = tmp_path / "seq"
    write_sequence(out, frames=10, width=320, height=240, noise=0.0)
    reader = open_dataset(out)
    frames = list(reader)
    keyframes = frames[::3]
    Kc = torch.from_numpy(reader.camera.K)
    flow, tracks = FlowTracks(300), FeatureTracks(reader.camera.K, 1500, 8)
    indices = [f.index for f in keyframes]
    for f in frames:
        flow.add(f.index, grey_image(f.rgb), keyframe=f.index in indices)
        if f.index in indices:
            tracks.add(f.index, grey_image(f.rgb))
    followed, described = flow.observations(indices, 3), tracks.observations(indices, 3)
    assert followed.points > 100
    T_cw = pose.invert(torch.from_numpy(np.stack([f.T_wc for f in keyframes])))
    r, _ = reprojection(T_cw, triangulate(T_cw, Kc, followed), Kc, followed)
    assert float(r.norm(dim=1).median()) < 0.5
    both = described.cat(followed)
    assert both.points == described.points + followed.points
    assert torch.equal(both.p[len(described.k) :], followed.p + described.points)
    assert torch.equal(both.uv[len(described.k) :], followed.uv)


def test_realigned_flow_follows_the_corner_not_its_window(tmp_path):
    """The built-in scene with its sensor noise: corners aligned again at every keyframe
    with their first keyframe's patch reproject at the true poses within a tenth of a pixel
    (median); in the flow's 21-pixel window, whose best shift follows the patch as it
    changes shape across the keyframes, about 0.14."""
    out = tmp_path / "seq"
    write_sequence(out, frames=60, width=320, height=240, noise=1.0)
    reader = open_dataset(out)
    frames = list(reader)
    indices = [f.index for f in frames[::3]]
    T_cw = pose.invert(torch.from_numpy(np.stack([f.T_wc for f in frames[::3]])))
    Kc = torch.from_numpy(reader.camera.K)
    median = {}
    for window in (FLOW_REALIGN_WINDOW, FLOW_WINDOW):
        flow = FlowTracks(300, realign=True, window=window)
        for f in frames:
            flow.add(f.index, grey_image(f.rgb), keyframe=f.index in indices)
        followed = flow.observations(indices, 4)
        assert followed.points > 300
        r, _ = reprojection(T_cw, triangulate(T_cw, Kc, followed), Kc, followed)
        median[window] = float(r.norm(dim=1).median())
    assert median[FLOW_REALIGN_WINDOW] < 0.1 < median[FLOW_WINDOW]


def test_flow_near_keeps_the_flows_observations_about_steps_orb_does_not_link():
    """Eight keyframes whose ORB features chain over 0-3 and over 4-7 but not across: with
    `flow_near 1`, the flow's ten tracks are observed at keyframes 2-5 only, beside every
    ORB observation; with -1 everywhere; an adjustment without a weak step gets no flow."""
    tracks = FeatureTracks(K.numpy(), 100, 8)
    for index in range(8):
        tracks.insert(index, Features(np.zeros((20, 2)), np.ones(20), None))
    for a in [0, 1, 2, 4, 5, 6]:
        for i in range(20):
            tracks.join(a + 1, i, a, i)
    flow = FlowTracks(10)
    flow.seen = [(index, np.arange(10), np.zeros((10, 2))) for index in range(8)]
    indices = list(range(8))
    orb = tracks.observations(indices, 3)
    assert links(orb, 8).tolist() == [20, 20, 20, 0, 20, 20, 20]
    near = observed(tracks, flow, indices, BundleConfig(flow=10, flow_near=1))
    added = near.p >= orb.points
    assert (~added).sum() == len(orb.k) == 160
    assert sorted(set(near.k[added].tolist())) == [2, 3, 4, 5] and added.sum() == 40
    everywhere = observed(tracks, flow, indices, BundleConfig(flow=10))
    assert len(everywhere.k) == 160 + 80
    linked = observed(tracks, flow, [0, 1, 2, 3], BundleConfig(flow=10, flow_near=1))
    assert len(linked.k) == 4 * 20


def _short_tracks():
    """Features of the points every camera of `_scene` sees, beside 200 random ones per
    keyframe (indices 0, 10, ..., 70), joined over keyframes 0-2 only (and, for points
    100-149, again over 5-7); points 0-49 have another descriptor in keyframe 5."""
    T_wc, X, obs = _scene(cameras=8, points=300)
    uv = obs.uv.view(8, 300, 2)
    inside = ((uv >= 0) & (uv < torch.tensor([320.0, 240.0]))).all(2).all(0)
    X, uv = X[inside], uv[:, inside]  # the points every keyframe sees
    n = len(X)
    rng = np.random.default_rng(0)
    described = rng.integers(0, 256, (n, 32), dtype=np.uint8)
    tracks = FeatureTracks(K.numpy(), 1500, 8)
    for k in range(8):
        clutter = rng.uniform([0, 0], [320, 240], (200, 2))
        descriptors = np.concatenate([described, rng.integers(0, 256, (200, 32), dtype=np.uint8)])
        if k == 5:
            descriptors[:50] = rng.integers(0, 256, (50, 32), dtype=np.uint8)
        points = np.concatenate([uv[k].numpy(), clutter])
        tracks.insert(10 * k, Features(points, np.ones(len(points)), descriptors))
    for i in range(n):
        tracks.join(10, i, 0, i)
        tracks.join(20, i, 10, i)
    for i in range(100, 150):
        tracks.join(60, i, 50, i)
        tracks.join(70, i, 60, i)
    return tracks, T_wc, X


def test_guided_matching_carries_tracks_to_every_keyframe_that_sees_them():
    """Projected at the poses, each point finds its feature in the other keyframes and the
    two tracks of one point become one; a feature whose descriptor is another's and the
    random features beside the points are left alone."""
    tracks, T_wc, X = _short_tracks()
    n = len(X)
    indices = [10 * k for k in range(8)]
    before = tracks.observations(indices, 3)
    assert before.points == n + 50 and int(torch.bincount(before.p).max()) == 3

    made = tracks.guide(indices, pose.invert(T_wc), 3, 3.0)

    after = tracks.observations(indices, 3)
    seen = torch.bincount(after.p)
    # 0-49: keyframes 3, 4, 6, 7; 100-149: one merge, then 3 and 4; the rest 3-7.
    assert made == 50 * 4 + 50 * 3 + (n - 100) * 5
    assert after.points == n and int((seen == 7).sum()) == 50 and int((seen == 8).sum()) == n - 50
    # Every observation is of its track's point: none of the clutter, none of another point.
    T_cw = pose.invert(T_wc)
    r, _ = reprojection(T_cw, triangulate(T_cw, K, after), K, after)
    assert float(r.norm(dim=1).max()) < 1e-6


def test_guided_matching_between_the_passes_of_the_adjustment():
    """`bundle.guided`: from perturbed poses, the tracks of 3 keyframes are carried at the
    first pass's poses to the others, and the second pass ends at the truth (keyframes 3
    and 4, which no track saw, with them)."""
    tracks, T_wc, _ = _short_tracks()
    indices = [10 * k for k in range(8)]
    start = pose.invert(_perturbed(T_wc, 0.003))
    cfg = BundleConfig(guided=True)
    result = adjust_tracks(tracks, indices, start, K, cfg, None)
    n = len(_short_tracks()[2])
    assert result.guided > 4 * n and result.observations >= 7 * n  # from 3 views to 7-8
    assert float((result.T_wc[:, :3, 3] - T_wc[:, :3, 3]).norm(dim=1).max()) < 1e-4


def test_settings_are_checked():
    with pytest.raises(ValueError, match="positive"):
        BundleConfig(turn_deg=0)
    with pytest.raises(ValueError, match="neighbours"):
        BundleConfig(neighbours=0)
    with pytest.raises(ValueError, match="flow"):
        BundleConfig(flow=-1)
    with pytest.raises(ValueError, match="flow_near"):
        BundleConfig(flow_near=-2)
    with pytest.raises(ValueError, match="gauge"):
        BundleConfig(gauge="middle")
    with pytest.raises(ValueError, match="length_linked"):
        BundleConfig(length_linked=-0.2)


def test_the_benchmark_says_which_keyframes_it_cannot_find(tmp_path, monkeypatch, capsys):
    fba = benchmark(monkeypatch, "feature_ba")
    run = tmp_path / "run"
    run.mkdir()
    (run / "keyframes.txt").write_text("# keyframes\n123.0 0 0 0 0 0 0 1\n")
    data = tmp_path / "seq"
    write_sequence(data, frames=3, width=80, height=60)
    err = usage_error(monkeypatch, capsys, fba.main, ["feature_ba.py", str(run), str(data)])
    assert "0 of 1 keyframes found" in err


@pytest.mark.parametrize(
    ("flags", "needs"),
    [
        (["--fill-evenly"], "--fill-gaps FACTOR"),
        (["--every-frame"], "--flow N"),
        (["--every-frame", "--live", "--flow", "300"], "not both"),
        (["--prior-every-step"], "needs --every-frame"),
    ],
)
def test_the_benchmark_refuses_a_flag_without_the_one_it_needs(
    tmp_path, monkeypatch, capsys, flags, needs
):
    """Before any file is read: RUN and DATASET do not exist here."""
    fba = benchmark(monkeypatch, "feature_ba")
    argv = ["feature_ba.py", str(tmp_path / "run"), str(tmp_path / "seq"), *flags]
    assert needs in usage_error(monkeypatch, capsys, fba.main, argv)


def test_the_benchmark_carries_every_frame_as_the_mapper_does(monkeypatch):
    """Keyframes that the adjustment left where they were leave every frame where it was;
    keyframes moved take the frames after them along, scaled as the path about them grew."""
    fba = benchmark(monkeypatch, "feature_ba")
    twists = torch.zeros(9, 6, dtype=torch.float64)
    twists[:, 0] = torch.arange(9) * 0.1
    twists[:, 5] = torch.arange(9) * 0.02
    every = Trajectory(np.arange(9.0), pose.exp_se3(twists).numpy())
    keyframes = Trajectory(every.timestamps[::2], every.poses[::2])
    assert np.allclose(
        fba.carried(every, keyframes, torch.from_numpy(keyframes.poses)), every.poses
    )
    longer = torch.from_numpy(keyframes.poses).clone()
    longer[3:, 0, 3] += 0.2  # the step from keyframe 2 to 3 grows from 0.2 to 0.4
    moved = fba.carried(every, keyframes, longer)
    T_new, scales = brought_back(torch.from_numpy(keyframes.poses), longer)
    assert np.allclose(moved[::2], T_new.numpy())
    offset = np.linalg.inv(moved[4]) @ moved[5]  # frame 5 after keyframe 2 (frame 4)
    tracked = np.linalg.inv(every.poses[4]) @ every.poses[5]
    assert np.allclose(offset[:3, 3], tracked[:3, 3] * float(scales[2]))
    assert abs(float(scales[2]) - 1) > 0.01  # a scale that the check can see


def test_the_benchmark_adds_the_initialization_frames_at_the_keyframe_spacing(monkeypatch):
    """`--init-keyframes`: keyframes at frames 0, 13, 15, 17 and 19 (spacing 2) get frames 2,
    4, 6, 8 and 10 of the initialization, with their tracked poses; frame 12, a frame before
    the second keyframe, stays out."""
    fba = benchmark(monkeypatch, "feature_ba")
    twists = torch.zeros(20, 6, dtype=torch.float64)
    twists[:, 0] = torch.arange(20) * 0.05
    every = Trajectory(1 + np.arange(20) / 30, pose.exp_se3(twists).numpy())
    at = [0, 13, 15, 17, 19]
    keyframes = Trajectory(every.timestamps[at], every.poses[at])
    both = fba.with_init_keyframes(keyframes, every)
    expected = [0, 2, 4, 6, 8, 10, 13, 15, 17, 19]
    assert np.allclose(both.timestamps, every.timestamps[expected])
    assert np.allclose(both.poses, every.poses[expected])
    with pytest.raises(ValueError, match="each a frame"):
        fba.with_init_keyframes(Trajectory(np.array([0.5, 1.0]), every.poses[:2]), every)
    # `--init-keyframes 4,8,12`: those, as the mapper's rule marked them (`bundle.init_frames`).
    chosen = fba.with_init_keyframes(keyframes, every, [8, 4, 12])
    assert np.allclose(chosen.timestamps, every.timestamps[[0, 4, 8, 12, 13, 15, 17, 19]])
    with pytest.raises(ValueError, match="between the run's first two keyframes"):
        fba.with_init_keyframes(keyframes, every, [4, 13])


def test_the_benchmark_fills_the_long_gaps_between_keyframes(monkeypatch):
    """`--fill-gaps 3`: keyframes at frames 0, 13, 15, 17, 25, 27, 29 (spacing 2) get frames
    19, 21 and 23 of the gap of 8 after 17; the initialization's gap (0-13) is left to
    `--init-keyframes`, the gaps of 2 have none."""
    fba = benchmark(monkeypatch, "feature_ba")
    twists = torch.zeros(30, 6, dtype=torch.float64)
    twists[:, 0] = torch.arange(30) * 0.05
    every = Trajectory(1 + np.arange(30) / 30, pose.exp_se3(twists).numpy())
    at = [0, 13, 15, 17, 25, 27, 29]
    keyframes = Trajectory(every.timestamps[at], every.poses[at])
    filled = fba.with_gap_frames(keyframes, every, 3)
    expected = [0, 13, 15, 17, 19, 21, 23, 25, 27, 29]
    assert np.allclose(filled.timestamps, every.timestamps[expected])
    assert np.allclose(filled.poses, every.poses[expected])
    assert len(fba.with_gap_frames(keyframes, every, 5)) == len(at)  # 8 < 5 x 2


def test_the_benchmark_splits_long_gaps_evenly(monkeypatch):
    """`--fill-gaps 3 --fill-evenly`: at spacing 2, the gap of 15 after frame 17 gets frames
    22 and 27 (three pieces of 5), the gap of 7 after 32 frame 36 (or 35: two pieces of 3-4),
    the gap of 6 none (not longer than 3 spacings), the gaps of 2 none."""
    fba = benchmark(monkeypatch, "feature_ba")
    twists = torch.zeros(56, 6, dtype=torch.float64)
    twists[:, 0] = torch.arange(56) * 0.05
    every = Trajectory(1 + np.arange(56) / 30, pose.exp_se3(twists).numpy())
    at = [0, 13, 15, 17, 32, 39, 41, 43, 49, 51, 53, 55]
    keyframes = Trajectory(every.timestamps[at], every.poses[at])
    filled = fba.with_gap_frames(keyframes, every, 3, evenly=True)
    rows = np.round((filled.timestamps - 1) * 30).astype(int).tolist()
    assert rows[:5] == [0, 13, 15, 17, 22] and rows[5] == 27 and rows[6] == 32
    assert rows[7] in (35, 36) and rows[8:] == [39, 41, 43, 49, 51, 53, 55]
    assert np.allclose(filled.poses, every.poses[rows])
    # The default fills every 2nd frame of the gaps of 6 spacings or more.
    assert len(fba.with_gap_frames(keyframes, every, 3)) == len(at) + 6 + 2 + 2


def test_the_benchmark_adjusts_at_another_runs_keyframes(tmp_path, monkeypatch):
    """`--keyframes-from`: the other run's keyframe frames, posed as this run's path has
    them; a keyframe that is not a frame of this run is an error that names it."""
    fba = benchmark(monkeypatch, "feature_ba")
    twists = torch.zeros(10, 6, dtype=torch.float64)
    twists[:, 2] = torch.arange(10) * 0.03
    every = Trajectory(1 + np.arange(10) / 30, pose.exp_se3(twists).numpy())
    other = Trajectory(every.timestamps[[0, 3, 7]], np.stack([np.eye(4)] * 3))
    at = fba.keyframes_at(every, other)
    assert np.allclose(at.timestamps, every.timestamps[[0, 3, 7]])
    assert np.allclose(at.poses, every.poses[[0, 3, 7]])
    with pytest.raises(ValueError, match="1 keyframes are not frames"):
        fba.keyframes_at(every, Trajectory(np.array([1.0, 7.5]), np.stack([np.eye(4)] * 2)))


def test_the_reduced_camera_system_is_the_points_eliminated():
    """`_reduced` with each unordered pair of a point's observations once (`_schur_pairs`)
    is the dense elimination H_cc - H_cp H_pp^-1 H_cp^T, mirrored blocks and all."""
    generator = torch.Generator().manual_seed(0)
    m, points = 7, 40
    k, p = [], []
    for point in range(points):
        seen = torch.randperm(m, generator=generator)[: 1 + point % m]
        k += seen.tolist()
        p += [point] * len(seen)
    n = len(p)
    obs = Observations(torch.tensor(k), torch.tensor(p), torch.zeros(n, 2), torch.ones(n))
    H_cp = torch.randn(n, 6, 3, dtype=torch.float64, generator=generator)
    A = torch.randn(points, 3, 3, dtype=torch.float64, generator=generator)
    H_pp_inv = A @ A.transpose(1, 2) + torch.eye(3, dtype=torch.float64)
    B = torch.randn(6 * m, 6 * m, dtype=torch.float64, generator=generator)
    H = B @ B.T
    H_cc = H.reshape(m, 6, m, 6).transpose(1, 2).contiguous()
    ii, jj = _schur_pairs(obs, torch.ones(n, dtype=torch.bool))
    assert len(ii) == sum(c * (c + 1) // 2 for c in torch.bincount(obs.p).tolist())
    S = _reduced(H_cc, H_cp, H_pp_inv, obs.p, obs.k, ii, jj)
    H_cp_dense = torch.zeros(6 * m, 3 * points, dtype=torch.float64)
    for i in range(n):
        H_cp_dense[6 * k[i] : 6 * k[i] + 6, 3 * p[i] : 3 * p[i] + 3] = H_cp[i]
    expected = H - H_cp_dense @ torch.block_diag(*H_pp_inv) @ H_cp_dense.T
    assert torch.allclose(S, expected, rtol=0, atol=1e-9 * float(expected.abs().max()))
    assert torch.allclose(S, S.T, rtol=0, atol=1e-12 * float(S.abs().max()))

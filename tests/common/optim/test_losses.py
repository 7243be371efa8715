"""Loss building blocks: warping geometry against the exact synthetic room, SSIM against skimage,
gradients, visibility, smoothness, zero-count guards and high-gradient pixel sampling."""

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from dimslam.common.geometry import pose
from dimslam.common.geometry.camera import Camera
from dimslam.common.io.synth import SynthScene, default_camera
from dimslam.common.optim import losses as L

CAM = default_camera(160, 120)
FRAME_K = 0
FRAMES_L = [10, 20, 30, 40]  # 15 to 60 cm from frame k: 8 to 30 px of parallax


class Views:
    """Frame k and frames l of the synthetic room, with patches that warp cleanly."""

    def __init__(self) -> None:
        scene = SynthScene(0)
        T = scene.path(max(FRAMES_L) + 1)
        rgb_k, depth_k = scene.render(T[FRAME_K], CAM)
        rendered = [scene.render(T[i], CAM) for i in FRAMES_L]
        self.image_k = torch.from_numpy(rgb_k)
        self.images_l = torch.from_numpy(np.stack([r for r, _ in rendered]))
        self.T_k = torch.from_numpy(T[FRAME_K]).float()
        self.T_l = torch.from_numpy(T[FRAMES_L]).float()
        depth = torch.from_numpy(depth_k)
        uv = L.high_gradient_pixels(self.image_k, 400, torch.Generator().manual_seed(0), 5)
        d = depth[uv[:, 1], uv[:, 0]]
        # One surface under the whole 11x11 patch: no depth edge inside it. Slanted planes stay,
        # so the fronto-parallel approximation is exercised too.
        window = torch.nn.functional.unfold(depth[None, None], 11, padding=5)[0]
        window = window.T.reshape(*depth.shape, 121)[uv[:, 1], uv[:, 0]]
        flat = ((window - d[:, None]).abs().amax(-1) / d) < 0.05
        # Not occluded in any frame l: the centre's depth there matches frame l's depth map
        # (computed independently of warp_patches, point by point).
        p_l = pose.transform_points(
            pose.compose(pose.invert(self.T_l), self.T_k), CAM.unproject(uv.float(), d)
        )
        self.centre_uv_l, z_l = CAM.project(p_l)  # (F, M, 2), (F, M)
        px = self.centre_uv_l.round().long()
        px[..., 0].clamp_(0, CAM.width - 1)
        px[..., 1].clamp_(0, CAM.height - 1)
        depth_l = torch.from_numpy(np.stack([d for _, d in rendered]))
        seen = depth_l[torch.arange(len(FRAMES_L))[:, None], px[..., 1], px[..., 0]]
        occluded = ((seen - z_l).abs() > 0.02 * z_l) & CAM.inside(self.centre_uv_l) & (z_l > 0)
        keep = flat & ~occluded.any(0)
        self.uv, self.depth = uv[keep].float(), d[keep]
        self.centre_uv_l = self.centre_uv_l[:, keep]
        self.offsets = L.patch_offsets(11)
        self.ref = L.sample_images(self.image_k, self.uv[:, None] + self.offsets)

    def loss(self, depth=None, T_k=None, T_l=None, sizes=L.PATCH_SIZES) -> L.LossTerm:
        depth = self.depth if depth is None else depth
        T_k = self.T_k if T_k is None else T_k
        T_l = self.T_l if T_l is None else T_l
        warp = L.warp_patches(self.uv, depth, T_k, T_l, CAM, self.offsets)
        warped = L.sample_images(self.images_l, warp.uv)
        visible = torch.ones(len(self.uv), dtype=torch.bool)  # 4 frames l: the paper's > 5 is moot
        return L.warping_loss(self.ref, warped, warp.valid, visible, sizes)


@pytest.fixture(scope="module")
def views() -> Views:
    return Views()


def test_patch_offsets_layout():
    off = L.patch_offsets(3)
    assert off.shape == (9, 2)
    assert off[0].tolist() == [-1, -1] and off[1].tolist() == [0, -1]  # row-major: du inner
    assert off[4].tolist() == [0, 0]  # the centre sits in the middle
    assert L.patch_offsets(1).tolist() == [[0, 0]]
    for bad in (0, 2, 4, -3):
        with pytest.raises(ValueError):
            L.patch_offsets(bad)


def test_sample_images_pixel_centres_are_integers():
    g = torch.Generator().manual_seed(1)
    images = torch.rand(2, 7, 9, 3, generator=g)
    uv = torch.tensor([[[0.0, 0.0], [8.0, 6.0], [3.0, 2.0]], [[5.0, 1.0], [2.0, 4.0], [7.0, 3.0]]])
    out = L.sample_images(images, uv)
    assert out.shape == (2, 3, 3)
    for f in range(2):
        for m in range(3):
            u, v = uv[f, m].long()
            assert torch.allclose(out[f, m], images[f, v, u], atol=1e-6)
    # One image with patch-shaped coordinates; half a pixel right averages two neighbours.
    one = L.sample_images(images[0], torch.tensor([[[2.5, 3.0], [4.0, 5.0]]]))
    assert one.shape == (1, 2, 3)
    assert torch.allclose(one[0, 0], (images[0, 3, 2] + images[0, 3, 3]) / 2, atol=1e-6)
    assert torch.allclose(one[0, 1], images[0, 5, 4], atol=1e-6)
    # Far outside the image: zeros and zero gradients, nothing non-finite.
    far = torch.tensor([[1e30, 2.0], [-3e9, 1.0]], requires_grad=True)
    out = L.sample_images(images[0], far)
    out.sum().backward()
    assert (out == 0).all() and (far.grad == 0).all()


def test_true_geometry_warps_patches_onto_themselves(views):
    assert len(views.uv) >= 50
    # Every patch pixel lands where a point-by-point projection of the pixel, unprojected at the
    # centre's depth (the fronto-parallel plane in k), puts it.
    warp = L.warp_patches(views.uv, views.depth, views.T_k, views.T_l, CAM, views.offsets)
    p_k = CAM.unproject(views.uv[:, None] + views.offsets, views.depth[:, None].expand(-1, 121))
    T_lk = pose.compose(pose.invert(views.T_l), views.T_k)
    expected, _ = CAM.project(pose.transform_points(T_lk[:, None], p_k))  # (F, M, P, 2)
    assert torch.allclose(warp.uv, expected, atol=1e-2)
    assert torch.allclose(warp.uv[:, :, 60], views.centre_uv_l, atol=1e-2)
    for s in L.PATCH_SIZES:
        term = views.loss(sizes=(s,))
        # Most patches land fully inside most frames l.
        assert int(term.count) > 0.6 * len(views.uv) * len(FRAMES_L)
        # Residue: bilinear resampling of the texture and the fronto-parallel approximation.
        assert term.value < 0.02, s
    # The warped patches' SSIM itself is near 1.
    ssim = L.patch_ssim(views.ref, L.sample_images(views.images_l, warp.uv))
    assert ssim[warp.valid.all(-1)].median() > 0.97


def test_patches_from_several_source_frames_warp_in_one_call(views):
    # Half the patches come from frame k, half from frame l[0] at a depth of their own: one
    # call with a pose per patch gives what one call per source frame gives.
    n = len(views.uv) // 2
    depth = views.depth * torch.linspace(0.9, 1.1, len(views.uv))
    T_src = torch.stack([views.T_k] * n + [views.T_l[0]] * (len(views.uv) - n))
    both = L.warp_patches(views.uv, depth, T_src, views.T_l, CAM, views.offsets)
    for rows, T in ((slice(0, n), views.T_k), (slice(n, None), views.T_l[0])):
        one = L.warp_patches(views.uv[rows], depth[rows], T, views.T_l, CAM, views.offsets)
        assert torch.allclose(both.uv[:, rows], one.uv, atol=1e-4)
        assert torch.equal(both.valid[:, rows], one.valid)
    with pytest.raises(ValueError, match="T_wc_k"):
        L.warp_patches(views.uv, depth, T_src[:-1], views.T_l, CAM, views.offsets)


def test_wrong_depth_or_pose_costs_clearly_more(views):
    true = views.loss().value
    assert views.loss(depth=views.depth * 1.1).value > 3 * true
    assert views.loss(depth=views.depth * 0.9).value > 3 * true
    nudge = torch.tensor([0.0, 0.0, 0.0, 0.0, 0.015, 0.0])  # ~1 degree of yaw
    assert views.loss(T_l=pose.retract(views.T_l, nudge)).value > 3 * true
    assert views.loss(T_k=pose.retract(views.T_k, nudge)).value > 3 * true
    shift = torch.tensor([0.03, 0.0, 0.0, 0.0, 0.0, 0.0])  # 3 cm sideways
    assert views.loss(T_l=pose.retract(views.T_l, shift)).value > 3 * true


@pytest.mark.parametrize("factor", [1.05, 0.95])
def test_depth_gradient_points_to_the_true_depth(views, factor):
    depth = (views.depth * factor).requires_grad_()
    before = views.loss(depth=depth).value
    before.backward()
    grad = depth.grad
    moved = grad != 0
    # Too deep -> positive gradient (shrink), too shallow -> negative, for nearly every pixel.
    right_way = (grad > 0) == (factor > 1)
    assert right_way[moved].float().mean() > 0.8
    step = depth.detach() - 0.02 * views.depth * grad / grad.abs().max()
    assert views.loss(depth=step).value < before
    assert (step - views.depth).abs().mean() < (depth.detach() - views.depth).abs().mean()


def test_pose_gradients_are_finite_and_descend(views):
    # Frames l pushed 3 cm sideways: a step against the gradient of the increment brings them back.
    start = torch.tensor([0.03, 0.0, 0.0, 0.0, 0.0, 0.0])
    xi = start.clone().requires_grad_()
    before = views.loss(T_l=pose.retract(views.T_l, xi.expand(len(FRAMES_L), 6))).value
    before.backward()
    assert torch.isfinite(xi.grad).all() and xi.grad.abs().sum() > 0
    step = start - 0.01 * xi.grad / xi.grad.norm()
    after = views.loss(T_l=pose.retract(views.T_l, step.expand(len(FRAMES_L), 6))).value
    assert after < 0.8 * before
    # Frame k's pose receives a gradient too.
    xi_k = torch.zeros(6, requires_grad=True)
    views.loss(T_k=pose.retract(views.T_k, xi_k)).value.backward()
    assert torch.isfinite(xi_k.grad).all() and xi_k.grad.abs().sum() > 0


@pytest.mark.parametrize("size", [3, 5, 7, 11])
def test_patch_ssim_matches_skimage(size):
    rng = np.random.default_rng(size)
    for _ in range(5):
        a = rng.uniform(0, 1, (size, size, 3))
        b = np.clip(
            rng.uniform(0.2, 0.9) * a + rng.normal(0, rng.uniform(0.02, 0.3), a.shape), 0, 1
        )
        _, full = structural_similarity(
            a,
            b,
            win_size=size,
            use_sample_covariance=False,
            data_range=1,
            channel_axis=-1,
            full=True,
        )
        expected = full[size // 2, size // 2].mean()
        got = L.patch_ssim(torch.from_numpy(a).reshape(-1, 3), torch.from_numpy(b).reshape(-1, 3))
        assert got.item() == pytest.approx(expected, abs=1e-9)


def test_identical_patches_give_ssim_one_and_zero_loss():
    g = torch.Generator().manual_seed(2)
    ref = torch.rand(6, 121, 3, generator=g)
    assert torch.allclose(L.patch_ssim(ref, ref), torch.ones(6))
    valid = torch.ones(3, 6, 121, dtype=torch.bool)
    term = L.warping_loss(ref, ref.expand(3, 6, 121, 3), valid, torch.ones(6, dtype=torch.bool))
    assert term.value.abs() < 1e-6 and int(term.count) == 3 * 6 * 3


def test_warping_loss_counts_only_valid_visible_terms():
    g = torch.Generator().manual_seed(3)
    ref = torch.rand(2, 25, 3, generator=g)
    warped = torch.rand(1, 2, 25, 3, generator=g)
    valid = torch.ones(1, 2, 25, dtype=torch.bool)
    valid[0, 0, 0] = False  # a corner of the 5x5 patch of pixel 0 falls off the image
    visible = torch.tensor([True, True])
    term = L.warping_loss(ref, warped, valid, visible, sizes=(1, 5))
    assert int(term.count) == 3  # both pixels' 1x1 terms, only pixel 1's 5x5 term
    l1 = (ref[:, 12] - warped[0, :, 12]).abs().mean(-1)
    ssim = L.patch_ssim(ref[1], warped[0, 1])
    assert term.value.item() == pytest.approx(((l1.sum() + (1 - ssim) / 2) / 3).item(), rel=1e-5)
    hidden = L.warping_loss(ref, warped, valid, torch.tensor([False, True]), sizes=(1, 5))
    assert int(hidden.count) == 2
    with pytest.raises(ValueError):
        L.warping_loss(ref, warped, valid, visible, sizes=(7,))


def test_warping_loss_gradient_matches_finite_differences():
    # The fused backward of the patch moments against numerical derivatives, for both inputs.
    g = torch.Generator().manual_seed(5)
    ref = torch.rand(3, 25, 3, generator=g, dtype=torch.float64, requires_grad=True)
    warped = torch.rand(2, 3, 25, 3, generator=g, dtype=torch.float64, requires_grad=True)
    valid = torch.ones(2, 3, 25, dtype=torch.bool)
    visible = torch.ones(3, dtype=torch.bool)

    def loss(a, b):
        return L.warping_loss(a, b, valid, visible, sizes=(1, 3, 5)).value

    assert torch.autograd.gradcheck(loss, (ref, warped))


def test_zero_count_terms_are_zero_without_nan():
    ref = torch.rand(4, 121, 3, requires_grad=True)
    warped = torch.rand(2, 4, 121, 3)
    none = torch.zeros(4, dtype=torch.bool)
    term = L.warping_loss(ref, warped, torch.ones(2, 4, 121, dtype=torch.bool), none)
    assert term.value.item() == 0 and int(term.count) == 0
    term.value.backward()
    assert torch.isfinite(ref.grad).all()
    empty = L.render_l1(torch.zeros(0, 3), torch.zeros(0, 3))
    assert empty.value.item() == 0 and int(empty.count) == 0
    smooth = L.smoothness_loss(torch.zeros(0, 2, 2), torch.zeros(0, 2, 2, 3))
    assert smooth.value.item() == 0 and int(smooth.count) == 0


def test_visibility_needs_more_than_five_frames():
    valid = torch.zeros(10, 2, 9, dtype=torch.bool)
    valid[:5, 0, 4] = True  # pixel 0: centre inside exactly 5 frames
    valid[:6, 1, 4] = True  # pixel 1: 6 frames
    valid[:, 0, :4] = True  # other patch pixels do not count
    warp = L.WarpResult(torch.zeros(10, 2, 9, 2), valid)
    assert L.visibility_mask(warp).tolist() == [False, True]
    assert L.visibility_mask(warp, min_views=4).tolist() == [True, True]


def test_points_behind_a_camera_are_invalid_and_finite():
    cam = Camera(64, 48, 50.0, 50.0, 31.5, 23.5)
    turned = torch.diag(torch.tensor([-1.0, 1.0, -1.0, 1.0]))  # looks backwards
    T_l = torch.stack([torch.eye(4), turned, pose.exp_se3(torch.tensor([0, 0, 2.0, 0, 0, 0]))])
    depth = torch.tensor([2.0], requires_grad=True)
    warp = L.warp_patches(
        torch.tensor([[31.5, 23.5]]), depth, torch.eye(4), T_l, cam, L.patch_offsets(3)
    )
    assert warp.valid[0].all() and not warp.valid[1].any()
    assert not warp.valid[2].any()  # the plane passes through camera 2's centre
    assert torch.isfinite(warp.uv).all()
    warp.uv.sum().backward()
    assert torch.isfinite(depth.grad).all()


def test_smoothness_is_edge_aware():
    flat_rgb = torch.full((1, 2, 2, 3), 0.5)
    edge_rgb = flat_rgb.clone()
    edge_rgb[:, :, 1] = 1.0  # a strong colour edge between the two columns
    constant = torch.full((1, 2, 2), 3.0)
    assert L.smoothness_loss(constant, edge_rgb).value == 0
    step = torch.tensor([[[1.0, 2.0], [1.0, 2.0]]], requires_grad=True)  # depth step at the edge
    on_edge = L.smoothness_loss(step, edge_rgb)
    on_flat = L.smoothness_loss(step, flat_rgb)
    assert int(on_flat.count) == 4
    assert on_flat.value.item() == pytest.approx(2 / 4)
    assert on_edge.value < 0.6 * on_flat.value
    on_edge.value.backward()
    assert step.grad.abs().sum() > 0


def test_render_l1_is_the_mean_over_pixels_and_channels():
    rendered = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    observed = torch.tensor([[0.3, 0.0, 0.0], [1.0, 1.0, 0.4]])
    term = L.render_l1(rendered, observed)
    assert term.value.item() == pytest.approx((0.1 + 0.2) / 2) and int(term.count) == 2


def test_high_gradient_pixels_land_on_the_edge_and_respect_the_margin():
    image = torch.zeros(60, 80, 3)
    image[:, 50:] = 1.0  # one vertical edge between columns 49 and 50
    g = torch.Generator().manual_seed(4)
    uv = L.high_gradient_pixels(image, 40, g, margin=5)
    assert uv.shape == (40, 2) and uv.dtype == torch.int64
    assert ((uv[:, 0] - 49.5).abs() <= 1.5).all()
    assert len({tuple(p) for p in uv.tolist()}) == 40  # without replacement
    again = L.high_gradient_pixels(image, 40, torch.Generator().manual_seed(4), margin=5)
    assert torch.equal(uv, again)
    noise = torch.rand(30, 40, 3, generator=g)
    many = L.high_gradient_pixels(noise, 500, g, margin=5)  # more than the top 10%
    assert (many[:, 0] >= 5).all() and (many[:, 0] <= 34).all()
    assert (many[:, 1] >= 5).all() and (many[:, 1] <= 24).all()
    with pytest.raises(ValueError):
        L.high_gradient_pixels(noise, 10, g, margin=15)

"""Tests of gsmsdr_ns.blur (MAAN, HPKO, BlurField, DegradationProfile, ResolutionLossModel) on CPU, no nerfstudio.

Images are tiny (<= 32 x 48). Time and memory per configuration are measured by ``gsmsdr-bench memory``, not here.
"""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch
import torch.nn.functional as F
from kornia.color import linear_rgb_to_rgb, rgb_to_linear_rgb

from gsmsdr_ns.blur.degradation_config import DegradationConfig
from gsmsdr_ns.blur.degradation_model import DegradationModel
from gsmsdr_ns.blur.field import BlurField, BlurFieldConfig
from gsmsdr_ns.blur.hpko import HPKOScheduler, ScaleInfo, kernel_prior_logits, kernel_upsample_matrix
from gsmsdr_ns.blur.losses import DegradationAux, degradation_losses, mask_regulariser
from gsmsdr_ns.blur.maan import (
    GAKA,
    MCA,
    SAFM,
    BAGSFeatures,
    DepthwiseConv2d,
    RGBDFeatures,
    normalize_depth,
    positional_encoding_2d,
)
from gsmsdr_ns.blur.profile import DegradationProfile, ResolutionLossModel, effective_factor
from gsmsdr_ns.ops.grid_kernels import GridKernels
from gsmsdr_ns.ops.mixres import resolution_loss
from gsmsdr_ns.ops.pixel_kernels import apply_image_kernels, apply_pixel_kernels

NUM_VIEWS = 5


def reference_apply(image: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Per-pixel kernels via F.unfold on a replicate-padded image (the convention apply_pixel_kernels follows)."""
    B, C, H, W = image.shape
    K = int(round(weights.shape[1] ** 0.5))
    patches = F.unfold(F.pad(image, [K // 2] * 4, mode="replicate"), K).view(B, C, K * K, H, W)
    return (patches * weights[:, None]).sum(2)


def inputs(B: int = 2, H: int = 16, W: int = 24, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    render = torch.rand(B, 3, H, W, generator=g).requires_grad_()
    depth = (1.0 + 4.0 * torch.rand(B, 1, H, W, generator=g)).requires_grad_()
    view_ids = torch.arange(B) % NUM_VIEWS
    return render, depth, view_ids


def field(**kw) -> BlurField:
    torch.manual_seed(0)
    return BlurField(BlurFieldConfig(**kw), num_train_views=NUM_VIEWS)


def num_params(module: torch.nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


def has(module: torch.nn.Module, cls: type) -> bool:
    return any(isinstance(m, cls) for m in module.modules())


# ------------------------------------------------------------------------------------------------ import hygiene


def test_blur_package_imports_without_nerfstudio():
    code = (
        "import sys; import gsmsdr_ns.blur.field, gsmsdr_ns.blur.profile, gsmsdr_ns.blur.hpko, gsmsdr_ns.blur.maan; "
        "import gsmsdr_ns.blur.degradation_model, gsmsdr_ns.blur.preview, gsmsdr_ns.timing_hooks; "
        "bad = [m for m in sys.modules if m.split('.')[0] in ('nerfstudio', 'gsplat', 'tyro')]; "
        "assert not bad, bad"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


# ------------------------------------------------------------------------------------------------ shapes, ranges


@pytest.mark.parametrize("mode", ["full", "view"])
@pytest.mark.parametrize("scale,K", [(3, 5), (2, 9), (1, 17)])
def test_shapes_kernels_and_masks_at_each_scale(scale, K, mode):
    f = field(mode=mode)
    d = 2 ** (scale - 1)
    render, depth, view_ids = inputs(H=32 // d, W=48 // d)
    weights, mask = f(render, depth, view_ids, scale)
    assert f.kernel_size(scale) == K
    assert weights.shape == (2, K * K, 32 // d, 48 // d)
    assert mask.shape == (2, 1, 32 // d, 48 // d)
    torch.testing.assert_close(weights.sum(1), torch.ones(2, 32 // d, 48 // d))
    assert (weights > 0).all()
    assert ((mask > 0) & (mask < 1)).all() if mode == "full" else (mask == 1).all()  # view: no mask
    assert f.degrade(render, weights, mask).shape == render.shape


def test_invalid_inputs_raise():
    f = field()
    render, depth, view_ids = inputs()
    with pytest.raises(ValueError, match="scale"):
        f(render, depth, view_ids, 4)
    with pytest.raises(ValueError, match="depth"):
        f(render, None, view_ids, 3)
    with pytest.raises(ValueError, match="view_ids"):
        f(render, depth, torch.tensor([0, NUM_VIEWS]), 3)
    with pytest.raises(ValueError, match="render"):
        f(render[:, :2], depth, view_ids, 3)
    with pytest.raises(ValueError):
        BlurFieldConfig(kernel_sizes=(5, 8, 17))
    with pytest.raises(ValueError):
        BlurFieldConfig(mode="bogus")  # type: ignore[arg-type]


# ------------------------------------------------------------------------------------------------ degrade()


def test_zero_mask_and_identity_kernel_reproduce_the_render():
    render, _, _ = inputs()
    B, _, H, W = render.shape
    K = 9
    random_w = torch.softmax(torch.randn(B, K * K, H, W), dim=1)
    identity = torch.zeros(B, K * K, H, W)
    identity[:, K * K // 2] = 1.0
    zeros, ones = torch.zeros(B, 1, H, W), torch.ones(B, 1, H, W)
    assert torch.equal(BlurField.degrade(render, random_w, zeros), render)  # zero mask: exactly the render
    assert torch.equal(BlurField.degrade(render, identity, ones), render)  # identity kernel: exactly the render
    assert torch.equal(BlurField.degrade(render, identity, zeros), render)
    torch.testing.assert_close(BlurField.degrade(render, identity, torch.rand(B, 1, H, W)), render)


def test_degrade_matches_unfold_reference():
    render, _, _ = inputs(H=12, W=10)
    B, _, H, W = render.shape
    for K in (5, 9, 17):  # 17 > image height: replicate border everywhere
        w = torch.softmax(torch.randn(B, K * K, H, W), dim=1)
        m = torch.rand(B, 1, H, W)
        expected = m * reference_apply(render, w) + (1 - m) * render
        torch.testing.assert_close(BlurField.degrade(render, w, m), expected)


def test_linear_light_blur_reproduces_a_camera_blur_and_keeps_the_identities():
    # a camera averages irradiance: a black/white edge blurred in linear light, then sRGB-encoded
    render = torch.zeros(1, 3, 8, 12, dtype=torch.float64)
    render[..., 6:] = 1.0
    K = 5
    box = torch.zeros(1, K * K, 8, 12, dtype=torch.float64)
    box[:, 2 * K : 3 * K] = 1.0 / K  # horizontal 5-tap box (the kernel's middle row)
    ones = torch.ones(1, 1, 8, 12, dtype=torch.float64)
    camera = linear_rgb_to_rgb(reference_apply(rgb_to_linear_rgb(render), box))
    torch.testing.assert_close(BlurField.degrade(render, box, ones, linear_light=True), camera)
    # blurring the encoded values instead is a different image (the edge's mid-greys are darker)
    encoded = BlurField.degrade(render, box, ones)
    assert float((encoded - camera).abs().max()) > 0.1
    # zero mask: exactly the render; identity kernel: the render up to the encoding round trip
    x, _, _ = inputs()
    B, _, H, W = x.shape
    w = torch.softmax(torch.randn(B, 81, H, W), dim=1)
    assert torch.equal(BlurField.degrade(x, w, torch.zeros(B, 1, H, W), linear_light=True), x)
    identity = torch.zeros(B, 81, H, W)
    identity[:, 40] = 1.0
    torch.testing.assert_close(BlurField.degrade(x, identity, torch.ones(B, 1, H, W), linear_light=True), x)


def test_linear_light_gradients_are_finite_at_black_and_white():
    # the sRGB curve's power branch has an infinite slope at 0; kornia clamps it, this keeps it that way
    row = torch.tensor([0.0, 0.0, 0.0, 0.0, 1e-8, 0.04045, 0.5, 1.0])  # blurred black stays exactly 0
    render = row.repeat(3, 4, 1)[None].requires_grad_()  # [1, 3, 4, 8]
    w = torch.softmax(torch.randn(1, 9, 4, 8), dim=1).requires_grad_()
    out = BlurField.degrade(render, w, torch.full((1, 1, 4, 8), 0.7), linear_light=True)
    out.square().sum().backward()
    assert torch.isfinite(out).all() and torch.isfinite(render.grad).all() and torch.isfinite(w.grad).all()
    assert render.grad.abs().sum() > 0


# ------------------------------------------------------------------------------------------------ gradients


@pytest.mark.parametrize("mode", ["full", "msd_only", "re_only", "view"])
def test_gradients_reach_every_active_parameter_and_the_render(mode):
    f = field(mode=mode)
    for scale in f.scales:
        d = 2 ** (scale - 1)
        render, depth, view_ids = inputs(H=32 // d, W=48 // d, seed=scale)
        f.zero_grad(set_to_none=True)
        weights, mask = f(render, depth, view_ids, scale)
        out = f.degrade(render, weights, mask)
        target = torch.rand_like(out)
        loss = (out - target).abs().mean() + mask_regulariser(mask, DegradationConfig().mask_reg_weight)
        loss.backward()
        active = {id(p) for p in f.parameters_for_scale(scale)}
        for name, p in f.named_parameters():
            if id(p) in active:
                assert p.grad is not None and p.grad.abs().sum() > 0, f"{mode} s={scale}: no gradient for {name}"
            else:
                assert p.grad is None, f"{mode} s={scale}: {name} is not used at this scale but got a gradient"
        assert render.grad is not None and render.grad.abs().sum() > 0
        assert depth.grad is None  # inputs of the feature network are detached (BAGS)


# ------------------------------------------------------------------------------------------------ ablations, modes


@pytest.mark.parametrize(
    "switch,module_cls", [("gaka", GAKA), ("safm", SAFM), ("mca", MCA), ("rgbd", None), ("hpko", None)]
)
def test_each_ablation_switch_removes_its_parameters_and_still_runs(switch, module_cls):
    full, ablated = field(), field(**{switch: False})
    assert num_params(ablated) < num_params(full)
    if module_cls is not None:
        assert has(full, module_cls) and not has(ablated, module_cls)
    if switch == "rgbd":
        n = full.config.dims.feature_dim
        assert num_params(full) - num_params(ablated) == 9 * n  # one input channel less in the 3x3 SFE
        assert not ablated.uses_depth
    if switch == "hpko":
        assert ablated.scales == (1,) and ablated.kernel_size(1) == 17
    scale = ablated.scales[0]
    d = 2 ** (scale - 1)
    render, _, view_ids = inputs(H=32 // d, W=48 // d)
    depth = None if switch == "rgbd" else torch.rand(2, 1, 32 // d, 48 // d)
    weights, mask = ablated(render, depth, view_ids, scale)
    ablated.degrade(render, weights, mask).sum().backward()
    assert render.grad is not None


def test_rgbd_off_never_touches_depth():
    f = field(rgbd=False)
    render, _, view_ids = inputs()
    poisoned = torch.full((2, 1, 16, 24), float("nan"))
    weights, mask = f(render, poisoned, view_ids, 3)  # depth is ignored, not normalised
    assert torch.isfinite(weights).all() and torch.isfinite(mask).all()
    g = BlurField(BlurFieldConfig(), NUM_VIEWS, use_depth=False)  # profile says depth does not matter
    assert not g.uses_depth and num_params(g) == num_params(f)


def test_all_switches_off_still_runs():
    f = field(gaka=False, safm=False, mca=False, rgbd=False, hpko=False)
    render, _, view_ids = inputs()
    weights, mask = f(render, None, view_ids, 1)
    assert weights.shape == (2, 17 * 17, 16, 24)


def test_msd_only_and_re_only_modes():
    msd, re, full = field(mode="msd_only"), field(mode="re_only"), field()
    assert has(msd, BAGSFeatures) and not has(msd, RGBDFeatures)
    assert not (has(msd, GAKA) or has(msd, SAFM) or has(msd, MCA))
    assert msd.scales == (3, 2, 1)
    assert has(re, GAKA) and has(re, SAFM) and has(re, MCA) and not has(re, BAGSFeatures)
    assert re.scales == (1,)
    assert num_params(re) == num_params(field(hpko=False))  # RE-only is Table 6's "-HPKO"
    assert num_params(re) < num_params(full)
    motion = [DegradationProfile(motion=True)]
    assert DegradationModel(motion, re.config).hpko.scale_for_step(0) == ScaleInfo(1, 17, 1)
    assert DegradationModel(motion, msd.config).hpko.scale_for_step(0) == ScaleInfo(3, 5, 4)


def test_lite_size_is_smaller_and_explicit_widths_win():
    lite = field(size="lite")
    assert num_params(lite) < num_params(field()) / 2
    assert BlurFieldConfig(size="lite", feature_dim=24).dims.feature_dim == 24
    assert BlurFieldConfig().dims == (32, 32, 16, 64, 2)  # BAGS' 80-channel contextual features
    assert field().mcf.out_channels == 80


def test_shared_dict_hooks():
    f = field()
    groups = f.get_param_groups({"means": []})
    assert set(groups) == {"means", "blur_field", "blur_view_kernels"}  # the thin lens is the degradation model's
    owned = [p for g in ("blur_field", "blur_view_kernels") for p in groups[g]]
    assert len(owned) == len({id(p) for p in owned}) == len(list(f.parameters()))  # each parameter in one group
    paper = field(view_kernels=False).get_param_groups({})
    assert set(paper) == {"blur_field"}
    mask = torch.full((4, 4, 1), 0.5)
    image = torch.zeros(4, 4, 3)
    weights = DegradationConfig(mask_reg_weight=0.001).loss_weights
    losses = degradation_losses(DegradationAux(image, mask, learnt_mask=True), image, None, weights)
    torch.testing.assert_close(losses["blur_mask_reg"], torch.tensor(0.0005))
    assert degradation_losses(DegradationAux(image), image, None, weights) == {}  # the field did not run
    assert degradation_losses(DegradationAux(image, mask, learnt_mask=False), image, None, weights) == {}  # mode view


def test_kernel_centroids_measure_the_shift_a_kernel_applies():
    """A kernel's centre of mass is the shift it applies to an image: blurring a ramp by it moves the ramp by that
    much (away from the border), and a symmetric kernel has its centre on the pixel."""
    from gsmsdr_ns.ops.pixel_kernels import apply_pixel_kernels, kernel_centroids

    K, H, W = 5, 12, 14
    g = torch.Generator().manual_seed(0)
    weights = torch.softmax(torch.randn(2, K * K, H, W, generator=g, dtype=torch.float64), dim=1)
    centroids = kernel_centroids(weights)
    assert centroids.shape == (2, 2, H, W)
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    ramp = torch.stack([ys, xs])[None].expand(2, 2, H, W).contiguous()  # channel 0 = row, channel 1 = column
    moved = apply_pixel_kernels(ramp, weights) - ramp
    inner = (slice(None), slice(None), slice(K // 2, H - K // 2), slice(K // 2, W - K // 2))
    torch.testing.assert_close(moved[inner], centroids[inner])
    symmetric = (weights + weights.flip(1)) / 2  # the window mirrored through its centre
    assert kernel_centroids(symmetric).abs().max() < 1e-12


def test_kernel_centre_regulariser():
    centroids = torch.zeros(1, 2, 3, 3)
    centroids[0, 0] = 2.0  # every kernel two rows off its pixel
    image = torch.zeros(3, 3, 3)
    aux = DegradationAux(image, kernel_centroids=centroids)
    losses = degradation_losses(aux, image, None, DegradationConfig(kernel_centre_weight=0.5).loss_weights)
    torch.testing.assert_close(losses["blur_kernel_centre"], torch.tensor(2.0))  # 0.5 * 2^2
    off = DegradationConfig(kernel_centre_weight=0.0).loss_weights
    assert degradation_losses(aux, image, None, off) == {}  # 0: off
    with pytest.raises(ValueError, match="kernel_centre_weight"):
        DegradationConfig(kernel_centre_weight=-1.0)


# ------------------------------------------------------------------------------------------------ pure helpers


@pytest.mark.parametrize("kernel,dilation", [(5, 1), (7, 3)])
def test_depthwise_conv_matches_a_grouped_conv_in_values_and_gradients(kernel, dilation):
    torch.manual_seed(0)
    conv = DepthwiseConv2d(6, kernel, dilation).double()
    x = torch.randn(2, 6, 19, 23, dtype=torch.float64, requires_grad=True)
    y = conv(x)
    assert y.shape == x.shape and y.is_contiguous()
    pad = (kernel // 2) * dilation
    reference = F.conv2d(x, conv.weight, conv.bias, padding=pad, dilation=dilation, groups=6)
    torch.testing.assert_close(y, reference)
    g = torch.randn_like(y)
    got = torch.autograd.grad(y, (x, conv.weight, conv.bias), g)
    want = torch.autograd.grad(reference, (x, conv.weight, conv.bias), g)
    for a, b in zip(got, want):
        torch.testing.assert_close(a, b)


def test_positional_encoding_and_depth_normalisation():
    pe = positional_encoding_2d(4, 6, 16)
    assert pe.shape == (1, 16, 4, 6)
    # resolution independent: the centre of coarse pixel (i, j) is the centre of fine pixel (3i + 1, 3j + 1)
    torch.testing.assert_close(positional_encoding_2d(12, 18, 16)[..., 1::3, 1::3], pe)
    with pytest.raises(ValueError):
        positional_encoding_2d(4, 6, 6)
    d = torch.tensor([[[[2.0, 4.0], [float("inf"), 3.0]]]])
    n = normalize_depth(d)
    assert n.min() == 0 and n.max() <= 1 and torch.isfinite(n).all()


# ------------------------------------------------------------------------------------------------ kernel start


def kernel_rms_radius(weights: torch.Tensor) -> torch.Tensor:
    """[B, K*K, H, W] kernels -> [B, H, W] RMS distance of their mass from the centre tap (taps)."""
    K = int(round(weights.shape[1] ** 0.5))
    r = torch.arange(K, dtype=weights.dtype) - K // 2
    r2 = (r[:, None] ** 2 + r[None, :] ** 2).reshape(1, K * K, 1, 1)
    return (weights * r2).sum(1).sqrt()


def test_kernel_prior_is_a_centred_gaussian_with_learnable_tails():
    logits = kernel_prior_logits(17, sigma=0.5)
    w = torch.softmax(logits, 0).reshape(17, 17)
    assert int(w.argmax()) == 17 * 8 + 8 and float(w[8, 8]) > 0.5
    torch.testing.assert_close(w, w.flip(0)), torch.testing.assert_close(w, w.T)
    assert float(logits.min()) == -8.0  # floored: the far taps keep a gradient
    with pytest.raises(ValueError):
        kernel_prior_logits(5, sigma=0.0)


def test_kernel_upsample_matrix_is_exact_for_linear_logits():
    for coarse, fine in [(5, 9), (9, 17), (9, 13), (3, 9)]:
        M = kernel_upsample_matrix(coarse, fine).double()
        assert M.shape == (fine * fine, coarse * coarse)
        torch.testing.assert_close(M.sum(1), torch.ones(fine * fine, dtype=torch.float64))
        c = torch.arange(coarse, dtype=torch.float64) - coarse // 2
        u = torch.arange(fine, dtype=torch.float64) - fine // 2
        coarse_logits = (0.3 * c[:, None] - 0.7 * c[None, :]).reshape(-1)
        # a fine tap at u fine pixels reads the coarse kernel at u / 2 coarse pixels (clamped to its window)
        uc = (u / 2).clamp(-(coarse // 2), coarse // 2)
        expected = (0.3 * uc[:, None] - 0.7 * uc[None, :]).reshape(-1)
        torch.testing.assert_close(M @ coarse_logits, expected)


def test_untrained_field_simulates_almost_no_blur():
    """The kernels start as the narrow prior (not a near-uniform K x K blur): the untrained field's simulated
    degradation at the first trained (coarsest) scale stays close to the render, so the mask is not taught to
    switch the field off. Finer scales start from the coarser kernel re-sampled on their grid."""
    for progressive in (True, False):
        f = field(progressive=progressive)
        render, depth, view_ids = inputs(H=32, W=48)
        weights, mask = f(render, depth, view_ids, 3)
        assert float(kernel_rms_radius(weights.detach()).max()) < 1.0
        out = f.degrade(render, weights, mask)
        uniform = f.degrade(render, torch.full_like(weights, 1.0 / weights.shape[1]), mask)
        assert float((out - render).abs().mean()) < 0.5 * float((uniform - render).abs().mean())


def test_for_schedule_keeps_the_scales_the_resolution_schedule_visits():
    config = BlurFieldConfig()
    assert config.for_schedule(2).kernel_sizes == (5, 9, 17) and config.for_schedule(5).kernel_sizes == (5, 9, 17)
    assert config.for_schedule(1).kernel_sizes == (9, 17) and config.for_schedule(0).kernel_sizes == (17,)
    model = DegradationModel([DegradationProfile(motion=True)], config, num_downscales=1, resolution_schedule=100)
    sched = model.hpko
    assert sched.scale_for_step(0) == ScaleInfo(2, 9, 2) and sched.scale_for_step(100) == ScaleInfo(1, 17, 1)
    assert config.for_schedule(0, switch_steps=(10, 20)) is config  # explicit switch steps keep every scale
    assert BlurFieldConfig(hpko=False).for_schedule(1).kernel_sizes == (5, 9, 17)  # one scale (K_1) anyway


def test_progressive_heads_keep_the_blur_extent_across_a_scale_switch():
    """A wide blur learnt at the coarse scale is still there, twice as many (finer) pixels wide, right after
    HPKO switches to the finer scale; independent heads (progressive=False) restart from the prior."""
    render, depth, view_ids = inputs(H=32, W=48)
    coarse_render, coarse_depth = render[:, :, ::2, ::2], depth[:, :, ::2, ::2]
    radii = {}
    for progressive in (True, False):
        f = field(progressive=progressive)
        with torch.no_grad():  # "learnt" coarse kernels: a wide Gaussian (sigma 1.5 coarse pixels)
            f.heads.blur["3"].weight.zero_()
            f.heads.blur["3"].bias.copy_(kernel_prior_logits(5, sigma=1.5))
        # the coarsest kernel is evaluated on the half-resolution render, then the next scale on the full one
        wide = kernel_rms_radius(f(coarse_render, coarse_depth, view_ids, 3)[0].detach()).mean()
        finer = kernel_rms_radius(f(render, depth, view_ids, 2)[0].detach()).mean()
        radii[progressive] = (float(wide), float(finer))
    wide, finer = radii[True]
    assert 1.6 * wide < finer < 2.4 * wide, radii
    assert radii[False][1] < 0.6 * finer, radii


# ------------------------------------------------------------------------------------------------ scheduler


def splatfacto_downscale(step: int, num_downscales: int = 2, resolution_schedule: int = 3000) -> int:
    """``SplatfactoModel._get_downscale_factor`` in training mode (nerfstudio 1.1.5)."""
    return 2 ** max(num_downscales - step // resolution_schedule, 0)


def test_scheduler_follows_the_resolution_schedule():
    sched = HPKOScheduler()
    expected = {0: (3, 5, 4), 2999: (3, 5, 4), 3000: (2, 9, 2), 5999: (2, 9, 2), 6000: (1, 17, 1), 60000: (1, 17, 1)}
    for step, info in expected.items():
        assert sched.scale_for_step(step) == ScaleInfo(*info)
    for nd, rs in [(2, 3000), (1, 500), (0, 3000), (3, 1000)]:
        s = HPKOScheduler(num_downscales=nd, resolution_schedule=rs)
        for step in range(0, 5 * rs, rs // 4):
            d = splatfacto_downscale(step, nd, rs)
            info = s.scale_for_step(step)
            assert info == s.scale_for_downscale(d)
            assert info.downsample == min(d, 4)  # coarser renders than 1/4 keep the coarsest kernel
    assert sched.scale_for_downscale(1) == ScaleInfo(1, 17, 1)
    assert sched.scale_for_downscale(2.0) == ScaleInfo(2, 9, 2)
    with pytest.raises(ValueError):
        sched.scale_for_downscale(3)


def test_scheduler_switch_steps_and_warmup():
    sched = HPKOScheduler(switch_steps=(1000, 2500), warmup=250)
    assert [sched.scale_for_step(s).scale for s in (0, 999, 1000, 2499, 2500)] == [3, 3, 2, 2, 1]
    with pytest.raises(ValueError):
        HPKOScheduler(switch_steps=(3000,))
    assert sched.scale_at(0, 4) is None and sched.scale_at(249, 4) is None  # warm-up: blur field off
    assert sched.scale_at(250, 4) == ScaleInfo(3, 5, 4)
    assert sched.scale_at(1000, 4).scale == 2  # explicit switch steps win over the render's downscale
    following = HPKOScheduler(warmup=250)  # without them, the downscale the model renders at decides
    assert [following.scale_at(step, 1) for step in (0, 250, 10)] == [None, ScaleInfo(1, 17, 1), None]
    assert following.scale_at(1002, 2) == ScaleInfo(2, 9, 2)
    off = HPKOScheduler(enabled=False)
    assert off.scales == (1,)
    assert {off.scale_for_step(s) for s in (0, 3000, 9000)} == {ScaleInfo(1, 17, 1)}
    assert off.scale_for_downscale(4) == ScaleInfo(1, 17, 1)


def test_the_degradation_model_builds_a_scheduler_tied_to_the_model_schedule():
    options = DegradationConfig(warmup=100)
    model = DegradationModel([DegradationProfile(motion=True)], BlurFieldConfig(), options, 1, resolution_schedule=500)
    sched = model.hpko
    assert sched.warmup == 100 and sched.scale_for_step(0) == ScaleInfo(2, 9, 2)
    assert sched.scale_for_step(500) == ScaleInfo(1, 17, 1)


# ------------------------------------------------------------------------------------------------ profiles


def entry(effects, split="train", degraded=True):
    return {"split": split, "degraded": degraded, "effects": effects}


def test_profile_from_metadata_for_each_effect():
    motion = DegradationProfile.from_metadata(entry({"motion": {"model": "trajectory"}}))
    assert motion == DegradationProfile(motion=True)
    assert motion.needs_blur_field and motion.needs_depth and not motion.is_sharp
    defocus = DegradationProfile.from_metadata(entry({"defocus": {"model": "disk", "radius_px": 3}}))
    assert defocus == DegradationProfile(defocus=True) and defocus.needs_depth and defocus.needs_blur_field
    mix = DegradationProfile.from_metadata(entry({"mixres": {"factor": 4, "upsample": "bicubic"}}))
    assert mix.mixres_factor == 4 and mix.mixres_upsample == "bicubic"
    assert mix.needs_resolution_model and not mix.needs_blur_field and not mix.needs_depth
    noise = DegradationProfile.from_metadata(entry({"noise": {"sigma": 0.01, "model": "gaussian"}}))
    assert noise.noise and not noise.is_sharp and not noise.needs_blur_field
    both = DegradationProfile.from_metadata(entry({"motion": {}, "noise": {"sigma": 0.01}, "mixres": {"factor": 2}}))
    assert both == DegradationProfile(motion=True, noise=True, mixres_factor=2)
    # a dataparser record carries mixres_factor explicitly
    record = {"name": "a.png", "split": "train", "degraded": True, "effects": {"mixres": {"factor": 3}}}
    record["mixres_factor"] = 3
    assert DegradationProfile.from_metadata(record).mixres_factor == 3
    full_res = DegradationProfile.from_metadata(entry({"mixres": {"factor": 1}}))
    assert full_res.is_sharp and not full_res.needs_resolution_model
    with pytest.raises(ValueError, match="unknown degradation effect"):
        DegradationProfile.from_metadata(entry({"rain": {}}))


def test_sharp_and_unknown_profiles():
    for meta in (entry({}, split="test", degraded=False), entry({}, degraded=False), entry({"motion": {}}, "test")):
        p = DegradationProfile.from_metadata(meta)
        assert p.is_sharp and not p.needs_blur_field and not p.needs_depth and not p.needs_resolution_model
    unknown = {"name": "x.png", "split": "train", "degraded": None, "effects": {}, "mixres_factor": None}
    for meta in (None, unknown, entry({})):
        p = DegradationProfile.from_metadata(meta)
        assert p == DegradationProfile.unknown() and p.needs_blur_field and p.mixres_factor is None
        assert not p.blur_kind_known and not p.known_defocus


def test_an_estimate_that_names_both_blurs_leaves_the_kind_unknown():
    estimated = {"model": "estimated"}
    both = DegradationProfile.from_metadata(entry({"motion": dict(estimated), "defocus": dict(estimated)}))
    assert both.motion and both.defocus and not both.blur_kind_known and not both.known_defocus
    assert DegradationProfile.from_metadata(entry({"defocus": dict(estimated)})).known_defocus
    recorded = DegradationProfile.from_metadata(entry({"motion": {"model": "trajectory"}, "defocus": {}}))
    assert recorded.blur_kind_known and recorded.known_defocus
    assert not DegradationProfile.from_metadata(entry({"motion": dict(estimated)})).known_defocus


def test_profile_from_mode():
    unknown = {"split": "train", "degraded": None, "effects": {}}
    known = entry({"motion": {}, "mixres": {"factor": 2}})
    assert DegradationProfile.from_mode("auto", known) == DegradationProfile.from_metadata(known)
    assert DegradationProfile.from_mode("auto", unknown) == DegradationProfile.unknown()
    assert DegradationProfile.from_mode("motion", unknown) == DegradationProfile(motion=True)
    assert DegradationProfile.from_mode("defocus", unknown) == DegradationProfile(defocus=True)
    assert DegradationProfile.from_mode("defocus", known) == DegradationProfile(defocus=True, mixres_factor=2)
    assert DegradationProfile.from_mode("mixres", known) == DegradationProfile(mixres_factor=2)
    mix_unknown = DegradationProfile.from_mode("mixres", unknown)
    assert mix_unknown.mixres_factor is None and mix_unknown.needs_blur_field and not mix_unknown.needs_depth
    assert DegradationProfile.from_mode("sharp", known).is_sharp
    assert DegradationProfile.from_mode("motion", entry({}, split="test", degraded=False)).is_sharp
    with pytest.raises(ValueError):
        DegradationProfile.from_mode("rain", known)  # type: ignore[arg-type]
    with pytest.raises(ValueError):
        DegradationProfile(mixres_factor=0)


# ------------------------------------------------------------------------------------------------ resolution loss


def test_resolution_loss_model_identity_residual_equals_the_operator():
    g = torch.Generator().manual_seed(1)
    render = torch.rand(4, 3, 30, 41, generator=g).requires_grad_()
    factors = [4, 1, 2, 3]
    for num_views in (None, NUM_VIEWS):
        model = ResolutionLossModel(num_views=num_views, kernel_size=3)
        out = model(render, factors, torch.tensor([0, 1, 2, 4]))
        for i, f in enumerate(factors):
            torch.testing.assert_close(out[i : i + 1], resolution_loss(render[i : i + 1], f), rtol=0, atol=1e-6)
        torch.testing.assert_close(out[1:2], render[1:2], rtol=0, atol=1e-6)  # factor 1: untouched
    assert resolution_loss(render, 1) is render and resolution_loss(render, 0.5) is render
    # learnable: gradients reach the residual and the render; kernels keep summing to 1
    model = ResolutionLossModel(num_views=NUM_VIEWS, kernel_size=5)
    model(render, torch.tensor(factors), torch.tensor([0, 1, 2, 4])).square().mean().backward()
    assert model.residual.grad.abs().sum() > 0 and render.grad.abs().sum() > 0
    with torch.no_grad():
        model.residual.normal_()
    torch.testing.assert_close(model.kernels(torch.arange(NUM_VIEWS), NUM_VIEWS).sum(1), torch.ones(NUM_VIEWS))
    assert effective_factor(4, 2) == 2 and effective_factor(4, 4) == 1


def test_resolution_loss_is_the_degrade_tools_operator_and_accepts_fractional_factors():
    from gsmsdr_ns.ops.mixres import apply_mixres

    render = torch.rand(2, 3, 37, 50, generator=torch.Generator().manual_seed(2))
    for f in (1, 2, 3, 4):
        for up in ("bilinear", "bicubic"):
            assert torch.equal(resolution_loss(render, f, up), apply_mixres(render, f, up))
            assert torch.equal(resolution_loss(render, float(f), up), apply_mixres(render, f, up))
    # a factor 3 image seen at 1/2 resolution: shrunk to round(37 / 1.5) x round(50 / 1.5), between x1 and x2
    half = resolution_loss(render, 1.5)
    assert half.shape == render.shape and 0.0 <= float(half.min()) and float(half.max()) <= 1.0
    error = lambda x: float((x - render).abs().mean())  # noqa: E731
    assert 0.0 < error(half) < error(resolution_loss(render, 2))


def test_float64_field():
    f = field(size="lite").double()
    render, depth, view_ids = inputs(H=8, W=12)
    weights, mask = f(render.double(), depth.double(), view_ids, 3)
    assert weights.dtype == mask.dtype == torch.float64
    torch.testing.assert_close(weights.sum(1), torch.ones(2, 8, 12, dtype=torch.float64))


# ------------------------------------------------------------------------------------------------ per-view kernels


def test_view_kernels_give_each_view_its_own_kernel():
    """A per-view table shifts every pixel's kernel of that view (and only that view's); without the per-pixel
    heads the kernel is the same at every pixel of a view."""
    f = field(view_kernels=True, pixel_kernels=False)
    render, depth, _ = inputs(B=2, H=16, W=24)
    view_ids = torch.tensor([1, 3])
    with torch.no_grad():
        f.heads.view_logits["3"][3] = kernel_prior_logits(5, sigma=1.5) - kernel_prior_logits(5, sigma=0.5)
    weights, _ = f(render, depth, view_ids, 3)
    radius = kernel_rms_radius(weights.detach())
    assert float(radius[0].max()) < 1.0 < float(radius[1].min())
    torch.testing.assert_close(weights[:, :, :1, :1].expand_as(weights), weights)  # spatially uniform per view
    # with the per-pixel heads the view's table is added to their (spatially varying) logits
    g = field(view_kernels=True)
    weights, _ = g(render, depth, view_ids, 3)
    assert float((weights[:, :, 0, 0] - weights[:, :, 5, 7]).abs().max()) > 0


def test_view_kernels_train_only_the_drawn_views_in_their_own_group():
    f = field(view_kernels=True)
    groups = f.get_param_groups({})
    assert set(groups) == {"blur_field", "blur_view_kernels"}
    assert len(groups["blur_field"]) + len(groups["blur_view_kernels"]) == len(list(f.parameters()))
    for scale in f.scales:
        d = 2 ** (scale - 1)
        render, depth, _ = inputs(B=1, H=32 // d, W=48 // d)
        f.zero_grad(set_to_none=True)
        weights, mask = f(render, depth, torch.tensor([2]), scale)
        (f.degrade(render, weights, mask) - 0.5).abs().mean().backward()
        grad = f.heads.view_logits[str(scale)].grad
        assert grad[2].abs().sum() > 0 and grad[[0, 1, 3, 4]].abs().sum() == 0
    with pytest.raises(ValueError, match="pixel_kernels, view_kernels"):
        BlurFieldConfig(pixel_kernels=False, view_kernels=False)
    with pytest.raises(ValueError, match="view_ids"):
        f.heads(torch.zeros(1, f.mcf.out_channels, 4, 4), 1)


def test_view_mode_has_no_feature_network_and_blurs_by_one_kernel_per_view():
    """Mode "view": only per-view tables (all in the blur_view_kernels group), no MAAN; its expanded kernels are
    applied as a convolution that equals the per-pixel application of the same kernel everywhere."""
    f = field(mode="view")
    assert f.mcf is None and f.mca is None and not f.uses_depth
    assert set(f.get_param_groups({})) == {"blur_view_kernels"}
    assert num_params(f) == sum(NUM_VIEWS * k * k for k in (5, 9, 17))  # kernels only: the mask is 1
    render, _, view_ids = inputs(B=2, H=16, W=24)
    with torch.no_grad():
        f.heads.view_logits["3"][view_ids[1]] = kernel_prior_logits(5, sigma=1.5)
    weights, mask = f(render, None, view_ids, 3)
    assert weights.stride()[-2:] == (0, 0)  # expanded, not materialised
    radius = kernel_rms_radius(weights[:, :, :1, :1])
    assert float(radius[0]) < 1.0 < float(radius[1])
    assert torch.equal(mask, torch.ones(2, 1, 16, 24))
    fast = f.degrade(render, weights, mask)
    torch.testing.assert_close(fast, apply_pixel_kernels(render, weights.contiguous()))
    # training's form: each kernel as a grid of one cell, the same blur and the same gradient
    grid, grid_mask = f(render, None, view_ids, 3, dense=False)
    assert isinstance(grid, GridKernels) and grid.weights.shape == (2, 25, 1, 1) and grid.size == (16, 24)
    assert torch.equal(grid.dense(), weights) and torch.equal(grid_mask, mask)
    logits = f.heads.view_logits["3"]
    (dense_grad,) = torch.autograd.grad(f.degrade(render, weights, mask).square().sum(), logits)
    (grid_grad,) = torch.autograd.grad(f.degrade(render, grid, grid_mask).square().sum(), logits)
    torch.testing.assert_close(grid_grad, dense_grad)
    assert dense_grad[view_ids].abs().sum() > 0
    with pytest.raises(ValueError, match="view_ids"):
        f(render, None, torch.tensor([0, NUM_VIEWS]), 3)
    with pytest.raises(ValueError, match="no feature network"):
        f.features(render, None, view_ids)


def test_apply_image_kernels_matches_the_per_pixel_version_in_float64():
    g = torch.Generator().manual_seed(3)
    image = torch.rand(2, 3, 11, 14, dtype=torch.float64, generator=g, requires_grad=True)
    kernels = torch.rand(2, 49, dtype=torch.float64, generator=g, requires_grad=True)  # any weights, K = 7
    out = apply_image_kernels(image, kernels)
    ref = apply_pixel_kernels(image, kernels[:, :, None, None].expand(-1, -1, 11, 14).contiguous())
    torch.testing.assert_close(out, ref, rtol=0, atol=1e-12)
    grads = torch.autograd.grad(out.square().sum(), (image, kernels))
    ref_grads = torch.autograd.grad(ref.square().sum(), (image, kernels))
    for a, b in zip(grads, ref_grads):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-10)
    with pytest.raises(ValueError, match="kernels"):
        apply_image_kernels(image, kernels[:1])


@pytest.mark.parametrize("dtype, size, K", [(torch.float32, (37, 52), 17), (torch.float32, (5, 6), 9),
                                            (torch.bfloat16, (9, 12), 5)])  # fmt: skip
def test_apply_image_kernels_in_other_dtypes_and_kernels_larger_than_the_image(dtype, size, K):
    g = torch.Generator().manual_seed(4)
    image = torch.rand(1, 3, *size, generator=g).to(dtype)
    kernels = torch.softmax(torch.randn(1, K * K, generator=g), dim=1).to(dtype)
    out = apply_image_kernels(image, kernels)
    ref = apply_pixel_kernels(image.double(), kernels.double()[:, :, None, None].expand(-1, -1, *size).contiguous())
    assert out.dtype == dtype and out.shape == image.shape
    torch.testing.assert_close(out.double(), ref, rtol=0, atol=1e-5 if dtype == torch.float32 else 2e-2)

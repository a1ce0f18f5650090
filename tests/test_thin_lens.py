"""The blur field's thin lens (gsmsdr_ns.blur.defocus): disk kernels, the CoC formula, the learnable per-view lens.

No nerfstudio here: the core imports and trains on its own.
"""

from __future__ import annotations

import math

import pytest
import torch

from gsmsdr_ns.blur.defocus import ThinLensDefocus, lens_window, thin_lens_radius
from gsmsdr_ns.blur.degradation_config import DegradationConfig
from gsmsdr_ns.blur.degradation_model import DegradationModel
from gsmsdr_ns.blur.field import BlurField, BlurFieldConfig
from gsmsdr_ns.blur.preview import kernel_spread
from gsmsdr_ns.blur.profile import DegradationProfile
from gsmsdr_ns.degrade.kernels import defocus_radius
from gsmsdr_ns.ops.disk_kernels import occluding_disk_kernels, soft_disk_kernels
from gsmsdr_ns.ops.pixel_kernels import apply_pixel_kernels


def test_soft_disk_kernels_sum_to_one_and_grow_with_the_radius():
    radius = torch.tensor([0.0, 1.0, 2.0, 3.0]).reshape(1, 1, 1, 4)
    k = soft_disk_kernels(radius, 9)
    assert k.shape == (1, 81, 1, 4)
    torch.testing.assert_close(k.sum(1), torch.ones(1, 1, 4))
    assert float(k[0, 40, 0, 0]) > 0.99  # radius 0: the identity (an in-focus pixel stays sharp)
    spread = kernel_spread(k)[0, 0, 0]
    assert all(float(a) < float(b) for a, b in zip(spread[:-1], spread[1:])), spread
    # a disk of radius r has an RMS radius of about r / sqrt(2)
    assert abs(float(spread[3]) - 3.0 / math.sqrt(2.0)) < 0.35, spread
    # symmetric under flips (a disk)
    square = k[0, :, 0, 3].reshape(9, 9)
    torch.testing.assert_close(square, square.flip(0))
    torch.testing.assert_close(square, square.t())


def test_soft_disk_kernels_are_differentiable_in_the_radius_at_zero():
    radius = torch.zeros(1, 1, 2, 2, requires_grad=True)
    image = torch.rand(1, 3, 2, 2)
    image[..., 0, 0] = 1.0
    out = apply_pixel_kernels(torch.rand(1, 3, 2, 2), soft_disk_kernels(radius, 5))
    out.square().sum().backward()
    assert radius.grad is not None and torch.isfinite(radius.grad).all() and radius.grad.abs().sum() > 0


@pytest.mark.parametrize("bad", [dict(kernel_size=4), dict(kernel_size=0), dict(softness=0.0)])
def test_soft_disk_kernels_reject_bad_arguments(bad):
    args = {"kernel_size": 5, "softness": 0.15, **bad}
    with pytest.raises(ValueError):
        soft_disk_kernels(torch.zeros(1, 1, 2, 2), args["kernel_size"], args["softness"])


def test_occluding_disk_kernels_reduce_to_soft_disks_on_a_flat_scene_and_to_the_identity_in_focus():
    flat = torch.ones(1, 1, 6, 7)
    for r in (0.0, 1.3, 2.6):
        radius = torch.full((1, 1, 6, 7), r, dtype=torch.float64)
        k = occluding_disk_kernels(radius, flat.double(), 9)
        torch.testing.assert_close(k, soft_disk_kernels(radius, 9))
        torch.testing.assert_close(k.sum(1), torch.ones(1, 6, 7, dtype=torch.float64))
    depth = torch.rand(1, 1, 6, 7) + 0.5
    identity = occluding_disk_kernels(torch.zeros(1, 1, 6, 7), 1.0 / depth, 5)
    image = torch.rand(1, 3, 6, 7)
    assert torch.equal(apply_pixel_kernels(image, identity), image)


def test_occluding_disk_kernels_keep_a_sharp_foreground_and_spread_a_blurred_one():
    """Left half near (inverse depth 1), right half far (0.1). An in-focus near half takes nothing from the blurred
    far half; a blurred near half spreads its light over the in-focus far half."""
    inverse_depth = torch.full((1, 1, 5, 12), 0.1)
    inverse_depth[..., :6] = 1.0
    image = torch.zeros(1, 1, 5, 12)
    image[..., 6:] = 1.0  # far half bright
    sharp_near = torch.zeros(1, 1, 5, 12)
    sharp_near[..., 6:] = 3.0  # background blurred, foreground in focus
    out = apply_pixel_kernels(image, occluding_disk_kernels(sharp_near, inverse_depth, 9))
    assert float(out[..., :6].abs().max()) < 1e-6  # no background light on the in-focus foreground
    assert float(out[..., 6:].min()) > 0.99  # the background blurs only among itself
    # the gather-only disk of soft_disk_kernels lets the blurred background take in the dark foreground instead
    gathered = apply_pixel_kernels(image, soft_disk_kernels(sharp_near, 9))
    assert float(gathered[..., 6].mean()) < 0.8
    blurred_near = torch.zeros(1, 1, 5, 12)
    blurred_near[..., :6] = 3.0  # foreground blurred, background in focus
    image_near = 1.0 - image  # near half bright
    out = apply_pixel_kernels(image_near, occluding_disk_kernels(blurred_near, inverse_depth, 9))
    assert float(out[..., 6:8].min()) > 0.05  # the blurred foreground's light reaches over the background edge
    assert float(out[..., 11].max()) < 1e-3  # but not beyond its disk


def test_occluding_disk_kernels_are_differentiable_in_the_radius_and_check_shapes():
    radius = torch.full((1, 1, 4, 4), 1.5, requires_grad=True)
    inverse_depth = torch.rand(1, 1, 4, 4)
    kernels = occluding_disk_kernels(radius, inverse_depth, 5)
    apply_pixel_kernels(torch.rand(1, 3, 4, 4), kernels).square().sum().backward()
    assert radius.grad is not None and torch.isfinite(radius.grad).all() and radius.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="inverse_depth"):
        occluding_disk_kernels(torch.zeros(1, 1, 4, 4), torch.zeros(1, 1, 4, 5), 5)
    with pytest.raises(ValueError):
        occluding_disk_kernels(torch.zeros(1, 1, 4, 4), torch.zeros(1, 1, 4, 4), 4)


def test_thin_lens_radius_is_the_degradation_tools_circle_of_confusion():
    """Same optics as the degradation simulator: aperture = f_px * A / 2 per unit of inverse depth."""
    depth = torch.linspace(0.5, 20.0, 50).reshape(1, 1, 5, 10)
    f_px, aperture, focus = 300.0, 0.05, 3.0
    expected = defocus_radius(depth, f_px, aperture, focus)
    got = thin_lens_radius(1.0 / depth, torch.tensor([0.5 * f_px * aperture]), torch.tensor([1.0 / focus]))
    torch.testing.assert_close(got, expected.float())


def _depth_ramp(height: int = 32, width: int = 40) -> torch.Tensor:
    """[1, 1, H, W] depth from 1 (left) to 6 (right): a slanted wall, so the CoC varies across the image."""
    return torch.linspace(1.0, 6.0, width).expand(height, width)[None, None].clone()


def test_focus_starts_at_the_median_inverse_depth_once_and_is_checkpointed():
    lens = ThinLensDefocus(num_views=3)
    depth = _depth_ramp()
    lens.radius(depth, torch.tensor([1]))
    assert lens.focus_initialised.tolist() == [False, True, False]
    median = float((1.0 / depth).flatten().median())
    assert abs(float(lens.inverse_focus.detach()[1]) - median) < 1e-6
    lens.radius(depth * 2.0, torch.tensor([1]))  # seen before: kept
    assert abs(float(lens.inverse_focus.detach()[1]) - median) < 1e-6
    lens.eval()
    lens.radius(depth, torch.tensor([2]))  # a viewer preview (eval mode) leaves unseen views alone
    assert lens.focus_initialised.tolist() == [False, True, False]
    restored = ThinLensDefocus(num_views=3)
    restored.load_state_dict(lens.state_dict())
    assert restored.focus_initialised.tolist() == [False, True, False]
    assert torch.equal(restored.inverse_focus.detach(), lens.inverse_focus.detach())


def test_kernel_window_follows_the_largest_disk():
    lens = ThinLensDefocus(num_views=1, initial_aperture=0.01)
    depth = _depth_ramp()
    assert lens(depth, torch.tensor([0]), 17).shape[1] == 25  # barely blurs: radius < 0.5 -> a 5x5 window
    with torch.no_grad():
        lens.log_aperture.fill_(math.log(50.0))
    k = lens(depth, torch.tensor([0]), 17)
    assert k.shape[1] == 17 * 17  # capped at the scale's kernel
    torch.testing.assert_close(k.sum(1), torch.ones(1, 32, 40))
    half = lens(depth, torch.tensor([0]), 17, pixel_scale=0.5)  # same lens at half resolution: half the radius
    torch.testing.assert_close(lens.radius(depth, torch.tensor([0]), 0.5), 0.5 * lens.radius(depth, torch.tensor([0])))
    assert half.shape[1] == 17 * 17


def test_lens_rejects_bad_inputs():
    lens = ThinLensDefocus(num_views=2)
    with pytest.raises(ValueError, match="view_ids"):
        lens(_depth_ramp(), torch.tensor([2]), 9)
    with pytest.raises(ValueError, match="depth"):
        lens(torch.ones(1, 32, 40), torch.tensor([0]), 9)
    with pytest.raises(ValueError, match="max_kernel_size"):
        lens(_depth_ramp(), torch.tensor([0]), 8)
    with pytest.raises(ValueError):
        ThinLensDefocus(num_views=0)


def test_gradients_reach_the_lens_and_the_render_but_not_the_depth():
    lens = ThinLensDefocus(num_views=1, initial_aperture=2.0)
    render = torch.rand(1, 3, 32, 40, requires_grad=True)
    depth = _depth_ramp().requires_grad_(True)
    out = BlurField.blur(render, lens(depth, torch.tensor([0]), 9), linear_light=True)
    (out - torch.rand_like(out)).square().mean().backward()
    assert render.grad is not None and render.grad.abs().sum() > 0
    assert lens.log_aperture.grad is not None and lens.log_aperture.grad.abs() > 0
    assert lens.inverse_focus.grad is not None and lens.inverse_focus.grad.abs().sum() > 0
    assert depth.grad is None  # the lens reads the depth detached


def test_a_lens_is_recovered_from_a_defocused_photo():
    """Fit aperture and focus from one defocused image of a textured slanted wall (the per-view problem training
    solves): the fitted CoC map matches the true one to a fraction of a pixel."""
    torch.manual_seed(0)
    depth = _depth_ramp()
    sharp = torch.rand(1, 3, 32, 40)
    truth = ThinLensDefocus(num_views=1)
    with torch.no_grad():
        truth.log_aperture.fill_(math.log(4.0))  # CoC radius 0 (depth 2) to 2 px (depth 1), 1.3 px (depth 6)
        truth.inverse_focus.fill_(1.0 / 2.0)
        truth.focus_initialised.fill_(True)
        target = BlurField.blur(sharp, truth(depth, torch.tensor([0]), 11), linear_light=True)
        true_radius = truth.radius(depth, torch.tensor([0]))
    lens = ThinLensDefocus(num_views=1)
    optimizer = torch.optim.Adam(lens.parameters(), lr=0.05)
    for _ in range(300):
        out = BlurField.blur(sharp, lens(depth, torch.tensor([0]), 11), linear_light=True)
        loss = (out - target).abs().mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    error = (lens.radius(depth, torch.tensor([0])) - true_radius).abs().mean()
    assert float(error) < 0.1, (float(error), float(true_radius.mean()))


def test_the_degradation_model_builds_a_lens_only_when_asked():
    config = BlurFieldConfig(mode="view", kernel_sizes=(5, 9))
    defocus, motion = [DegradationProfile(defocus=True)] * 3, [DegradationProfile(motion=True)] * 3
    assert DegradationModel(defocus, config).thin_lens is not None
    assert DegradationModel(motion, config).thin_lens is None  # no image can be defocused
    assert DegradationModel(defocus, config, DegradationConfig(thin_lens=False)).thin_lens is None
    groups = DegradationModel(defocus, config).get_param_groups({})
    assert set(groups) == {"blur_view_kernels", "blur_defocus"} and len(groups["blur_defocus"]) == 3
    with pytest.raises(ValueError, match="thin_lens_initial_aperture"):
        DegradationConfig(thin_lens_initial_aperture=0.0)


def test_a_non_finite_depth_gives_nan_kernels_and_leaves_the_focus_alone():
    """NaN depth (a diverged render) must reach the loss as NaN, where training stops naming the step, and must not
    become a view's focus."""
    lens = ThinLensDefocus(num_views=1)
    depth = torch.full((1, 1, 8, 8), float("nan"))
    kernels = lens(depth, torch.tensor([0]), 9)
    assert kernels.shape == (1, 81, 8, 8) and torch.isnan(kernels).all()
    assert not bool(lens.focus_initialised[0]) and float(lens.inverse_focus.detach()[0]) == 0.0


@pytest.mark.parametrize("occlusion", [True, False])
def test_the_fused_lens_blur_is_the_kernels_applied(occlusion):
    """``ThinLensDefocus.blur`` (the fused op training uses) = ``BlurField.blur`` of the lens's kernels, values and
    the gradients of the render and of the lens's parameters."""
    torch.manual_seed(0)
    render = torch.rand(1, 3, 32, 40, requires_grad=True)
    target = torch.rand(1, 3, 32, 40)
    results = []
    for fused in (True, False):
        lens = ThinLensDefocus(num_views=2, initial_aperture=3.0, occlusion=occlusion)
        ids = torch.tensor([1])
        if fused:
            out = lens.blur(render, _depth_ramp(), ids, 11, pixel_scale=0.8, linear_light=True)
        else:
            out = BlurField.blur(render, lens(_depth_ramp(), ids, 11, pixel_scale=0.8), linear_light=True)
        (out - target).square().mean().backward()
        results.append((out.detach(), render.grad.clone(), lens.log_aperture.grad, lens.inverse_focus.grad))
        render.grad = None
    for a, b in zip(*results):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-7)


def test_lens_window_reads_the_largest_radius_on_the_cpu_only():
    radius = torch.full((1, 1, 4, 4), 0.3)
    assert lens_window(radius, 17, 0.25) == 5  # ceil(0.3 + 1.5) = 2
    assert lens_window(torch.full((1, 1, 4, 4), float("nan")), 17, 0.25) == 17
    # elsewhere (CUDA) reading it would wait for the device: the full window, the tensor's values never read
    assert lens_window(torch.empty(1, 1, 4, 4, device="meta"), 17, 0.25) == 17


def test_focus_initialisation_on_a_device_matches_the_cpu_rule_without_reading_a_value():
    """``_initialise_focus_on_device`` (the CUDA path: no host round trip) sets the same focus as the CPU path: new
    views get their median, seen views and non-finite renders are left alone."""
    depth = torch.stack([_depth_ramp()[0], 2.0 * _depth_ramp()[0], torch.full_like(_depth_ramp()[0], float("nan"))])
    inverse_depth = 1.0 / depth
    ids = torch.tensor([0, 2, 3])
    lenses = [ThinLensDefocus(num_views=4) for _ in range(2)]
    for lens in lenses:
        with torch.no_grad():
            lens.inverse_focus[2] = 0.7  # view 2 seen before
            lens.focus_initialised[2] = True
    lenses[0]._initialise_focus(ids, inverse_depth)
    lenses[1]._initialise_focus_on_device(ids, inverse_depth)
    assert lenses[1].focus_initialised.tolist() == [True, False, True, False]
    for a, b in zip(lenses[0].state_dict().values(), lenses[1].state_dict().values()):
        assert torch.equal(a, b)
    assert abs(float(lenses[1].inverse_focus[2]) - 0.7) < 1e-7


def test_the_degradation_model_blurs_through_the_fused_lens_as_through_its_kernels():
    model = DegradationModel([DegradationProfile(defocus=True)], BlurFieldConfig(mode="view", kernel_sizes=(5, 9)))
    lens = model.thin_lens
    with torch.no_grad():
        lens.log_aperture.fill_(math.log(4.0))
    render, depth, ids = torch.rand(1, 3, 20, 24), _depth_ramp(20, 24), torch.tensor([0])
    fused = model._lens_then_field(render, depth, ids, 1, 9, 1.0, lens=True, field=False, field_depth=False)
    kept = model._lens_then_field(render, depth, ids, 1, 9, 1.0, lens=True, field=False, field_depth=False,
                                  keep_lens_kernels=True)  # fmt: skip
    assert fused.lens_kernels is None and kept.lens_kernels is not None and kept.lens_kernels.shape[1] == 81
    torch.testing.assert_close(fused.image, kept.image, rtol=1e-5, atol=1e-7)
    assert not torch.allclose(fused.image, render, atol=1e-3)  # the lens did blur


def test_per_view_kernels_beyond_the_per_pixel_limit_leave_the_lens_at_that_limit(monkeypatch):
    """Mode view takes kernels up to MAX_VIEW_KERNEL_SIZE (one per image); the lens's disks stay per-pixel kernels,
    so its window stays at MAX_KERNEL_SIZE however large the field's kernel, in training and in the preview."""
    from gsmsdr_ns.blur.hpko import MAX_KERNEL_SIZE

    profiles = [DegradationProfile(defocus=True, motion=True)] * 2
    model = DegradationModel(profiles, BlurFieldConfig(mode="view", kernel_sizes=(13, 25, 49)))
    with torch.no_grad():
        model.thin_lens.log_aperture.fill_(math.log(400.0))  # disks far wider than any window
    windows = []  # the window K of every lens evaluation (the blur, the loss's mean disk, the preview)
    lens = model.thin_lens._lens

    def spy(*args, **kwargs):
        radius, inverse_depth, K = lens(*args, **kwargs)
        windows.append(K)
        return radius, inverse_depth, K

    monkeypatch.setattr(model.thin_lens, "_lens", spy)
    plan = model.plan(view_id=0, render_downscale=1, step=10**6)
    assert plan.thin_lens and plan.blur_scale is not None and plan.blur_scale.kernel_size == 49
    rgb = torch.rand(40, 48, 3, requires_grad=True)
    depth = _depth_ramp(40, 48)[0].permute(1, 2, 0)
    degraded, aux = model(rgb, depth, plan)
    assert windows and all(K == MAX_KERNEL_SIZE for K in windows)
    assert degraded.shape == (40, 48, 3) and bool(torch.isfinite(degraded).all())
    assert aux.kernel_mean is not None and bool(torch.isfinite(aux.kernel_mean).all())
    degraded.sum().backward()
    assert rgb.grad is not None and bool(torch.isfinite(rgb.grad).all())
    view_logits = model.blur_field.heads.view_logits["1"]
    assert view_logits.shape == (2, 49 * 49) and view_logits.grad is not None
    seen = len(windows)
    model.set_train_camera_centres(torch.eye(4)[:3].expand(2, 3, 4).clone())
    with torch.no_grad():
        preview = model.preview(rgb.detach(), depth, torch.zeros(3), 10**6)
    assert (
        len(windows) == seen + 1 and windows[-1] == MAX_KERNEL_SIZE and bool(torch.isfinite(preview["degraded"]).all())
    )

"""Numerical stability at the edges: extreme Gaussians, saturated kernels and masks, tiny images, LR spikes.

What must hold, for both CPU pixel kernels ("cpp" and "torch") where they apply:

* the rasterizer's forward and backward stay finite (colours, alphas, depth, the gradient of every input, the
  ``meta`` tensors and ``absgrad``), culled Gaussians get exactly zero gradient, and a pathological Gaussian (an
  overflowing covariance or centre, a NaN parameter) cannot change the gradients of the others;
* Adam steps (including one with every learning rate x1e4) and gsplat's ``DefaultStrategy`` refinement (every
  step, on the rasterizer's ``meta``, with and without absgrad) keep every parameter and optimizer state finite;
* the blur path (``apply_pixel_kernels``, the blur field's heads with saturated softmax / sigmoid, ``degrade``,
  the resolution-loss model) stays finite on 1x1 and one-pixel-thin images and on constant images;
* a real nerfstudio ``Trainer`` stops with ``NonFiniteLossError`` naming the step when a NaN reaches the loss (a
  NaN pixel in a training image, a NaN opacity), and survives a one-step learning-rate spike with finite
  parameters. (``test_plugin_model`` covers the model-level NaN guard on a bare model.)

Everything runs single-threaded: on a busy 2-core machine every OpenMP barrier of a multi-threaded op can wait for
a descheduled worker, which made the blur field ~100x slower here.

``run_autocast_checks(device)`` (not collected by pytest) repeats the blur and rasterizer checks under
``torch.autocast``; a GPU session runs it with ``python tests/test_stability.py cuda``.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Dict, List, Optional

import pytest
import torch
import torch.nn.functional as F
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gsmsdr_ns.blur.field import BlurField, BlurFieldConfig
from gsmsdr_ns.blur.hpko import ViewKernels
from gsmsdr_ns.blur.kernels import apply_pixel_kernels, apply_pixel_kernels_unfold
from gsmsdr_ns.blur.profile import ResolutionLossModel
from gsmsdr_ns.render import rasterization

BACKENDS = ("cpp", "torch")
NEAR = 0.25  # a power of two: z == NEAR survives the world-to-camera transform exactly
SETTINGS = dict(deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


@pytest.fixture(scope="module", autouse=True)
def single_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def all_finite(tensor: Optional[torch.Tensor]) -> bool:
    return tensor is not None and bool(torch.isfinite(tensor).all())


# --------------------------------------------------------------------------------------------------------------
# rasterizer: one render + backward with the model's activations (exp scales, sigmoid opacities)
# --------------------------------------------------------------------------------------------------------------


def pinhole(width: int, height: int, focal: float = 20.0):
    K = torch.tensor([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])
    return torch.eye(4)[None], K[None]


def render_with_grads(
    raw: Dict[str, torch.Tensor],
    width: int,
    height: int,
    backend: str,
    rasterize_mode: str = "classic",
    render_mode: str = "RGB+ED",
    with_background: bool = True,
    sh_degree: Optional[int] = None,
    near_plane: float = NEAR,
    seed: int = 0,
):
    """Render raw parameters like the model's (means, quats, log-scales "scales", opacity logits "opacities",
    colors) and backpropagate a random weighting of every output channel (colour, depth, alpha).

    The world-to-camera matrix requires grad too (nerfstudio's camera optimiser makes it a function of learnt pose
    offsets): one Gaussian's NaN reaching it would corrupt every Gaussian's render through the pose.

    Returns (colours, alphas, meta, gradients of the raw parameters and of "viewmats"; no colours gradient in
    depth-only modes)."""
    leaves = {name: value.detach().clone().requires_grad_() for name, value in raw.items()}
    viewmats, Ks = pinhole(width, height)
    viewmats.requires_grad_()
    gen = torch.Generator().manual_seed(seed)
    backgrounds = torch.rand(1, 3, generator=gen) if with_background else None
    colours, alphas, meta = rasterization(
        leaves["means"], leaves["quats"], torch.exp(leaves["scales"]), torch.sigmoid(leaves["opacities"]),
        leaves["colors"], viewmats, Ks, width, height, near_plane=near_plane, sh_degree=sh_degree, packed=False,
        backgrounds=backgrounds, render_mode=render_mode, absgrad=True, rasterize_mode=rasterize_mode,
        cpu_backend=backend,
    )  # fmt: skip
    meta["means2d"].retain_grad()
    weights = torch.rand(colours.shape, generator=gen), torch.rand(alphas.shape, generator=gen)
    loss = (colours * weights[0]).sum() + (alphas * weights[1]).sum()
    loss.backward()
    grads = {name: leaf.grad for name, leaf in leaves.items() if name != "colors" or render_mode not in ("D", "ED")}
    grads["viewmats"] = viewmats.grad
    return colours.detach(), alphas.detach(), meta, grads


def check_render(colours, alphas, meta, grads, n: int) -> None:
    """Everything finite, alphas in [0, 1], culled Gaussians without gradient."""
    assert all_finite(colours), "non-finite colours / depth"
    assert all_finite(alphas) and float(alphas.min()) >= 0.0 and float(alphas.max()) <= 1.0
    for name, grad in grads.items():
        assert all_finite(grad), f"gradient of {name}: {'missing' if grad is None else 'non-finite'}"
    for key in ("means2d", "conics", "depths", "opacities"):
        assert all_finite(meta[key]), f"meta[{key!r}] is not finite"
    assert all_finite(meta["means2d"].grad), "means2d.grad (DefaultStrategy's input) is missing or not finite"
    assert all_finite(getattr(meta["means2d"], "absgrad", None)), "means2d.absgrad is missing or not finite"
    radii = meta["radii"]
    assert radii.dtype == torch.int32 and int(radii.min()) >= 0
    culled = (radii == 0).all(dim=0)  # [N]
    for name in ("means", "quats", "scales", "opacities"):
        assert not grads[name][culled].any(), f"a culled Gaussian has a non-zero gradient of {name}"
    assert grads["means"].shape[0] == n


def gaussians(means, log_scales, quats=None, logits=None, colors=None, seed=0) -> Dict[str, torch.Tensor]:
    means = torch.as_tensor(means, dtype=torch.float32)
    n = means.shape[0]
    gen = torch.Generator().manual_seed(seed)
    return {
        "means": means,
        "scales": torch.as_tensor(log_scales, dtype=torch.float32).expand(n, 3).contiguous(),
        "quats": torch.randn(n, 4, generator=gen) if quats is None else torch.as_tensor(quats, dtype=torch.float32),
        "opacities": torch.zeros(n) if logits is None else torch.as_tensor(logits, dtype=torch.float32),
        "colors": torch.rand(n, 3, generator=gen) if colors is None else colors,
    }


SIZES = [(1, 1), (1, 23), (23, 1), (16, 12), (37, 19)]  # (width, height): one pixel, one row / column, tiles


@st.composite
def extreme_scenes(draw):
    """A handful of Gaussians, each extreme in some way: scales 1e-7..1e3, (near-)zero quaternions, saturated
    opacity logits, centres on / behind the near plane or far outside the frustum."""
    n = draw(st.integers(1, 8))
    floats = dict(allow_nan=False, allow_infinity=False)
    means, log_scales, quats, logits = [], [], [], []
    for _ in range(n):
        z = draw(
            st.one_of(
                st.just(NEAR), st.just(0.0), st.floats(-20.0, -1e-6, **floats), st.floats(0.26, 60.0, **floats),
                st.sampled_from([NEAR * (1 + 2**-20), NEAR * (1 - 2**-20), 1e6, 1e12]),
            )
        )  # fmt: skip
        # in the frustum (|x / z| < ~0.5) or far outside it, in either direction
        xy = draw(st.tuples(*[st.one_of(st.floats(-0.6, 0.6, **floats), st.sampled_from([-1e4, 1e3, 1e6]))] * 2))
        means.append([xy[0] * max(abs(z), 1.0), xy[1] * max(abs(z), 1.0), z])
        log_scales.append([math.log(10.0) * draw(st.floats(-7.0, 3.0, **floats)) for _ in range(3)])
        quats.append(
            draw(
                st.one_of(
                    st.just([0.0, 0.0, 0.0, 0.0]),
                    st.lists(st.floats(-1e-30, 1e-30, **floats), min_size=4, max_size=4),
                    st.lists(st.floats(-1.0, 1.0, **floats), min_size=4, max_size=4),
                )
            )
        )
        logits.append(draw(st.one_of(st.sampled_from([50.0, -50.0]), st.floats(-50.0, 50.0, **floats))))
    return gaussians(means, log_scales, quats, logits, seed=draw(st.integers(0, 2**16)))


@settings(max_examples=80, **SETTINGS)
@given(
    scene=extreme_scenes(),
    size=st.sampled_from(SIZES),
    rasterize_mode=st.sampled_from(["classic", "antialiased"]),
    render_mode=st.sampled_from(["RGB+ED", "RGB+D", "ED"]),
    with_background=st.booleans(),
    sh_degree=st.sampled_from([None, 1]),
)
def test_extreme_gaussians_render_and_backpropagate_finitely(
    scene, size, rasterize_mode, render_mode, with_background, sh_degree
):
    """Both pixel kernels: finite outputs and gradients (culled Gaussians exactly zero) and the same image."""
    width, height = size
    if sh_degree is not None:  # view-dependent colours: SH coefficients evaluated along camera-to-centre rays
        gen = torch.Generator().manual_seed(int(scene["colors"].sum() * 1e4))
        scene = {**scene, "colors": torch.randn(scene["means"].shape[0], 4, 3, generator=gen)}
    results = {}
    for backend in BACKENDS:
        out = render_with_grads(scene, width, height, backend, rasterize_mode, render_mode, with_background, sh_degree)
        check_render(*out, n=scene["means"].shape[0])
        results[backend] = out
    (c_cpp, a_cpp, _, _), (c_t, a_t, _, _) = results["cpp"], results["torch"]
    torch.testing.assert_close(a_cpp, a_t, atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(c_cpp, c_t, atol=1e-4, rtol=1e-4)


@pytest.mark.parametrize("backend", BACKENDS)
def test_near_plane_culling_follows_gsplat_and_stays_finite(backend):
    """gsplat keeps near_plane <= z <= far_plane: z exactly on the near plane renders, anything in front of it
    (z = 0, behind the camera) is culled with zero gradient."""
    z = [NEAR, NEAR * (1 - 2**-20), 0.0, -1e-30, -1.0, -1e6, 2.0]
    scene = gaussians([[0.0, 0.0, v] for v in z], math.log(0.05))
    colours, alphas, meta, grads = render_with_grads(scene, 16, 12, backend)
    check_render(colours, alphas, meta, grads, n=len(z))
    assert meta["radii"][0].gt(0).tolist() == [True, False, False, False, False, False, True]
    assert float(meta["depths"][0, 0]) == NEAR


@pytest.mark.parametrize("backend", BACKENDS)
def test_zero_near_plane_and_vanishing_depth(backend):
    """near_plane = 0: z = 0 is culled (no division by zero), z = 1e-30 overflows the Jacobian and is culled."""
    z = [0.0, 1e-30, 1e-20, 1e-6, 1.0]
    scene = gaussians([[0.0, 0.0, v] for v in z], math.log(0.05))
    colours, alphas, meta, grads = render_with_grads(scene, 16, 12, backend, near_plane=0.0)
    check_render(colours, alphas, meta, grads, n=len(z))
    assert int(meta["radii"][0, 0]) == 0 and int(meta["radii"][0, -1]) > 0


@pytest.mark.parametrize("backend", BACKENDS)
def test_footprint_wider_than_int32_is_clamped_not_wrapped(backend):
    """A 1e3 scale on the near plane seen with a 1e7-pixel focal length has a 3-sigma radius of ~1e11 pixels:
    radii are int32, and the cast used to wrap it to a negative number (the Gaussian silently vanished and gsplat's
    DefaultStrategy got a negative radius). It is clamped instead, like CUDA's saturating conversion."""
    log_scales = [[math.log(1e3)] * 3, [math.log(1e-7)] * 3]
    leaves = gaussians([[0.0, 0.0, 0.3], [0.0, 0.0, 2.0]], log_scales, logits=[50.0, 0.0])
    leaves = {name: value.requires_grad_() for name, value in leaves.items()}
    K = torch.tensor([[[5e5, 0.0, 8.0], [0.0, 5e5, 6.0], [0.0, 0.0, 1.0]]])
    colours, alphas, meta = rasterization(
        leaves["means"], leaves["quats"], torch.exp(leaves["scales"]), torch.sigmoid(leaves["opacities"]),
        leaves["colors"], torch.eye(4)[None], K, 16, 12, near_plane=NEAR, packed=False, cpu_backend=backend,
    )  # fmt: skip
    (colours.sum() + alphas.sum()).backward()
    assert int(meta["radii"][0, 0]) >= 2**30 and int(meta["radii"].min()) >= 0
    assert float(alphas.min()) > 0.99  # it covers the whole image
    for name, leaf in leaves.items():
        assert all_finite(leaf.grad), name


PATHOLOGICAL = {
    # scales whose covariance (or its projection) overflows float32
    "scale 1e19": ([0.05, 0.0, 2.0], math.log(1e19), None),
    "scale 1e20": ([0.0, 0.05, 2.0], math.log(1e20), None),
    "log-scale 50": ([0.0, 0.0, 3.0], 50.0, None),
    "mixed 1e-7 / 1e19": ([-0.1, 0.0, 2.0], [math.log(1e-7), math.log(1e19), 0.0], None),
    # centres whose projection overflows float32
    "x = 1e38": ([1e38, 0.0, 2.0], math.log(0.1), None),
    "y = -3e38": ([0.0, -3e38, 2.0], math.log(0.1), None),
    # NaN parameters: culled like gsplat does; only their own gradient may be NaN
    "NaN mean": ([math.nan, 0.0, 2.0], math.log(0.1), None),
    "NaN scale": ([0.0, 0.0, 2.0], math.nan, None),
    "NaN quaternion": ([0.0, 0.0, 2.0], math.log(0.1), [math.nan, 0.0, 0.0, 1.0]),
}


@pytest.mark.parametrize("rasterize_mode", ["classic", "antialiased"])
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("case", sorted(PATHOLOGICAL))
def test_pathological_gaussian_is_culled_and_cannot_touch_the_others(case, backend, rasterize_mode):
    """Regression: an overflowing covariance gave NaN gradients (0 * inf in the Jacobian's backward) to the means,
    quaternions and scales of *every* Gaussian, which an optimizer step then spread to the whole scene; it, a NaN
    centre or a NaN scale also gave a NaN gradient to the camera pose (the world-to-camera rotation)."""
    gen = torch.Generator().manual_seed(3)
    sh = torch.randn(4, 4, 3, generator=gen)  # degree-1 SH colours: the centres also enter the view directions
    good = gaussians([[0.0, 0.0, 2.0], [0.1, -0.05, 2.5], [-0.2, 0.1, 3.0]], math.log(0.1), colors=sh[:3], seed=3)
    mean, log_scale, quat = PATHOLOGICAL[case]
    bad = gaussians([mean], log_scale, quats=None if quat is None else [quat], logits=[2.0], colors=sh[3:], seed=4)
    both = {name: torch.cat([good[name], bad[name]]) for name in good}
    colours, alphas, meta, grads = out = render_with_grads(both, 16, 12, backend, rasterize_mode, sh_degree=1)
    reference = render_with_grads(good, 16, 12, backend, rasterize_mode, sh_degree=1)
    assert int(meta["radii"][0, -1]) == 0, f"{case}: the pathological Gaussian was not culled"
    torch.testing.assert_close(colours, reference[0], msg=f"{case}: the image changed")
    torch.testing.assert_close(alphas, reference[1], msg=f"{case}: the alphas changed")
    for name, grad in grads.items():
        others = grad if name == "viewmats" else grad[:-1]
        torch.testing.assert_close(others, reference[3][name], msg=lambda m: f"{case}: gradient of {name}: {m}")
    if not case.startswith("NaN"):  # a NaN parameter may get a NaN gradient itself (gsplat: garbage in)
        check_render(*out, n=4)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("opacity", ["saturated", "faint"])
def test_four_thousand_gaussians_at_one_pixel(backend, opacity):
    """4000 Gaussians in one tile, all over the same pixel, at 4000 depths: saturated ones stop compositing after
    a few (transmittance < 1e-4), faint ones (just above 1/255) composite ~2000 before stopping."""
    n = 4000
    gen = torch.Generator().manual_seed(5)
    depth = torch.linspace(1.0, 5.0, n)
    means = torch.stack([0.01 * torch.randn(n, generator=gen), 0.01 * torch.randn(n, generator=gen), depth], dim=-1)
    logits = torch.full((n,), 50.0 if opacity == "saturated" else math.log(0.01 / 0.99))
    scene = gaussians(means, math.log(0.02), logits=logits, seed=6)
    scene["scales"] = scene["scales"] + torch.linspace(-1.0, 1.0, n)[:, None]
    out = render_with_grads(scene, 16, 16, backend, render_mode="RGB+ED")
    check_render(*out, n=n)
    colours, alphas, meta, _ = out
    assert int(meta["isect_offsets"].numel()) == 1 and meta["flatten_ids"].numel() == n  # one tile, all in it
    # compositing stops before the transmittance reaches 1e-4: 0.999 after the first saturated Gaussian
    assert 0.999 - 1e-6 <= float(alphas.max()) < 1.0
    other = render_with_grads(scene, 16, 16, "torch" if backend == "cpp" else "cpp", render_mode="RGB+ED")
    torch.testing.assert_close(colours, other[0], atol=1e-4, rtol=1e-4)


# --------------------------------------------------------------------------------------------------------------
# optimizer steps, learning-rate spike and DefaultStrategy refinement on the rasterizer's meta
# --------------------------------------------------------------------------------------------------------------

LRS = {"means": 1.6e-4, "scales": 5e-3, "quats": 1e-3, "opacities": 5e-2, "colors": 2.5e-3}  # splatfacto's
TARGETS = {
    "black": lambda h, w, g: torch.zeros(h, w, 3),
    "white": lambda h, w, g: torch.ones(h, w, 3),
    "constant": lambda h, w, g: torch.full((h, w, 3), 0.37),
    "random": lambda h, w, g: torch.rand(h, w, 3, generator=g),
}


def extreme_parameters(n: int, seed: int) -> Dict[str, torch.Tensor]:
    """n Gaussians in front of the camera plus one of each extreme: tiny / huge scales, zero quaternion,
    saturated opacities, on the near plane, behind the camera, far outside the frustum."""
    gen = torch.Generator().manual_seed(seed)
    z = 1.0 + 3.0 * torch.rand(n, generator=gen)
    means = torch.stack([(torch.rand(n, generator=gen) - 0.5) * z, (torch.rand(n, generator=gen) - 0.5) * z, z], -1)
    extra = torch.tensor([[0.0, 0.0, NEAR], [0.1, 0.0, 0.0], [0.0, 0.1, -2.0], [1e6, 0.0, 2.0], [0.0, 0.0, 2.0],
                          [0.1, 0.1, 2.0], [-0.1, 0.1, 2.0], [0.1, -0.1, 1.5]])  # fmt: skip
    log_scales = math.log(10.0) * (-7.0 + 10.0 * torch.rand(n + 8, 3, generator=gen))
    log_scales[-4] = math.log(1e3)
    log_scales[-3] = math.log(1e-7)
    quats = torch.randn(n + 8, 4, generator=gen)
    quats[-2] = 0.0
    quats[-1] = 1e-30
    logits = 4.0 * torch.randn(n + 8, generator=gen)
    logits[: (n + 8) // 3] = 50.0
    logits[-1] = -50.0
    return {
        "means": torch.cat([means, extra]),
        "scales": log_scales,
        "quats": quats,
        "opacities": logits[:, None],
        "colors": torch.logit(torch.rand(n + 8, 3, generator=gen).clamp(0.01, 0.99)),
    }


def check_finite_state(params, optimizers, strategy_state, what: str) -> None:
    for name, param in params.items():
        assert all_finite(param.data), f"{what}: parameter {name} is not finite"
        for key, value in optimizers[name].state.get(param, {}).items():
            if isinstance(value, torch.Tensor):
                assert all_finite(value), f"{what}: Adam state {key} of {name} is not finite"
    for key in ("grad2d", "count", "radii"):
        if strategy_state.get(key) is not None:
            assert all_finite(strategy_state[key]), f"{what}: DefaultStrategy state {key} is not finite"


@pytest.mark.parametrize("absgrad", [False, True])
@pytest.mark.parametrize("backend", BACKENDS)
@settings(max_examples=5, **SETTINGS)
@given(
    target=st.sampled_from(sorted(TARGETS)),
    size=st.sampled_from([(1, 1), (24, 1), (1, 17), (20, 14)]),
    spike_step=st.integers(1, 4),
    seed=st.integers(0, 2**16),
)
def test_adam_lr_spike_and_densification_keep_everything_finite(backend, absgrad, target, size, spike_step, seed):
    """Six Adam steps from extreme parameters, one of them with every learning rate x1e4, each followed by
    DefaultStrategy's refinement (grow, split, prune, opacity reset every 3 steps) on the rasterizer's meta."""
    from gsplat.strategy import DefaultStrategy

    width, height = size
    params = torch.nn.ParameterDict({k: torch.nn.Parameter(v) for k, v in extreme_parameters(16, seed).items()})
    optimizers = {name: torch.optim.Adam([param], lr=LRS[name], eps=1e-15) for name, param in params.items()}
    strategy = DefaultStrategy(
        refine_start_iter=0, refine_every=1, reset_every=3, refine_stop_iter=10_000, refine_scale2d_stop_iter=10_000,
        grow_grad2d=1e-5, absgrad=absgrad, prune_scale3d=50.0, verbose=False,
    )  # fmt: skip
    strategy.check_sanity(params, optimizers)
    state = strategy.initialize_state(scene_scale=1.0)
    gen = torch.Generator().manual_seed(seed)
    image = TARGETS[target](height, width, gen)
    viewmats, Ks = pinhole(width, height)
    for step in range(1, 7):
        colours, alphas, meta = rasterization(
            params["means"], params["quats"], torch.exp(params["scales"]), torch.sigmoid(params["opacities"][:, 0]),
            torch.sigmoid(params["colors"]), viewmats, Ks, width, height, near_plane=NEAR, packed=False,
            absgrad=absgrad, cpu_backend=backend,
        )  # fmt: skip
        strategy.step_pre_backward(params, optimizers, state, step, meta)
        loss = (colours[0] - image).abs().mean() + 0.2 * (colours[0] - image).square().mean() + 0.01 * alphas.mean()
        assert math.isfinite(loss.item()), f"step {step}: loss {loss.item()}"
        loss.backward()
        for name, param in params.items():
            assert all_finite(param.grad), f"step {step}: gradient of {name} is missing or not finite"
        scale = 1e4 if step == spike_step else 1.0
        for name, optimizer in optimizers.items():
            for group in optimizer.param_groups:
                group["lr"] = LRS[name] * scale
            optimizer.step()
            optimizer.zero_grad(set_to_none=True)
        check_finite_state(params, optimizers, state, f"step {step} after Adam (lr x{scale:g})")
        strategy.step_post_backward(params, optimizers, state, step, meta, packed=False)
        check_finite_state(params, optimizers, state, f"step {step} after refinement")
        assert all(len(p) == len(params["means"]) for p in params.values())
    assert len(params["means"]) > 0


# --------------------------------------------------------------------------------------------------------------
# blur: per-pixel kernels, the blur field's heads, degrade and the resolution-loss model
# --------------------------------------------------------------------------------------------------------------


@settings(max_examples=30, **SETTINGS)
@given(
    hw=st.sampled_from([(1, 1), (1, 7), (7, 1), (2, 3), (5, 6)]),
    K=st.sampled_from([1, 3, 5, 9]),
    backend=st.sampled_from(BACKENDS),
    sign=st.sampled_from([1.0, -1.0]),
    image_kind=st.sampled_from(["black", "white", "constant", "random"]),
    seed=st.integers(0, 2**16),
)
def test_saturated_kernels_and_masks_on_tiny_images(hw, K, backend, sign, image_kind, seed):
    """Kernel logits of +-1e4 (the softmax saturates to one-hot kernels or to a uniform one) and mask logits of
    +-1e4 (masks exactly 0 or 1) on 1x1 / one-row / one-column images: finite values and gradients, the C++ and
    PyTorch kernels agree with the unfold reference."""
    H, W = hw
    gen = torch.Generator().manual_seed(seed)
    image = {
        "black": torch.zeros(2, 3, H, W),
        "white": torch.ones(2, 3, H, W),
        "constant": torch.full((2, 3, H, W), 0.6),
        "random": torch.rand(2, 3, H, W, generator=gen),
    }[image_kind].requires_grad_()
    logits = (sign * 1e4 * torch.randn(2, K * K, H, W, generator=gen).sign()).requires_grad_()
    mask_logits = (1e4 * torch.randn(2, 1, H, W, generator=gen).sign()).requires_grad_()
    weights, mask = F.softmax(logits, dim=1), torch.sigmoid(mask_logits)
    assert all_finite(weights) and bool(((mask == 0) | (mask == 1)).all())
    blurred = apply_pixel_kernels(image, weights, backend=backend)
    degraded = BlurField.degrade(image, weights, mask)
    target = torch.rand(degraded.shape, generator=gen)
    ((degraded - target).abs().mean() + blurred.square().mean()).backward()
    for name, t in (("blurred", blurred), ("degraded", degraded), ("image grad", image.grad),
                    ("logit grad", logits.grad), ("mask logit grad", mask_logits.grad)):  # fmt: skip
        assert all_finite(t), f"{name} is not finite"
    torch.testing.assert_close(blurred, apply_pixel_kernels_unfold(image.detach(), weights.detach()))
    # normalised kernels keep a constant image constant, and stay within the image's range
    assert float(blurred.min()) >= float(image.min()) - 1e-5 and float(blurred.max()) <= float(image.max()) + 1e-5


@pytest.mark.parametrize("backend", BACKENDS)
def test_unnormalised_weights_of_1e4(backend):
    image = torch.rand(1, 3, 1, 9, requires_grad=True)
    weights = torch.full((1, 25, 1, 9), 1e4).requires_grad_()
    out = apply_pixel_kernels(image, weights, backend=backend)
    out.sum().backward()
    assert all_finite(out) and all_finite(image.grad) and all_finite(weights.grad)
    torch.testing.assert_close(out, apply_pixel_kernels_unfold(image.detach(), weights.detach()))


def saturate_heads(field: BlurField, scale: int, hot: int, mask_sign: float) -> None:
    """Make the scale's heads output kernel logits of +-1e4 (one-hot at window index ``hot``) and mask logits of
    ``mask_sign * 1e4`` regardless of the features."""
    with torch.no_grad():
        if isinstance(field.heads, ViewKernels):  # mode view: per-view tables, no heads
            field.heads.view_logits[str(scale)].fill_(-1e4)
            field.heads.view_logits[str(scale)][:, hot] = 1e4
            return  # no mask to saturate: mode view's mask is 1
        blur, mask = field.heads.blur[str(scale)], field.heads.mask[str(scale)]
        blur.weight.mul_(1e-3)
        blur.bias.fill_(-1e4)
        blur.bias[hot] = 1e4
        mask.weight.mul_(1e-3)
        mask.bias.fill_(mask_sign * 1e4)


@pytest.mark.parametrize("mode", ["full", "msd_only", "re_only", "view"])
def test_blur_field_saturated_heads_on_tiny_and_constant_images(mode):
    """The MAAN / BAGS feature networks and the HPKO heads on 1x1, one-row and one-column renders of black, white
    and constant images (zero-variance features for every norm layer), with heads saturated to one-hot kernels
    and 0 / 1 masks. Regression: msd_only's InstanceNorm2d raised on a 1x1 render while training."""
    torch.manual_seed(0)
    config = BlurFieldConfig(mode=mode, size="lite", kernel_sizes=(3, 5, 9), feature_dim=8, mid_channels=8)
    sizes = [(1, 1), (1, 6), (6, 1), (4, 5)]
    renders = {"black": 0.0, "white": 1.0, "constant": 0.42}
    for scale in config.setup(num_train_views=2).scales:
        for mask_sign in (1.0, -1.0):
            field = config.setup(num_train_views=2).train()
            K = field.kernel_size(scale)
            hot = (K * K) // 2 + 1  # one pixel to the right: the output is the render shifted left (border clamped)
            saturate_heads(field, scale, hot, mask_sign)
            for (H, W) in sizes:
                for kind, value in renders.items():
                    render = torch.full((1, 3, H, W), value, requires_grad=True)
                    depth = torch.full((1, 1, H, W), 3.0)  # constant depth: normalises to zeros
                    field.zero_grad(set_to_none=True)
                    kernels, mask = field(render, depth, torch.tensor([1]), scale)
                    degraded = BlurField.degrade(render, kernels, mask, linear_light=True)  # black: sRGB curve at 0
                    loss = (degraded - 0.5).abs().mean() + field.mask_loss(mask)
                    loss.backward()
                    what = f"{mode} scale {scale} mask {mask_sign:+g} {H}x{W} {kind}"
                    assert all_finite(kernels) and all_finite(mask) and all_finite(degraded), what
                    assert bool(((mask == 0) | (mask == 1)).all()), what
                    assert torch.equal(kernels.argmax(dim=1), torch.full((1, H, W), hot)), what
                    torch.testing.assert_close(degraded, render.detach(), msg=what)  # constant render, any kernel
                    assert all_finite(render.grad), what
                    bad = [n for n, p in field.named_parameters() if p.grad is not None and not all_finite(p.grad)]
                    assert not bad, f"{what}: non-finite gradients of {bad}"


@pytest.mark.parametrize("factor", [1.0, 2.0, 4.0, 100.0])
def test_resolution_loss_model_on_tiny_and_constant_images(factor):
    model = ResolutionLossModel(num_views=2, kernel_size=3)
    with torch.no_grad():
        model.residual.normal_(0.0, 10.0)  # a far-from-identity residual kernel
    for (H, W) in [(1, 1), (1, 9), (9, 1), (6, 5)]:
        for value in (0.0, 1.0, 0.3):
            render = torch.full((2, 3, H, W), value, requires_grad=True)
            out = model(render, [factor, 1.0], torch.tensor([0, 1]))
            model.zero_grad(set_to_none=True)
            (out - 0.5).abs().mean().backward()
            assert all_finite(out) and all_finite(render.grad) and all_finite(model.residual.grad), (H, W, value)
            torch.testing.assert_close(out, render.detach())  # residual kernels sum to 1: constants pass through


# --------------------------------------------------------------------------------------------------------------
# the real nerfstudio Trainer: NaN guard and learning-rate spike
# --------------------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tiny_training_scene(tmp_path_factory) -> Path:
    from conftest import make_tiny_scene

    return make_tiny_scene(tmp_path_factory.mktemp("stability") / "scene", num_views=4, width=32, height=24,
                           num_points=120)  # fmt: skip


@pytest.fixture
def trainer_factory(tiny_training_scene, tmp_path):
    """Builds a nerfstudio Trainer for ``gsmsdr`` through its TrainerConfig (what ``ns-train gsmsdr`` runs) on the
    tiny scene: CPU, images cached as float32 (so a NaN can be written into one), blur field on from step 0."""
    from gsmsdr_ns.plugin.method_config import gsmsdr_trainer_config

    from nerfstudio.utils import writer  # after the configs: importing it first is a circular import

    saved_writers = list(writer.EVENT_WRITERS)

    def build(max_steps: int):
        config = gsmsdr_trainer_config()
        config.machine.device_type = "cpu"
        config.vis = "tensorboard"
        config.output_dir = tmp_path / "outputs"
        config.timestamp = "run"
        config.max_num_iterations = max_steps
        config.steps_per_save = 10_000
        config.steps_per_eval_image = config.steps_per_eval_batch = config.steps_per_eval_all_images = 0
        config.logging.steps_per_log = 10_000
        config.logging.local_writer.enable = False
        config.pipeline.datamanager.data = tiny_training_scene
        config.pipeline.datamanager.cache_images_type = "float32"
        model = config.pipeline.model
        model.num_downscales, model.warmup_length, model.refine_every = 0, 2, 2
        model.blur_field = BlurFieldConfig(size="lite", kernel_sizes=(3, 5, 9), warmup=0)
        trainer = config.setup(local_rank=0, world_size=1)
        trainer.setup()
        return trainer

    yield build
    writer.EVENT_WRITERS[:] = saved_writers


def add_callback(trainer, where: str, func, first: bool = True) -> None:
    """Run ``func(step)`` before / after each training iteration, ahead of (or after) the model's callbacks."""
    from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation

    callback = TrainingCallback([getattr(TrainingCallbackLocation, where)], func)
    trainer.callbacks.insert(0 if first else len(trainer.callbacks), callback)


@pytest.mark.parametrize("poison", ["image", "opacities", "means", "scales", "quats"])
def test_trainer_stops_on_a_nan_naming_the_step(trainer_factory, poison):
    from gsmsdr_ns.plugin.model import NonFiniteLossError

    trainer = trainer_factory(max_steps=12)
    model = trainer.pipeline.model
    assert model.blur_field is not None, "the tiny scene should train the blur field (nothing known about it)"
    bad_step = 5

    def inject(step: int) -> None:
        if step != bad_step:
            return
        if poison == "image":  # one NaN pixel in every cached training image
            for item in trainer.pipeline.datamanager.cached_train:
                item["image"][3, 4, 1] = float("nan")
        else:  # a NaN position / scale / rotation only culls its Gaussian: the loss alone would stay finite
            with torch.no_grad():
                model.gauss_params[poison][0] = float("nan")

    steps_done: List[int] = []
    add_callback(trainer, "BEFORE_TRAIN_ITERATION", inject)
    add_callback(trainer, "AFTER_TRAIN_ITERATION", lambda step: steps_done.append(step))
    with pytest.raises(NonFiniteLossError) as caught:
        trainer.train()
    message = str(caught.value)
    assert f"step {bad_step} " in message, message
    if poison in ("image", "opacities"):
        assert "main_loss=nan" in message, message
    assert (f"non-finite Gaussian parameters: {poison}" if poison != "image" else "parameters: none") in message
    assert steps_done == list(range(bad_step)), "training went on after the non-finite loss"


def test_trainer_survives_a_learning_rate_spike(trainer_factory):
    """Every learning rate x1e4 for one step (log-scales jump by ~50, opacity logits by ~500), with refinement
    every 2 steps: parameters and Adam states stay finite and training goes on. Regression: the overflowing
    covariances turned the means, quaternions and scales of the whole scene into NaN within one step, silently
    (NaN Gaussians are culled, so the loss stayed finite)."""
    trainer = trainer_factory(max_steps=10)
    model = trainer.pipeline.model
    optimizers = trainer.optimizers.optimizers
    base = {name: [group["lr"] for group in opt.param_groups] for name, opt in optimizers.items()}
    spike_step, checked = 3, []
    assert model.blur_field is not None
    blur_before = [param.detach().clone() for param in model.blur_field.parameters()]

    def set_lrs(step: int) -> None:
        for name, opt in optimizers.items():
            for group, lr in zip(opt.param_groups, base[name]):
                group["lr"] = lr * (1e4 if step == spike_step else 1.0)

    def check(step: int) -> None:
        for name, param in model.named_parameters():
            assert all_finite(param.data), f"step {step}: {name} is not finite"
        for name, opt in optimizers.items():
            for param_state in opt.state.values():
                for key, value in param_state.items():
                    if isinstance(value, torch.Tensor):
                        assert all_finite(value), f"step {step}: Adam {key} of {name} is not finite"
        checked.append(step)

    add_callback(trainer, "BEFORE_TRAIN_ITERATION", set_lrs)
    add_callback(trainer, "AFTER_TRAIN_ITERATION", check, first=False)  # after refinement
    trainer.train()
    assert checked == list(range(10))
    assert float(model.scales.max()) > 20.0, "the spike did not reach the scales: the test lost its point"
    moved = [not torch.equal(a, b) for a, b in zip(blur_before, model.blur_field.parameters())]
    assert any(moved), "the blur field was not trained: the spike did not go through the degradation path"


# --------------------------------------------------------------------------------------------------------------
# autocast: run_autocast_checks(device) is for a GPU session (not collected); on CPU it runs with bfloat16
# --------------------------------------------------------------------------------------------------------------


def test_cpu_autocast_bfloat16():
    """Regressions: under CPU autocast the blur heads return bfloat16 kernels, which ``degrade`` passed to
    ``apply_pixel_kernels`` next to a float32 render (ValueError); and the CPU rasterizer projected in bfloat16
    (centres off by pixels) and then failed the C++ kernel's one-dtype check. gsplat computes in float32."""
    report = run_autocast_checks("cpu", torch.bfloat16)
    assert report["rasterization"].startswith("ok (cpp, torch.float32")


def run_autocast_checks(device="cuda", dtype: Optional[torch.dtype] = None) -> Dict[str, str]:
    """The blur and rasterizer stability checks under ``torch.autocast`` on ``device``; raises AssertionError on a
    non-finite value. ``dtype``: float16 on CUDA, bfloat16 elsewhere by default. Returns a short report.

    Usage (GPU session): ``python tests/test_stability.py cuda``. On CUDA the rasterizer is gsplat's.
    """
    device = torch.device(device)
    dtype = dtype or (torch.float16 if device.type == "cuda" else torch.bfloat16)
    report: Dict[str, str] = {}
    gen = torch.Generator().manual_seed(0)

    # blur field + degrade with saturated heads, at every scale, on tiny and moderate images
    for mode in ("full", "msd_only", "re_only", "view"):
        config = BlurFieldConfig(mode=mode, size="lite", kernel_sizes=(3, 5, 9))
        for scale in config.setup(num_train_views=2).scales:
            field = config.setup(num_train_views=2).to(device).train()
            K = field.kernel_size(scale)
            saturate_heads(field, scale, (K * K) // 2, 1.0)
            for H, W in [(1, 1), (1, 16), (16, 1), (48, 64)]:
                render = torch.rand(1, 3, H, W, generator=gen).to(device).requires_grad_()
                depth = torch.rand(1, 1, H, W, generator=gen).to(device)
                with torch.autocast(device.type, dtype=dtype):
                    kernels, mask = field(render, depth, torch.tensor([1], device=device), scale)
                    degraded = BlurField.degrade(render, kernels, mask)
                    loss = (degraded.float() - 0.5).abs().mean() + field.mask_loss(mask).float()
                loss.backward()
                assert all_finite(kernels) and all_finite(mask) and all_finite(degraded), (mode, scale, H, W)
                assert all_finite(render.grad), (mode, scale, H, W)
                bad = [n for n, p in field.named_parameters() if p.grad is not None and not all_finite(p.grad)]
                assert not bad, (mode, scale, H, W, bad)
            report[f"blur field {mode} s={scale}"] = f"ok ({kernels.dtype})"

    # the rasterizer on extreme Gaussians (scales 1e-7..1e3, zero quaternions, +-50 logits, near plane)
    n = 64
    params = extreme_parameters(n - 8, seed=1)
    viewmats, Ks = pinhole(64, 48)
    leaves = {k: v.to(device).requires_grad_() for k, v in params.items()}
    with torch.autocast(device.type, dtype=dtype):
        colours, alphas, meta = rasterization(
            leaves["means"], leaves["quats"], torch.exp(leaves["scales"]), torch.sigmoid(leaves["opacities"][:, 0]),
            torch.sigmoid(leaves["colors"]), viewmats.to(device), Ks.to(device), 64, 48, near_plane=NEAR,
            packed=False, render_mode="RGB+ED", absgrad=True,
        )  # fmt: skip
        loss = colours.float().mean() + alphas.float().mean()
    loss.backward()
    assert all_finite(colours) and all_finite(alphas), "rasterizer output under autocast"
    for name, leaf in leaves.items():
        assert all_finite(leaf.grad), f"rasterizer gradient of {name} under autocast"
    # gsplat's kernels (and the CPU path) compute in float32 under autocast: the image must not move
    with torch.no_grad():
        reference, _, _ = rasterization(
            leaves["means"], leaves["quats"], torch.exp(leaves["scales"]), torch.sigmoid(leaves["opacities"][:, 0]),
            torch.sigmoid(leaves["colors"]), viewmats.to(device), Ks.to(device), 64, 48, near_plane=NEAR,
            packed=False, render_mode="RGB+ED",
        )  # fmt: skip
    difference = float((colours.float() - reference.float())[..., :3].abs().max())
    assert difference < 1e-3, f"autocast changed the rendered colours by {difference}"
    report["rasterization"] = f"ok ({meta.get('backend')}, {colours.dtype}, max colour change {difference:.2g})"
    return report


if __name__ == "__main__":
    for key, value in run_autocast_checks(sys.argv[1] if len(sys.argv) > 1 else "cuda").items():
        print(f"{key}: {value}")

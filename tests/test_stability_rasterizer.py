"""Numerical stability of the rasterizer at the edges, for both CPU pixel kernels ("cpp" and "torch"): forward
and backward stay finite (colours, alphas, depth, the gradient of every input, the ``meta`` tensors and
``absgrad``), culled Gaussians get exactly zero gradient, and a pathological Gaussian (an overflowing covariance or
centre, a NaN parameter) cannot change the gradients of the others.
"""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from stability_common import (  # noqa: F401  (single_thread: autouse fixture)
    BACKENDS,
    NEAR,
    SETTINGS,
    all_finite,
    check_render,
    gaussians,
    render_with_grads,
    single_thread,
)

from gsmsdr_ns.render import rasterization

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

"""Numerical stability of optimisation on the rasterizer: Adam steps (including one with every learning rate x1e4)
and gsplat's ``DefaultStrategy`` refinement (every step, on the rasterizer's ``meta``, with and without absgrad) keep
every parameter and optimizer state finite, for both CPU pixel kernels.
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
    extreme_parameters,
    pinhole,
    single_thread,
)

from gsmsdr_ns.render import rasterization

LRS = {"means": 1.6e-4, "scales": 5e-3, "quats": 1e-3, "opacities": 5e-2, "colors": 2.5e-3}  # splatfacto's
TARGETS = {
    "black": lambda h, w, g: torch.zeros(h, w, 3),
    "white": lambda h, w, g: torch.ones(h, w, 3),
    "constant": lambda h, w, g: torch.full((h, w, 3), 0.37),
    "random": lambda h, w, g: torch.rand(h, w, 3, generator=g),
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

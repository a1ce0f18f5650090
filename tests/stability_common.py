"""Shared helpers of the ``test_stability_*`` files: renders with gradients of every input, finiteness checks,
extreme Gaussians and saturated blur heads.

Everything in those files runs single-threaded (``single_thread``, imported by each test module): on a busy 2-core
machine every OpenMP barrier of a multi-threaded op can wait for a descheduled worker, which made the blur field
~100x slower there.
"""

from __future__ import annotations

import math
from typing import Dict, Optional

import pytest
import torch
from hypothesis import HealthCheck

from gsmsdr_ns.blur.field import BlurField
from gsmsdr_ns.blur.hpko import ViewKernels
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

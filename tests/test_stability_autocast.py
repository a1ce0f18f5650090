"""Numerical stability under ``torch.autocast``: the blur and rasterizer checks of the other ``test_stability_*``
files in reduced precision.

``run_autocast_checks(device)`` (not collected by pytest) is for a GPU session:
``python tests/test_stability_autocast.py cuda``; on CPU, ``test_cpu_autocast_bfloat16`` runs it with bfloat16.
Importing this file needs no GPU.
"""

from __future__ import annotations

import sys
from typing import Dict, Optional

import torch
from stability_common import (  # noqa: F401  (single_thread: autouse fixture)
    NEAR,
    all_finite,
    extreme_parameters,
    pinhole,
    saturate_heads,
    single_thread,
)

from gsmsdr_ns.blur.degradation_config import DegradationConfig
from gsmsdr_ns.blur.field import BlurField, BlurFieldConfig
from gsmsdr_ns.blur.losses import mask_regulariser
from gsmsdr_ns.render import rasterization


def test_cpu_autocast_bfloat16():
    """Regressions: under CPU autocast the blur heads return bfloat16 kernels, which ``degrade`` passed to
    ``apply_pixel_kernels`` next to a float32 render (ValueError); and the CPU rasterizer projected in bfloat16
    (centres off by pixels) and then failed the C++ kernel's one-dtype check. gsplat computes in float32."""
    report = run_autocast_checks("cpu", torch.bfloat16)
    assert report["rasterization"].startswith("ok (cpp, torch.float32")


def run_autocast_checks(device="cuda", dtype: Optional[torch.dtype] = None) -> Dict[str, str]:
    """The blur and rasterizer stability checks under ``torch.autocast`` on ``device``; raises AssertionError on a
    non-finite value. ``dtype``: float16 on CUDA, bfloat16 elsewhere by default. Returns a short report.

    Usage (GPU session): ``python tests/test_stability_autocast.py cuda``. On CUDA the rasterizer is gsplat's.
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
                    loss = (degraded.float() - 0.5).abs().mean() + mask_regulariser(
                        mask, DegradationConfig().mask_reg_weight
                    ).float()
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

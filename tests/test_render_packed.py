"""`rasterization(..., packed=True)` on the CPU: gsplat's default layout gives the same images and gradients as the
unpacked one, a packed `meta` that matches the unpacked entries row for row, and drives DefaultStrategy's packed
path to the same densification statistics."""

from __future__ import annotations

import pytest
import torch
from test_render import BACKENDS, random_scene

from gsmsdr_ns.render import rasterization


def _render(packed: bool, backend: str, seed: int = 3):
    means, quats, scales, opac, colors, viewmats, Ks, W, H = random_scene(150, seed, dtype=torch.float32)
    means = means.clone().requires_grad_(True)
    colors = colors.clone().requires_grad_(True)
    img, alpha, meta = rasterization(means, quats, scales, opac, colors, viewmats.float(), Ks.float(), W, H,
                                     packed=packed, cpu_backend=backend)  # fmt: skip
    return means, colors, img, alpha, meta


@pytest.mark.parametrize("backend", BACKENDS)
def test_packed_matches_unpacked_images_and_gradients(backend):
    results = {}
    for packed in (False, True):
        means, colors, img, alpha, meta = _render(packed, backend)
        meta["means2d"].retain_grad()
        upstream = torch.linspace(-1.0, 1.0, img.numel()).reshape(img.shape)
        (img * upstream).sum().backward()
        results[packed] = (img.detach(), alpha.detach(), means.grad, colors.grad, meta)
    for a, b in zip(results[False][:4], results[True][:4]):
        torch.testing.assert_close(a, b)
    unpacked, packed = results[False][4], results[True][4]
    cam, gid = packed["camera_ids"], packed["gaussian_ids"]
    visible = unpacked["radii"] > 0
    assert cam.shape[0] == int(visible.sum()) > 0
    assert torch.all(visible[cam, gid])
    for name in ("radii", "depths", "conics", "opacities", "tiles_per_gauss"):
        torch.testing.assert_close(packed[name], unpacked[name][cam, gid], msg=name)
    torch.testing.assert_close(packed["means2d"].detach(), unpacked["means2d"].detach()[cam, gid])
    torch.testing.assert_close(packed["means2d"].grad, unpacked["means2d"].grad[cam, gid])
    # the same tile intersections, each naming the same (camera, Gaussian) pair
    flat_unpacked = unpacked["flatten_ids"].long()
    flat_packed = packed["flatten_ids"].long()
    assert torch.all(flat_packed >= 0)
    num_gaussians = unpacked["radii"].shape[1]
    torch.testing.assert_close(cam[flat_packed] * num_gaussians + gid[flat_packed], flat_unpacked)


def test_packed_meta_drives_default_strategy_like_unpacked():
    from gsplat.strategy import DefaultStrategy

    stats = {}
    for packed in (False, True):
        means, quats, scales, opac, colors, viewmats, Ks, W, H = random_scene(120, 4, dtype=torch.float32)
        params = torch.nn.ParameterDict({
            "means": means, "quats": quats, "scales": torch.log(scales), "opacities": torch.logit(opac),
            "colors": colors,
        })  # fmt: skip
        optimizers = {k: torch.optim.Adam([p], lr=1e-3) for k, p in params.items()}
        strategy = DefaultStrategy(refine_start_iter=10, refine_every=100, verbose=False)
        state = strategy.initialize_state()
        img, _, info = rasterization(params["means"], params["quats"], torch.exp(params["scales"]),
                                     torch.sigmoid(params["opacities"]), params["colors"], viewmats.float(),
                                     Ks.float(), W, H, packed=packed, cpu_backend="torch")  # fmt: skip
        strategy.step_pre_backward(params, optimizers, state, 1, info)
        (img - 0.5).square().sum().backward()
        strategy.step_post_backward(params, optimizers, state, 1, info, packed=packed)
        stats[packed] = (state["grad2d"], state["count"])
    torch.testing.assert_close(stats[True][0], stats[False][0])
    torch.testing.assert_close(stats[True][1], stats[False][1])
    assert stats[True][1].sum() > 0

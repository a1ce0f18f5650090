"""Kernels predicted on a coarse grid (ops/grid_kernels.py) and the blur field's ``feature_downsample``."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from reference_checks import assert_matches_reference

from gsmsdr_ns.blur.field import BlurField, BlurFieldConfig
from gsmsdr_ns.ops.grid_kernels import (
    GridKernels,
    apply_grid_kernels,
    grid_kernels_cpp_available,
    grid_size,
    pool_to_grid,
    upsample_grid,
)
from gsmsdr_ns.ops.pixel_kernels import apply_pixel_kernels_unfold

needs_cpp = pytest.mark.skipif(not grid_kernels_cpp_available(), reason="no C++ compiler for the grid-kernel op")

# (H, W, factor, K): factors that divide the image and factors that leave a partial last cell, one-row images, and a
# grid of one cell (one kernel for the whole image, mode "view"), and kernels spanning several grid rows (the C++
# op keeps the resampled grid rows a window of pixel rows reads); rows of several 64-byte column blocks with a partial
# last one (the C++ op's inner loops)
CASES = [(13, 17, 4, 5), (12, 16, 2, 3), (7, 9, 3, 5), (1, 5, 2, 3), (6, 6, 2, 1), (9, 4, 5, 3), (5, 7, 8, 5),
         (37, 29, 3, 9), (11, 70, 4, 7)]  # fmt: skip


def reference(image: torch.Tensor, grid: torch.Tensor, factor: int) -> torch.Tensor:
    """Resample with F.interpolate to every pixel, then the unfold formulation (independent of both backends)."""
    H, W = image.shape[-2:]
    dense = F.interpolate(grid, scale_factor=factor, mode="bilinear", align_corners=False)[..., :H, :W]
    return apply_pixel_kernels_unfold(image, dense)


@pytest.mark.parametrize("backend", [pytest.param("cpp", marks=needs_cpp), "torch"])
@pytest.mark.parametrize("H, W, factor, K", CASES)
def test_matches_dense_reference_in_float64(backend, H, W, factor, K):
    gen = torch.Generator().manual_seed(H * 100 + W)
    image = torch.rand(2, 3, H, W, dtype=torch.float64, generator=gen, requires_grad=True)
    grid = torch.rand(2, K * K, *grid_size((H, W), factor), dtype=torch.float64, generator=gen, requires_grad=True)
    out = apply_grid_kernels(image, grid, factor, backend=backend)
    assert_matches_reference(out, reference(image, grid, factor), (image, grid), gen)


@needs_cpp
@pytest.mark.parametrize("channels", [1, 2, 4])
def test_cpp_matches_the_reference_for_any_channel_count(channels):
    """Three channels (RGB) take the C++ op's unrolled path; any other count its per-channel one."""
    gen = torch.Generator().manual_seed(channels)
    image = torch.rand(2, channels, 19, 35, dtype=torch.float64, generator=gen, requires_grad=True)
    grid = torch.rand(2, 49, *grid_size((19, 35), 4), dtype=torch.float64, generator=gen, requires_grad=True)
    out = apply_grid_kernels(image, grid, 4, backend="cpp")
    assert_matches_reference(out, reference(image, grid, 4), (image, grid), gen)


@needs_cpp
def test_cpp_gradcheck():
    gen = torch.Generator().manual_seed(3)
    image = torch.rand(1, 2, 5, 7, dtype=torch.float64, generator=gen, requires_grad=True)
    grid = torch.rand(1, 9, 3, 4, dtype=torch.float64, generator=gen, requires_grad=True)
    assert torch.autograd.gradcheck(lambda i, g: apply_grid_kernels(i, g, 2, backend="cpp"), (image, grid))


@needs_cpp
def test_cpp_float32_close_to_float64():
    gen = torch.Generator().manual_seed(4)
    image = torch.rand(1, 3, 30, 41, dtype=torch.float64, generator=gen)
    grid = torch.softmax(torch.randn(1, 81, 8, 11, dtype=torch.float64, generator=gen), dim=1)
    exact = apply_grid_kernels(image, grid, 4, backend="cpp")
    single = apply_grid_kernels(image.float(), grid.float(), 4, backend="cpp")
    torch.testing.assert_close(single.double(), exact, rtol=0, atol=1e-5)


def test_normalised_grid_kernels_keep_a_constant_image():
    grid = torch.softmax(torch.randn(1, 25, 4, 5, generator=torch.Generator().manual_seed(5)), dim=1)
    image = torch.full((1, 3, 15, 18), 0.25)
    torch.testing.assert_close(apply_grid_kernels(image, grid, 4), image)


def test_pool_and_upsample_conventions():
    x = torch.arange(10.0).reshape(1, 1, 1, 10)
    # a partial last cell averages the pixels it covers
    assert pool_to_grid(x, 4).flatten().tolist() == [1.5, 5.5, 8.5]
    grid = torch.tensor([[[[0.0, 4.0]]]])
    # cell centres at pixels 1.5 and 5.5 (factor 4): linear in between, constant beyond
    assert upsample_grid(grid, 4, (1, 8)).flatten().tolist() == [0.0, 0.0, 0.5, 1.5, 2.5, 3.5, 4.0, 4.0]


def test_wrong_grid_shape_is_named():
    image = torch.rand(1, 3, 10, 10)
    with pytest.raises(ValueError, match=r"grid: expected shape \[1, 9, 5, 5\]"):
        apply_grid_kernels(image, torch.rand(1, 9, 4, 5), 2)
    with pytest.raises(ValueError, match="factor must be an integer >= 1"):
        apply_grid_kernels(image, torch.rand(1, 9, 10, 10), 0)


def test_feature_downsample_must_be_a_positive_integer():
    with pytest.raises(ValueError, match="feature_downsample"):
        BlurFieldConfig(feature_downsample=0)


@pytest.mark.parametrize("factor", [1, 2, 4])
def test_field_predicts_on_the_grid_and_blurs_as_its_dense_kernels(factor):
    torch.manual_seed(0)
    field = BlurFieldConfig(kernel_sizes=(5, 9), feature_downsample=factor).setup(num_train_views=3)
    render = torch.rand(1, 3, 22, 29)
    depth = torch.rand(1, 1, 22, 29) + 1.0
    ids = torch.tensor([1])
    kernels, mask = field(render, depth, ids, 1, dense=False)
    assert mask.shape == (1, 1, 22, 29)
    if factor == 1:
        assert isinstance(kernels, torch.Tensor) and kernels.shape == (1, 81, 22, 29)
    else:
        assert isinstance(kernels, GridKernels)
        assert kernels.weights.shape == (1, 81, *grid_size((22, 29), factor))
    dense, dense_mask = field(render, depth, ids, 1)
    assert dense.shape == (1, 81, 22, 29)
    torch.testing.assert_close(dense.sum(dim=1), torch.ones(1, 22, 29))
    torch.testing.assert_close(dense_mask, mask)
    torch.testing.assert_close(
        BlurField.degrade(render, kernels, mask, linear_light=True),
        BlurField.degrade(render, dense, mask, linear_light=True),
        rtol=1e-5,
        atol=1e-6,
    )


def test_feature_grid_cells_cap_the_grid_at_any_render_size():
    config = BlurFieldConfig(feature_downsample=4, feature_grid_cells=100)
    assert config.grid_factor((30, 40)) == 4  # 1200 pixels: 8 x 10 cells of 4 px are under the cap
    assert config.grid_factor((333, 458)) == 40  # ceil(sqrt(152514 / 100))
    uncapped = BlurFieldConfig(feature_downsample=4, feature_grid_cells=0)
    assert uncapped.grid_factor((333, 458)) == 4  # no cap: always feature_downsample
    default = BlurFieldConfig()  # capped at 4096 cells: 4 px cells up to 256x256, larger above
    assert default.grid_factor((256, 256)) == 4 and default.grid_factor((333, 458)) == 7
    assert default.grid_factor((866, 1297)) == 17
    assert BlurFieldConfig(feature_downsample=1, feature_grid_cells=100).grid_factor((333, 458)) == 1  # per pixel
    with pytest.raises(ValueError, match="feature_grid_cells"):
        BlurFieldConfig(feature_grid_cells=-1)
    field = BlurFieldConfig(kernel_sizes=(5,), feature_downsample=2, feature_grid_cells=30).setup(num_train_views=2)
    render = torch.rand(1, 3, 22, 29)
    kernels, mask = field(render, torch.rand(1, 1, 22, 29) + 1.0, torch.tensor([0]), 1, dense=False)
    assert kernels.factor == 5 and kernels.weights.shape[-2:] == grid_size((22, 29), 5)  # ceil(sqrt(638 / 30))
    assert mask.shape == (1, 1, 22, 29)

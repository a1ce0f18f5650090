"""The deconvolved residual (``ops/deconvolved_loss.py``): the residual weighted by the inverse of the blur's
spectrum."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from gsmsdr_ns.ops.deconvolved_loss import compose_kernels, deconvolved_residual, mean_kernel
from gsmsdr_ns.ops.disk_kernels import mean_soft_disk_kernel, soft_disk_kernels
from gsmsdr_ns.ops.fft_length import fast_fft_length


def gaussian_kernel(K: int, sigma: float) -> torch.Tensor:
    r = torch.arange(K, dtype=torch.float64) - K // 2
    g = torch.exp(-(r[:, None] ** 2 + r[None, :] ** 2) / (2 * sigma**2))
    return (g / g.sum())[None]


def smooth_image(H: int, W: int, seed: int = 0) -> torch.Tensor:
    """[1, 3, H, W] random image whose detail is coarser than the test kernels' blur removes."""
    g = torch.Generator().manual_seed(seed)
    coarse = torch.rand(1, 3, H // 4, W // 4, generator=g, dtype=torch.float64)
    return F.interpolate(coarse, size=(H, W), mode="bicubic", align_corners=False)


def test_identity_kernel_scales_the_residual():
    residual = torch.randn(2, 3, 20, 30, dtype=torch.float64)
    identity = torch.zeros(2, 5, 5, dtype=torch.float64)
    identity[:, 2, 2] = 1.0
    out = deconvolved_residual(residual, identity, eps=0.01)
    torch.testing.assert_close(out, residual / 1.01**0.5)


def test_a_residual_blurred_by_the_kernel_is_deblurred():
    """For a blur with a positive spectrum the weight undoes it where the blur keeps the signal (away from the
    border, which the zero padding affects)."""
    K, sigma = 9, 1.0
    kernel = gaussian_kernel(K, sigma)
    sharp = smooth_image(48, 64)
    blurred = F.conv2d(F.pad(sharp, (K // 2,) * 4, mode="replicate"), kernel.expand(3, 1, K, K), groups=3)
    out = deconvolved_residual(blurred, kernel, eps=1e-4)
    inner = (slice(None), slice(None), slice(K, -K), slice(K, -K))
    error = (out - sharp)[inner].abs().mean()
    blur_error = (blurred - sharp)[inner].abs().mean()
    assert error < 0.1 * blur_error, (float(error), float(blur_error))


def test_frequencies_the_blur_removes_are_amplified_at_most_eps_to_the_minus_half():
    box = torch.full((1, 5, 5), 1 / 25, dtype=torch.float64)
    residual = torch.randn(1, 1, 64, 64, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    out = deconvolved_residual(residual, box, eps=0.01)
    assert 1.5 < float(out.std() / residual.std()) <= 10.0


def test_the_weight_is_a_constant_of_the_kernel():
    kernel = gaussian_kernel(5, 1.0).requires_grad_(True)
    residual = torch.randn(1, 3, 16, 16, dtype=torch.float64, requires_grad=True)
    deconvolved_residual(residual, kernel, eps=0.01).square().sum().backward()
    assert kernel.grad is None and residual.grad is not None


def test_mean_kernel_of_grid_weights():
    weights = torch.softmax(torch.randn(2, 25, 3, 4, dtype=torch.float64), dim=1)
    k = mean_kernel(weights)
    assert k.shape == (2, 5, 5)
    torch.testing.assert_close(k.sum(dim=(-2, -1)), torch.ones(2, dtype=torch.float64))


def test_composed_kernels_blur_as_one_blur_after_the_other():
    first, second = gaussian_kernel(5, 1.0), gaussian_kernel(3, 0.7)
    both = compose_kernels(first, second)
    assert both.shape == (1, 7, 7)
    torch.testing.assert_close(both.sum(), torch.tensor(1.0, dtype=torch.float64))
    image = smooth_image(24, 24)

    def blur(x, k):  # zero-padded correlation with a flipped kernel: a convolution
        K = k.shape[-1]
        return F.conv2d(F.pad(x, (K // 2,) * 4), k.flip(-2, -1)[:, None].expand(3, 1, K, K), groups=3)

    torch.testing.assert_close(blur(blur(image, first), second)[..., 4:-4, 4:-4], blur(image, both)[..., 4:-4, 4:-4])
    identity = torch.zeros(1, 3, 3, dtype=torch.float64)
    identity[0, 1, 1] = 1.0
    torch.testing.assert_close(compose_kernels(first, identity)[:, 1:-1, 1:-1], first)


def test_mean_soft_disk_kernel_is_the_mean_of_the_pixels_disks():
    radius = torch.rand(2, 1, 6, 7, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 3
    exact = soft_disk_kernels(radius, 7).mean(dim=(-2, -1)).reshape(2, 7, 7)
    torch.testing.assert_close(mean_soft_disk_kernel(radius, 7), exact)
    ramp = torch.linspace(0, 3, 40, dtype=torch.float64).expand(1, 1, 40, 40)  # a smooth radius map
    sampled = mean_soft_disk_kernel(ramp, 7, max_pixels=100)  # every 4th row and column
    torch.testing.assert_close(sampled.sum(), torch.tensor(1.0, dtype=torch.float64))
    assert (sampled - soft_disk_kernels(ramp, 7).mean(dim=(-2, -1)).reshape(1, 7, 7)).abs().max() < 0.02
    flat = torch.full((1, 1, 50, 50), 2.0, dtype=torch.float64)  # one radius everywhere: its disk, whatever the sample
    one_disk = soft_disk_kernels(flat[..., :1, :1], 7).reshape(1, 7, 7)
    torch.testing.assert_close(mean_soft_disk_kernel(flat, 7, max_pixels=16), one_disk)


@pytest.mark.parametrize("bad", [dict(eps=0.0), dict(kernel=torch.ones(1, 1, 3, 3))])
def test_bad_arguments_are_refused(bad):
    args = dict(residual=torch.zeros(1, 3, 8, 8), kernel=torch.ones(1, 3, 3) / 9, eps=0.01)
    args.update(bad)
    with pytest.raises(ValueError):
        deconvolved_residual(**args)


def _factors_2_3_5(n: int) -> bool:
    for p in (2, 3, 5):
        while n % p == 0:
            n //= p
    return n == 1


def test_fast_fft_length_is_the_next_2_3_5_smooth_length():
    for n in range(1, 1200):
        length = fast_fft_length(n)
        assert length >= n and _factors_2_3_5(length), n
        assert not any(_factors_2_3_5(m) for m in range(n, length)), n
    assert fast_fft_length(263) == 270  # 263 is prime: the size a 229-px row padded by 17 on each side has

"""LPIPS without downloads: splatfacto builds torchmetrics' LPIPS, whose AlexNet backbone torchvision downloads on
first use. Offline, the model builds a stand-in instead and the metric is left out (one warning per process)."""

from __future__ import annotations

import contextlib
import warnings
from pathlib import Path
from typing import Iterator, Type
from urllib.parse import urlparse

import torch
from torch import Tensor

_warning_shown = False  # the "LPIPS disabled" warning is shown once per process, however many models are built


def lpips_backbone_cache_path() -> Path:
    """Where torchvision keeps the AlexNet weights that torchmetrics' default LPIPS needs."""
    from torchvision.models import AlexNet_Weights

    filename = Path(urlparse(AlexNet_Weights.DEFAULT.url).path).name
    return Path(torch.hub.get_dir()) / "checkpoints" / filename


class LPIPSUnavailable(torch.nn.Module):
    """Stands in for LPIPS when its backbone weights are not cached; returns NaN, which the model drops."""

    def forward(self, *_args, **_kwargs) -> Tensor:
        return torch.tensor(float("nan"))


@contextlib.contextmanager
def lpips_disabled() -> Iterator[None]:
    """While active, torchmetrics' LPIPS class builds an :class:`LPIPSUnavailable` instead of downloading AlexNet.

    splatfacto's ``populate_modules`` imports ``LearnedPerceptualImagePatchSimilarity`` from
    ``torchmetrics.image.lpip`` when it runs, so swapping the module attribute for the duration of that call is
    enough; it is restored afterwards.
    """
    import torchmetrics.image.lpip as lpip_module

    original = lpip_module.LearnedPerceptualImagePatchSimilarity
    lpip_module.LearnedPerceptualImagePatchSimilarity = lambda *args, **kwargs: LPIPSUnavailable()  # type: ignore
    try:
        yield
    finally:
        lpip_module.LearnedPerceptualImagePatchSimilarity = original


def warn_lpips_disabled(lpips_path: Path, category: Type[Warning]) -> None:
    """Say once per process that LPIPS is left out and where its weights would have to be."""
    global _warning_shown
    if _warning_shown:
        return
    _warning_shown = True
    warnings.warn(
        f"gsmsdr: LPIPS is disabled because its AlexNet backbone is not in the torch hub cache ({lpips_path}) "
        "and nothing is downloaded at run time. Metrics (ns-eval) report psnr and ssim only. To enable LPIPS, "
        "place alexnet weights at that path (or set TORCH_HOME to a cache that has them).",
        category,
        stacklevel=4,
    )

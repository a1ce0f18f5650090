"""Photo sharpness as the variance of the Laplacian of its grey levels (lower is blurrier)."""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Dict, Optional, Sequence

import numpy as np
from skimage.color import rgb2gray
from skimage.filters import laplace

from gsmsdr_ns.io.images import read_image


def variance_of_laplacian(rgb: np.ndarray) -> float:
    """Variance of the Laplacian of ``rgb`` ([H, W, 3|4] uint8 or floats in [0, 1]), on grey levels in [0, 1]."""
    gray = rgb2gray(rgb[..., :3])
    return float(laplace(gray).var())


def sharpness_scores(
    images_dir: Path, names: Sequence[str], on_image: Optional[Callable[[], None]] = None
) -> Dict[str, float]:
    """Variance of the Laplacian of each named photo in ``images_dir``."""
    scores = {}
    for name in names:
        scores[name] = variance_of_laplacian(read_image(Path(images_dir) / name))
        if on_image is not None:
            on_image()
    return scores

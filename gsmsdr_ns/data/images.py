"""Image files: listing a folder in file-name order, matching names across folders, sizes, reading and writing.

Reading and writing go through scikit-image (``skimage.io``); the size of a file is read from its header only
(PIL), so checking a whole scene costs no decoding.
"""

from __future__ import annotations

from pathlib import Path
from typing import List, Sequence, Tuple

import numpy as np

from gsmsdr_ns.data.errors import GSMSDRDataError

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
"""File name endings (any case) that count as images when a folder is listed."""


def is_image_name(name: str) -> bool:
    return not name.startswith(".") and name.lower().endswith(IMAGE_EXTENSIONS)


def list_images(folder: Path) -> List[str]:
    """Names of the image files directly inside ``folder``, sorted by file name (hidden files are skipped)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise GSMSDRDataError(f"gsmsdr: image folder '{folder}' does not exist or is not a directory.")
    return sorted(p.name for p in folder.iterdir() if p.is_file() and is_image_name(p.name))


def resolve_image(folder: Path, name: str, listed_in: str) -> Path:
    """The file for image ``name`` inside ``folder``.

    The exact name wins; otherwise a unique file with the same stem is accepted, because downscaled copies
    (``images_4/``, LLFF's minify) are often re-encoded as PNG. ``listed_in`` says where the name came from, for
    the error message.
    """
    folder = Path(folder)
    exact = folder / name
    if exact.is_file():
        return exact
    stem = Path(name).stem
    if folder.is_dir():
        candidates = sorted(p for p in folder.glob(f"{stem}.*") if p.is_file() and is_image_name(p.name))
        if len(candidates) == 1:
            return candidates[0]
    raise GSMSDRDataError(
        f"gsmsdr: image '{name}' is listed in {listed_in} but '{exact}' does not exist (nor a file with the same "
        "name and another extension). Restore the file, or remove the image from the camera file."
    )


def read_image_size(path: Path) -> Tuple[int, int]:
    """(width, height) of an image file from its header; :class:`GSMSDRDataError` naming the file if unusable."""
    from PIL import Image  # header-only size read; scikit-image has none

    path = Path(path)
    if not path.is_file():
        raise GSMSDRDataError(f"gsmsdr: image file '{path}' does not exist.")
    if path.stat().st_size == 0:
        raise GSMSDRDataError(
            f"gsmsdr: image file '{path}' is empty (0 bytes): an interrupted copy or download? Re-copy it."
        )
    try:
        with Image.open(path) as image:
            width, height = image.size
    except Exception as err:  # UnidentifiedImageError, OSError, SyntaxError, DecompressionBombError, ...
        raise GSMSDRDataError(
            f"gsmsdr: cannot read image file '{path}': {err}. The file is not a readable image; re-copy or "
            "re-export it."
        ) from err
    if width <= 0 or height <= 0:
        raise GSMSDRDataError(f"gsmsdr: image file '{path}' has zero size ({width}x{height} px).")
    return int(width), int(height)


def read_image(path: Path) -> np.ndarray:
    """Decode an image file into a ``[H, W, C]`` uint8 array (C = 3 or 4; grey images get 3 equal channels)."""
    import skimage.io
    import skimage.util

    path = Path(path)
    read_image_size(path)  # clear messages for missing / empty / unidentifiable files
    try:
        image = skimage.io.imread(path)
    except Exception as err:
        raise GSMSDRDataError(
            f"gsmsdr: cannot decode image file '{path}': {err}. The file is truncated or corrupt; re-copy it."
        ) from err
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    if image.ndim != 3 or image.shape[2] not in (3, 4):
        raise GSMSDRDataError(f"gsmsdr: image file '{path}' has unsupported shape {image.shape} (need RGB or RGBA).")
    if image.dtype != np.uint8:
        image = skimage.util.img_as_ubyte(image)
    return np.ascontiguousarray(image)


def write_image(path: Path, image: np.ndarray) -> None:
    """Write a ``[H, W, C]`` uint8 array (PNG when the name ends in .png)."""
    import skimage.io

    if image.dtype != np.uint8 or image.ndim != 3:
        raise ValueError(f"write_image expects [H, W, C] uint8, got {image.dtype} {image.shape}")
    skimage.io.imsave(Path(path), image, check_contrast=False)


def fit_intrinsics(
    intrinsics: Sequence[float], model_size: Tuple[int, int], image_size: Tuple[int, int], what: str
) -> np.ndarray:
    """Rescale ``fx, fy, cx, cy`` given for ``model_size`` (w, h) to an image of ``image_size`` (w, h).

    A downscaled copy may round its size either way, so the two axes may scale by slightly different amounts; a
    different aspect ratio (beyond that rounding) means the image is not a rescaled copy of what the cameras
    describe, and is an error naming ``what``.
    """
    (w0, h0), (w, h) = model_size, image_size
    sx, sy = w / w0, h / h0
    # Rounding a downscaled size moves it by < 1 px on each axis.
    if abs(sx - sy) > 1.0 / w0 + 1.0 / h0 + 1.0 / max(min(w, h), 1):
        raise GSMSDRDataError(
            f"gsmsdr: {what} is {w}x{h} px but its camera is {w0}x{h0} px, and {w}x{h} is not a rescaled copy of "
            f"{w0}x{h0} (aspect ratios {w / h:.4f} vs {w0 / h0:.4f}). Use images of the size the camera poses were "
            "computed on (or a downscaled copy of them), or re-run COLMAP on these images."
        )
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    return np.array([fx * sx, fy * sy, cx * sx, cy * sy], dtype=np.float64)

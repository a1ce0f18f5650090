"""Image files: listing a folder in file-name order, matching names across folders, sizes, reading and writing.

Decoding goes through scikit-image (``skimage.io``); the size of a file is read from its header only (PIL), so
checking a whole scene costs no decoding. Writing goes through PIL, which stores no timestamps: equal arrays give
byte-identical files. Every failure is an :class:`~gsmsdr_ns.io.errors.InputError` naming the file.
"""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional, Tuple

import numpy as np

from gsmsdr_ns.io.errors import InputError

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
"""File name endings (any case) that count as images when a folder is listed."""


def is_image_name(name: str) -> bool:
    """Whether a file name counts as an image (see :data:`IMAGE_EXTENSIONS`; hidden files never do)."""
    return not name.startswith(".") and name.lower().endswith(IMAGE_EXTENSIONS)


def list_images(folder: Path) -> List[str]:
    """Names of the image files directly inside ``folder``, sorted by file name (hidden files are skipped)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"gsmsdr: image folder '{folder}' does not exist or is not a directory.")
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
    raise InputError(
        f"gsmsdr: image '{name}' is listed in {listed_in} but '{exact}' does not exist (nor a file with the same "
        "name and another extension). Restore the file, or remove the image from the camera file."
    )


def read_image_size(path: Path) -> Tuple[int, int]:
    """(width, height) of an image file from its header; :class:`InputError` naming the file if unusable."""
    return _read_header(path)[:2]


def _read_header(path: Path) -> Tuple[int, int, str]:
    """(width, height, Pillow mode) of an image file from its header; :class:`InputError` naming the file if
    unusable."""
    from PIL import Image  # header-only read; scikit-image has none

    path = Path(path)
    if not path.is_file():
        raise InputError(f"gsmsdr: image file '{path}' does not exist. Restore it, or remove it from the camera file.")
    if path.stat().st_size == 0:
        raise InputError(
            f"gsmsdr: image file '{path}' is empty (0 bytes): an interrupted copy or download? Re-copy it."
        )
    try:
        with Image.open(path) as image:
            (width, height), mode = image.size, image.mode
    except Exception as err:  # UnidentifiedImageError, OSError, SyntaxError, DecompressionBombError, ...
        raise InputError(
            f"gsmsdr: cannot read image file '{path}': {err}. The file is not a readable image; re-copy or "
            "re-export it."
        ) from err
    if width <= 0 or height <= 0:
        raise InputError(f"gsmsdr: image file '{path}' has zero size ({width}x{height} px).")
    return int(width), int(height), mode


def _png_bit_depth(path: Path) -> Optional[int]:
    """Bits per sample of a PNG file (its IHDR chunk), None for other files."""
    try:
        with open(path, "rb") as f:
            header = f.read(25)
    except OSError:
        return None
    if len(header) < 25 or header[:8] != b"\x89PNG\r\n\x1a\n" or header[12:16] != b"IHDR":
        return None
    return header[24]


CONVERTED_MODES = {"CMYK": "RGB", "YCbCr": "RGB", "LAB": "RGB", "HSV": "RGB", "LA": "RGBA", "PA": "RGBA"}
"""Pillow modes decoded into RGB(A) by Pillow's own conversion: their channels are not RGB(A) (a CMYK JPEG's four
channels would otherwise pass for RGBA), or there are two of them (grey + alpha)."""


def _decode(path: Path, mode: str) -> np.ndarray:
    """Pixel data of an image file: Pillow's conversion to RGB(A) for the modes of :data:`CONVERTED_MODES`,
    scikit-image's decoder otherwise (16-bit colour PNGs then re-read at their depth)."""
    import skimage.io
    from PIL import Image

    target = CONVERTED_MODES.get(mode)
    if target is not None:
        with Image.open(path) as image:
            return np.asarray(image.convert(target))
    image = np.asarray(skimage.io.imread(path))
    if image.dtype == np.uint8 and _png_bit_depth(path) == 16:
        image = _decode_png16(path, image)
    return image


def _decode_png16(path: Path, reduced: np.ndarray) -> np.ndarray:
    """A 16-bit colour PNG at its depth (Pillow, behind scikit-image, reduces it to 8 bits): OpenCV's decoder, its BGR
    order turned to RGB; ``reduced`` when OpenCV cannot read it."""
    import cv2

    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None or image.dtype != np.uint16 or image.shape[:2] != reduced.shape[:2]:
        return reduced
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2RGBA if image.shape[2] == 4 else cv2.COLOR_BGR2RGB)
    return image


def decode_image(path: Path, expected_size: Optional[Tuple[int, int]] = None) -> np.ndarray:
    """Decode an image file into ``[H, W, C]`` in the file's own dtype (C = 3 or 4; grey becomes 3 equal channels;
    16-bit PNGs stay 16-bit).

    Missing, empty, unidentifiable, truncated or corrupt files, unsupported channel counts and (when
    ``expected_size`` = (width, height) is given) a size other than the camera's are :class:`InputError`.
    """
    path = Path(path)
    mode = _read_header(path)[2]  # clear messages for missing / empty / unidentifiable files
    try:
        image = _decode(path, mode)
    except Exception as err:  # the decoders raise many types (OSError, ValueError, SyntaxError, ...)
        raise InputError(
            f"gsmsdr: cannot read image file '{path}': {err}. The file is unreadable or truncated; re-copy or "
            "re-export it."
        ) from err
    if image.ndim == 2:
        image = image[:, :, None]
    if image.ndim == 3 and image.shape[2] == 1:
        image = np.repeat(image, 3, axis=2)
    if image.ndim != 3 or image.shape[2] not in (3, 4):
        raise InputError(f"gsmsdr: image file '{path}' has unsupported shape {image.shape} (need grey, RGB or RGBA).")
    if image.shape[0] == 0 or image.shape[1] == 0:
        raise InputError(f"gsmsdr: image file '{path}' has zero size ({image.shape[1]}x{image.shape[0]} px).")
    if expected_size is not None and (image.shape[1], image.shape[0]) != tuple(int(v) for v in expected_size):
        raise InputError(
            f"gsmsdr: image file '{path}' is {image.shape[1]}x{image.shape[0]} px but its camera says "
            f"{int(expected_size[0])}x{int(expected_size[1])} px. Use the images the cameras were computed on (or "
            "resize them back), or recompute the cameras on these images."
        )
    return image


def read_image(path: Path, expected_size: Optional[Tuple[int, int]] = None) -> np.ndarray:
    """Decode an image file into a ``[H, W, C]`` uint8 array (C = 3 or 4); checks as :func:`decode_image`.

    Deeper files are scaled to 8 bits, not truncated: 16-bit values by ``round(v * 255 / 65535)``, float values
    (float TIFF) in [0, 1] by ``round(v * 255)``; float values outside [0, 1] (HDR) are an InputError.
    """
    import skimage.util

    image = decode_image(path, expected_size)
    if image.dtype == np.uint16:
        image = ((image.astype(np.uint32) * 255 + 32767) // 65535).astype(np.uint8)
    elif image.dtype.kind == "f":
        finite = np.isfinite(image).all()
        if not finite or image.min(initial=0.0) < 0.0 or image.max(initial=0.0) > 1.0:
            raise InputError(
                f"gsmsdr: image file '{path}' holds floating-point values outside [0, 1] (an HDR or unnormalised "
                "image); tone-map it to an 8- or 16-bit image first."
            )
        image = np.round(image * 255.0).astype(np.uint8)
    elif image.dtype != np.uint8:
        image = skimage.util.img_as_ubyte(image)
    return np.ascontiguousarray(image)


def read_image_float(path: Path, expected_size: Optional[Tuple[int, int]] = None) -> np.ndarray:
    """Decode an image file into float32 RGB ``[H, W, 3]`` in [0, 1] (alpha dropped, 16 bit scaled exactly)."""
    from skimage.util import img_as_float32

    return img_as_float32(decode_image(path, expected_size)[..., :3])


def write_image(path: Path, image: np.ndarray) -> None:
    """Write a ``[H, W, 3 or 4]`` uint8 array; the format follows the file name (PNG for .png)."""
    from PIL import Image

    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] not in (3, 4):
        raise ValueError(f"write_image expects [H, W, 3 or 4] uint8, got {image.dtype} {image.shape}")
    mode = "RGB" if image.shape[2] == 3 else "RGBA"
    Image.fromarray(np.ascontiguousarray(image), mode=mode).save(Path(path))

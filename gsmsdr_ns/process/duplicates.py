"""Duplicate photos in a capture: byte-identical files, and re-encoded or resized copies of one photo.

Two copies of a photo under different names would land one in the training views and one among the held-out test
views, and the test scores would measure memory instead of reconstruction. ``gsmsdr-process`` keeps the first
name of each set (sorted order) and leaves the others out, with a warning naming them (:func:`find_duplicates`);
the gsmsdr dataparser refuses a scene whose test split holds a copy of a training image (:func:`copies_across`).
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np

THUMBNAIL_SIZE = (24, 32)
"""(height, width) every photo is compared at: small enough that re-encoding noise averages out."""

NEAR_IDENTICAL = 1.0 / 255.0
"""Largest mean absolute difference of two grey thumbnails (values in [0, 1]) still called one photo. At this size
consecutive photos of the LLFF fern capture differ by 4.6/255 to 23/255, one of them re-encoded as JPEG (quality 90)
by 0.06/255 and a half-size copy by 0.7/255."""


def _file_digest(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def grey_thumbnail(image: np.ndarray) -> np.ndarray:
    """[24, 32] float grey thumbnail in [0, 1] of a [H, W, C] uint8 photo (area-averaged, any aspect ratio)."""
    from skimage.color import rgb2gray
    from skimage.transform import resize

    grey = rgb2gray(image[..., :3])
    return resize(grey, THUMBNAIL_SIZE, anti_aliasing=True, preserve_range=True).astype(np.float32)


def _closest_copy(thumbnails: List[np.ndarray], thumbnail: np.ndarray) -> Optional[int]:
    """Index of the thumbnail within :data:`NEAR_IDENTICAL` of ``thumbnail`` (the closest one), else None."""
    if not thumbnails:
        return None
    differences = np.abs(np.stack(thumbnails) - thumbnail).mean(axis=(1, 2))
    closest = int(np.argmin(differences))
    return closest if differences[closest] <= NEAR_IDENTICAL else None


def find_duplicates(images_dir: Path, names: List[str]) -> Dict[str, str]:
    """Photos of ``names`` (sorted) that duplicate an earlier one: ``{duplicate: the name it duplicates}``.

    A duplicate is byte-identical to an earlier photo, or its grey thumbnail differs from an earlier photo's by at
    most :data:`NEAR_IDENTICAL` on average (a re-encoded or resized copy).
    """
    from gsmsdr_ns.io.images import read_image

    images_dir = Path(images_dir)
    duplicates: Dict[str, str] = {}
    first_with_digest: Dict[str, str] = {}
    kept: List[str] = []
    thumbnails: List[np.ndarray] = []
    for name in sorted(names):
        digest = _file_digest(images_dir / name)
        if digest in first_with_digest:
            duplicates[name] = first_with_digest[digest]
            continue
        first_with_digest[digest] = name
        thumbnail = grey_thumbnail(read_image(images_dir / name))
        closest = _closest_copy(thumbnails, thumbnail)
        if closest is not None:
            duplicates[name] = kept[closest]
            continue
        kept.append(name)
        thumbnails.append(thumbnail)
    return duplicates


def copies_across(train: List[Path], test: List[Path]) -> List[Tuple[Path, Path]]:
    """(test image, training image) pairs where a test image is a copy of a training image (byte-identical, or
    thumbnails within :data:`NEAR_IDENTICAL`): a test view that training has seen."""
    from gsmsdr_ns.io.images import read_image

    if not train or not test:
        return []
    digests = {_file_digest(Path(p)): Path(p) for p in train}
    pairs, unmatched = [], []
    for path in map(Path, test):
        same = digests.get(_file_digest(path))
        if same is not None:
            pairs.append((path, same))
        else:
            unmatched.append(path)
    if unmatched:
        train_paths = list(map(Path, train))
        thumbnails = [grey_thumbnail(read_image(p)) for p in train_paths]
        for path in unmatched:
            closest = _closest_copy(thumbnails, grey_thumbnail(read_image(path)))
            if closest is not None:
                pairs.append((path, train_paths[closest]))
    return pairs


__all__ = ["NEAR_IDENTICAL", "THUMBNAIL_SIZE", "copies_across", "find_duplicates", "grey_thumbnail"]

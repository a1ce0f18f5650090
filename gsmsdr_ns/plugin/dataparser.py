"""A validating COLMAP dataparser for ``gsmsdr``.

nerfstudio's ``ColmapDataParser`` does the parsing; this subclass fixes the scene layout that ``gsmsdr-synth`` and
a plain COLMAP run produce (``images/`` + ``sparse/0``, full resolution, so nerfstudio never stops to ask
interactively about downscaled copies) and turns bad input into :class:`GSMSDRDataError` messages that name the
offending file or value and say what to do, instead of an assertion or a NaN-filled training run.

Checks, in the order they run:

* the data directory and the COLMAP model (``cameras`` / ``images`` as ``.bin`` or ``.txt``) exist;
* every camera has finite, positive intrinsics and every image a finite pose with a non-zero quaternion;
* every image of the split exists, decodes completely (a truncated file fails here, not mid-training) and has
  the size its COLMAP camera says;
* an empty or missing ``points3D`` is not an error: the point cloud comes back empty and the model falls back to
  random initialisation with a warning.

The class is deliberately small so that a later dataparser (with layout auto-detection) can replace it in
``gsmsdr_ns.plugin.method_config`` without touching the model.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Type

import numpy as np
import torch
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from nerfstudio.data.dataparsers.colmap_dataparser import ColmapDataParser, ColmapDataParserConfig
from nerfstudio.data.utils import colmap_parsing_utils as colmap_io
from nerfstudio.utils.rich_utils import CONSOLE
from PIL import Image

from gsmsdr_ns.data.errors import GSMSDRDataError  # shared with the other readers; re-exported here


@dataclass
class GSMSDRDataParserConfig(ColmapDataParserConfig):
    """COLMAP scene in the ``gsmsdr-synth`` layout (``images/``, ``sparse/0``), checked before training."""

    _target: Type = field(default_factory=lambda: GSMSDRDataParser)
    colmap_path: Path = Path("sparse/0")
    """COLMAP reconstruction directory, relative to the data path."""
    images_path: Path = Path("images")
    """Image directory, relative to the data path."""
    downscale_factor: Optional[int] = 1
    """Image downscale factor. Values above 1 read pre-made copies from ``<images_path>_<factor>/``."""
    verify_images: bool = True
    """Decode every image of a split once while parsing, so unreadable, truncated or wrongly sized files fail
    early with their name (costs one decode per image)."""


class GSMSDRDataParser(ColmapDataParser):
    """``ColmapDataParser`` with input validation (see the module docstring)."""

    config: GSMSDRDataParserConfig

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        self._check_layout()
        outputs = super()._generate_dataparser_outputs(split, **kwargs)
        if self.config.verify_images:
            check_images_match_cameras(outputs.image_filenames, outputs.cameras)
        return outputs

    def _get_all_images_and_cameras(self, recon_dir: Path) -> Dict:
        check_colmap_model(recon_dir)
        return super()._get_all_images_and_cameras(recon_dir)

    def _load_3D_points(self, colmap_path: Path, transform_matrix: torch.Tensor, scale_factor: float) -> Dict:
        if count_points3d(colmap_path) == 0:
            CONSOLE.log(f"[yellow]gsmsdr: no 3D points in {colmap_path} (points3D missing or empty)")
            return {
                "points3D_xyz": torch.zeros((0, 3), dtype=torch.float32),
                "points3D_rgb": torch.zeros((0, 3), dtype=torch.uint8),
            }
        return super()._load_3D_points(colmap_path, transform_matrix, scale_factor)

    def _check_layout(self) -> None:
        data = Path(self.config.data)
        hint = "Pass the scene directory with --data <dir> (make a test scene with `gsmsdr-synth`)."
        if not data.is_dir():
            raise GSMSDRDataError(f"gsmsdr: data directory '{data}' does not exist or is not a directory. {hint}")
        recon = data / self.config.colmap_path
        if not any((recon / f"cameras{ext}").exists() for ext in (".bin", ".txt")):
            raise GSMSDRDataError(
                f"gsmsdr: no COLMAP model in '{recon}' (expected cameras.bin/images.bin or cameras.txt/images.txt). "
                f"{hint} If the model lives elsewhere, append `colmap --colmap-path <path relative to the data>` "
                "to the ns-train command."
            )
        factor = self.config.downscale_factor
        if factor is not None and factor > 1:
            folder = data / f"{self.config.images_path}_{factor}"
            if not folder.is_dir():
                raise GSMSDRDataError(
                    f"gsmsdr: downscale factor {factor} reads images from '{folder}', which does not exist. "
                    "Create the downscaled copies there, or append `colmap --downscale-factor 1` to ns-train."
                )


def _read_colmap_model(recon_dir: Path):
    if (recon_dir / "cameras.txt").exists():
        return colmap_io.read_cameras_text(recon_dir / "cameras.txt"), colmap_io.read_images_text(
            recon_dir / "images.txt"
        )
    return colmap_io.read_cameras_binary(recon_dir / "cameras.bin"), colmap_io.read_images_binary(
        recon_dir / "images.bin"
    )


def check_colmap_model(recon_dir: Path) -> None:
    """Raise :class:`GSMSDRDataError` for non-finite intrinsics or poses in a COLMAP model.

    nerfstudio centres and scales all poses together, so a single NaN pose would silently poison every camera;
    a zero quaternion makes the pose matrix singular.
    """
    cameras, images = _read_colmap_model(Path(recon_dir))
    for cam in cameras.values():
        params = np.asarray(cam.params, dtype=np.float64)
        if not np.all(np.isfinite(params)) or params.size == 0 or params[0] <= 0 or cam.width <= 0 or cam.height <= 0:
            raise GSMSDRDataError(
                f"gsmsdr: COLMAP camera {cam.id} in '{recon_dir}' has invalid intrinsics "
                f"(model {cam.model}, {cam.width}x{cam.height}, params {params.tolist()}): the focal length must be "
                "finite and positive. Re-run COLMAP's mapper or fix cameras.txt."
            )
    for image in images.values():
        qvec = np.asarray(image.qvec, dtype=np.float64)
        tvec = np.asarray(image.tvec, dtype=np.float64)
        if not (np.all(np.isfinite(qvec)) and np.all(np.isfinite(tvec))) or np.linalg.norm(qvec) < 1e-8:
            raise GSMSDRDataError(
                f"gsmsdr: image '{image.name}' (COLMAP image id {image.id} in '{recon_dir}') has a non-finite or "
                f"degenerate camera pose: qvec={qvec.tolist()}, tvec={tvec.tolist()}. Remove the image from the "
                "reconstruction or re-run COLMAP's mapper."
            )


def count_points3d(recon_dir: Path) -> int:
    """Number of points in ``points3D.bin`` / ``points3D.txt`` (0 when neither exists), without parsing them."""
    recon_dir = Path(recon_dir)
    binary, text = recon_dir / "points3D.bin", recon_dir / "points3D.txt"
    if binary.exists():
        with binary.open("rb") as f:
            head = f.read(8)
        return struct.unpack("<Q", head)[0] if len(head) == 8 else 0
    if text.exists():
        with text.open("r", encoding="utf8") as f:
            return sum(1 for line in f if line.strip() and not line.lstrip().startswith("#"))
    return 0


def check_images_match_cameras(image_filenames: List[Path], cameras: Cameras) -> None:
    """Decode each image once and compare its size with its camera; raise :class:`GSMSDRDataError` naming the file."""
    widths = cameras.width.reshape(-1).tolist()
    heights = cameras.height.reshape(-1).tolist()
    for path, width, height in zip(image_filenames, widths, heights):
        path = Path(path)
        if not path.is_file():
            raise GSMSDRDataError(
                f"gsmsdr: image file '{path}' is listed in the COLMAP model but does not exist. "
                "Restore it, or point ns-train at the right folder with `colmap --images-path <folder>`."
            )
        try:
            with Image.open(path) as image:
                size = image.size
                image.load()  # decodes all pixel data: truncated or corrupt files raise here
        except Exception as err:  # PIL raises OSError, SyntaxError, ValueError, DecompressionBombError, ...
            raise GSMSDRDataError(
                f"gsmsdr: cannot read image file '{path}': {err}. The file is unreadable or truncated; "
                "re-copy or re-export it (or remove it from the COLMAP model)."
            ) from err
        if size != (int(width), int(height)):
            raise GSMSDRDataError(
                f"gsmsdr: image file '{path}' is {size[0]}x{size[1]} px but its COLMAP camera says "
                f"{int(width)}x{int(height)} px. Use the images COLMAP was run on (or resize them back), or re-run "
                "COLMAP on these images."
            )

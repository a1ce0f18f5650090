"""A validating COLMAP dataparser for ``gsmsdr``.

nerfstudio's ``ColmapDataParser`` does the parsing; this subclass fixes the scene layout that ``gsmsdr-synth`` and
a plain COLMAP run produce (``images/`` + ``sparse/0``, full resolution, so nerfstudio never stops to ask
interactively about downscaled copies) and turns bad input into :class:`~gsmsdr_ns.io.errors.InputError` messages
that name the offending file or value and say what to do, instead of an assertion or a NaN-filled training run.
nerfstudio's parser still builds the outputs; the model is first read and validated by
:func:`gsmsdr_ns.io.colmap.read_colmap`.

Checks, in the order they run:

* the data directory and the COLMAP model (``cameras`` / ``images`` as ``.bin`` or ``.txt``) exist;
* every camera has finite, positive intrinsics and every image a finite pose with a non-zero quaternion;
* every pose nerfstudio built is a rotation (``max |R^T R - I| <= 1e-3``, det +1): nerfstudio does not normalise
  the quaternions it reads, so a scaled quaternion would give a scaled rotation;
* every image of the split exists, decodes completely (a truncated file fails here, not mid-training) and has
  the size its COLMAP camera says;
* an empty or missing ``points3D`` is not an error: the point cloud comes back empty and the model falls back to
  random initialisation with a warning.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Type

import torch
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from nerfstudio.data.dataparsers.colmap_dataparser import ColmapDataParser, ColmapDataParserConfig
from nerfstudio.utils.rich_utils import CONSOLE

from gsmsdr_ns.data.poses import check_rotations
from gsmsdr_ns.io.colmap import ColmapModel, read_colmap
from gsmsdr_ns.io.errors import InputError, SceneFolderMissingError
from gsmsdr_ns.io.images import read_image


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
    _colmap_model: Optional[ColmapModel] = None

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        self._check_layout()
        outputs = super()._generate_dataparser_outputs(split, **kwargs)
        # nerfstudio builds rotations from the file's quaternions without normalising them
        recon = Path(self.config.data) / self.config.colmap_path
        check_pose_rotations(outputs.cameras, recon, [Path(f).name for f in outputs.image_filenames])
        if self.config.verify_images:
            check_images_match_cameras(outputs.image_filenames, outputs.cameras)
        return outputs

    def _get_all_images_and_cameras(self, recon_dir: Path) -> Dict:
        # nerfstudio's parser asserts or produces NaN poses on bad models: read and validate with ours first
        self._colmap_model = read_colmap(recon_dir)
        return super()._get_all_images_and_cameras(recon_dir)

    def _load_3D_points(self, colmap_path: Path, transform_matrix: torch.Tensor, scale_factor: float) -> Dict:
        model = self._colmap_model if self._colmap_model is not None else read_colmap(colmap_path)
        if len(model.points.xyz) == 0:
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
            raise SceneFolderMissingError(data)
        recon = data / self.config.colmap_path
        if not any((recon / f"cameras{ext}").exists() for ext in (".bin", ".txt")):
            raise InputError(
                f"gsmsdr: no COLMAP model in '{recon}' (expected cameras.bin/images.bin or cameras.txt/images.txt). "
                f"{hint} If the model lives elsewhere, append `colmap --colmap-path <path relative to the data>` "
                "to the ns-train command."
            )
        factor = self.config.downscale_factor
        if factor is not None and factor > 1:
            folder = data / f"{self.config.images_path}_{factor}"
            if not folder.is_dir():
                raise InputError(
                    f"gsmsdr: downscale factor {factor} reads images from '{folder}', which does not exist. "
                    "Create the downscaled copies there, or append `colmap --downscale-factor 1` to ns-train."
                )


def check_image_files(image_filenames: List[Path], listed_in: str) -> None:
    """Check each image file exists and decodes completely (one full decode each, at parse time, so a truncated or
    corrupt file fails before training with its name); ``listed_in`` names the file that lists them."""
    for path in map(Path, image_filenames):
        if not path.is_file():
            raise InputError(
                f"gsmsdr: image file '{path}' is listed in {listed_in} but does not exist. Restore it, or remove it "
                "from that file."
            )
        read_image(path)  # decodes all pixel data: truncated or corrupt files raise InputError naming the file


def check_pose_rotations(cameras: Cameras, source: Path, names: List[str]) -> None:
    """Reject camera-to-world rotations that are not orthonormal with det +1 (``gsmsdr_ns.data.poses``)."""
    check_rotations(
        cameras.camera_to_worlds[:, :3, :3].double().numpy(),
        source,
        [f"image '{name}'" for name in names],
        "Re-run COLMAP's mapper (or re-export the model); a pose's quaternion must be a unit quaternion.",
    )


def check_images_match_cameras(image_filenames: List[Path], cameras: Cameras) -> None:
    """Decode each image once and compare its size with its camera; raise :class:`InputError` naming the file."""
    widths = cameras.width.reshape(-1).tolist()
    heights = cameras.height.reshape(-1).tolist()
    for path, width, height in zip(image_filenames, widths, heights):
        path = Path(path)
        if not path.is_file():
            raise InputError(
                f"gsmsdr: image file '{path}' is listed in the COLMAP model but does not exist. "
                "Restore it, or point ns-train at the right folder with `colmap --images-path <folder>`."
            )
        image = read_image(path)  # decodes all pixel data: truncated or corrupt files raise here
        size = (image.shape[1], image.shape[0])
        if size != (int(width), int(height)):
            raise InputError(
                f"gsmsdr: image file '{path}' is {size[0]}x{size[1]} px but its COLMAP camera says "
                f"{int(width)}x{int(height)} px. Use the images COLMAP was run on (or resize them back), or re-run "
                "COLMAP on these images."
            )

"""Shared base of the ``deblur-nerf-data`` and ``mixres-data`` dataparsers: scenes read in file-name order.

Both readers hold out test views by their index in the file-name-sorted image list (never by COLMAP image id),
take poses from a COLMAP model (pycolmap) or an LLFF ``poses_bounds.npy``, and make every camera's intrinsics match
the size of the image file it is paired with (``images_N/`` copies, sharp twins of another size, a COLMAP camera
that was computed at another resolution: fx, fy, cx, cy are rescaled per image). Within one folder every image must
be at the same scale of its camera (``gsmsdr_ns.data.cameras.check_same_scale``): a half-size view among full-size
ones is an error naming it, checked from the image headers when the scene is loaded.

Poses are oriented, centred and scaled as nerfstudio's ``colmap`` dataparser does (OpenCV -> OpenGL camera axes,
COLMAP's -y gravity guess -> +z, ``camera_utils.auto_orient_and_center_poses``, largest |translation| -> 1), over
all views of the scene, so train and eval splits share one world frame; the COLMAP points get the same transform.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Sequence, Tuple, Type

import numpy as np
import torch
from nerfstudio.cameras import camera_utils
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataParserConfig, DataparserOutputs
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.utils.rich_utils import CONSOLE

from gsmsdr_ns.data.cameras import (
    SceneCameras,
    cameras_from_colmap,
    check_same_scale,
    fit_intrinsics,
    read_poses_bounds,
)
from gsmsdr_ns.io.colmap import has_colmap_model, read_colmap
from gsmsdr_ns.io.errors import InputError
from gsmsdr_ns.io.images import list_images, read_image_size, resolve_image
from gsmsdr_ns.plugin.dataparser import check_images_match_cameras

POSES_BOUNDS = "poses_bounds.npy"

# COLMAP's world has -y as its gravity guess; nerfstudio's has +z up (same matrix as nerfstudio's colmap parser).
COLMAP_TO_NERFSTUDIO_WORLD = np.array(
    [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
)


@dataclass
class SortedSceneParserConfig(DataParserConfig):
    """Options shared by the file-name-ordered scene readers."""

    _target: Type = field(default_factory=lambda: SortedSceneParser)
    data: Path = Path()
    """Scene directory."""
    images_path: Path = Path("images")
    """Image folder, relative to the data path."""
    downscale_factor: int = 1
    """Read the images from ``<images_path>_<factor>/`` (pre-made downscaled copies) when above 1; intrinsics are
    rescaled to the size of the files found there."""
    orientation_method: Literal["pca", "up", "vertical", "none"] = "up"
    """How to orient the poses (nerfstudio's ``auto_orient_and_center_poses``)."""
    center_method: Literal["poses", "focus", "none"] = "poses"
    """How to centre the poses."""
    auto_scale_poses: bool = True
    """Scale the poses so that the largest camera translation is 1."""
    scale_factor: float = 1.0
    """Extra scale applied to the camera positions (after the automatic one)."""
    scene_scale: float = 1.0
    """Half-size of the scene box."""
    load_3D_points: bool = True
    """Load the COLMAP sparse points (transformed like the poses) as the seed of the Gaussians."""
    verify_images: bool = True
    """Decode every image of a split once while parsing, so truncated or corrupt files fail early with their name."""


@dataclass
class SceneSource:
    """What a pose source provides, before normalisation."""

    cameras: SceneCameras
    files: List[Path]
    """The image file of each camera (same order)."""
    points: Optional[Tuple[np.ndarray, np.ndarray]]
    """COLMAP points (xyz [P, 3] float64 in the source world, rgb [P, 3] uint8), None without a COLMAP model."""
    origin: str
    """The camera file, for messages."""


@dataclass
class LoadedScene:
    """A whole scene in file-name order, normalised once and shared by all splits."""

    cameras: SceneCameras
    """Cameras sorted by image name, in the source's world frame and image size."""
    files: List[Path]
    """The image file of each camera in the image folder."""
    poses: torch.Tensor
    """[N, 3, 4] float32 normalised camera-to-world (nerfstudio / OpenGL camera axes)."""
    transform: torch.Tensor
    """[3, 4] float32: source world -> normalised world, before scaling (``dataparser_transform``)."""
    scale: float
    """Scale applied after ``transform`` (``dataparser_scale``)."""
    points: Optional[Tuple[torch.Tensor, torch.Tensor]]
    """Seed points (xyz [P, 3] float32 normalised, rgb [P, 3] uint8), or None when not loaded."""


def normalise_poses(
    c2w_opencv: np.ndarray, config: SortedSceneParserConfig
) -> Tuple[torch.Tensor, torch.Tensor, float]:
    """[N, 4, 4] OpenCV camera-to-world (COLMAP world) -> nerfstudio poses [N, 3, 4], transform [3, 4], scale."""
    c2w = np.array(c2w_opencv, dtype=np.float64)
    c2w[:, 0:3, 1:3] *= -1  # OpenCV (x right, y down, z forward) -> OpenGL (x right, y up, z back)
    c2w = COLMAP_TO_NERFSTUDIO_WORLD @ c2w
    poses, transform = camera_utils.auto_orient_and_center_poses(
        torch.from_numpy(c2w.astype(np.float32)),
        method=config.orientation_method,
        center_method=config.center_method,
    )
    scale = 1.0
    if config.auto_scale_poses:
        extent = float(torch.max(torch.abs(poses[:, :3, 3])))
        scale = 1.0 / extent if extent > 0 else 1.0
    scale *= config.scale_factor
    poses[:, :3, 3] *= scale
    world = torch.from_numpy(COLMAP_TO_NERFSTUDIO_WORLD.astype(np.float32))
    transform = transform @ world  # [3, 4] @ [4, 4]: applies to homogeneous COLMAP-world points
    return poses, transform, scale


def transform_points(xyz: np.ndarray, transform: torch.Tensor, scale: float) -> torch.Tensor:
    """COLMAP-world points [P, 3] -> normalised world, as nerfstudio transforms its seed points."""
    points = torch.from_numpy(np.asarray(xyz, dtype=np.float32)).reshape(-1, 3)
    homogeneous = torch.cat([points, torch.ones_like(points[:, :1])], dim=1)
    return (homogeneous @ transform.T) * scale


class SortedSceneParser(DataParser):
    """Reads the cameras, images and points of a scene in file-name order (see the module docstring)."""

    config: SortedSceneParserConfig

    def __init__(self, config: SortedSceneParserConfig):
        super().__init__(config)
        self.config = config
        self._scene: Optional[LoadedScene] = None

    # --- layout ----------------------------------------------------------------------------------------------

    def images_dir(self) -> Path:
        factor = int(self.config.downscale_factor)
        if factor < 1:
            raise InputError(f"gsmsdr: downscale_factor must be >= 1, got {factor}.")
        name = str(self.config.images_path) if factor == 1 else f"{self.config.images_path}_{factor}"
        return Path(self.config.data) / name

    def check_data_dir(self) -> Path:
        data = Path(self.config.data)
        if not data.is_dir():
            raise InputError(
                f"gsmsdr: data directory '{data}' does not exist or is not a directory. Pass the scene directory "
                "with --data <dir>."
            )
        images = self.images_dir()
        if not images.is_dir():
            hint = (
                "Create the downscaled copies there or use --pipeline.datamanager.dataparser.downscale-factor 1."
                if self.config.downscale_factor > 1
                else "The scene needs its images in that folder."
            )
            raise InputError(f"gsmsdr: image folder '{images}' does not exist. {hint}")
        return data

    # --- cameras -----------------------------------------------------------------------------------------------

    def colmap_source(self, recon_dir: Path) -> SceneSource:
        """Cameras and points of a COLMAP model, paired with their files; every image on disk must have a pose."""
        images_dir = self.images_dir()
        model = read_colmap(recon_dir)
        cameras, xyz, rgb = cameras_from_colmap(model), model.points.xyz, model.points.rgb
        files = [resolve_image(images_dir, name, f"the COLMAP model '{recon_dir}'") for name in cameras.names]
        self._check_no_unposed_images(images_dir, files, f"'{recon_dir}' has poses for {len(cameras)}")
        return SceneSource(cameras, files, (xyz, rgb), str(recon_dir))

    def read_llff(self, path: Path) -> SceneSource:
        """Cameras from poses_bounds.npy for the images of the image folder (sorted by name); no points."""
        images_dir = self.images_dir()
        names = list_images(images_dir)
        if not names:
            raise InputError(f"gsmsdr: image folder '{images_dir}' contains no images.")
        return SceneSource(read_poses_bounds(path, names), [images_dir / name for name in names], None, str(path))

    @staticmethod
    def _check_no_unposed_images(images_dir: Path, files: Sequence[Path], poses_note: str) -> None:
        on_disk = list_images(images_dir)
        extra = sorted(set(on_disk) - {Path(f).name for f in files})
        if extra:
            raise InputError(
                f"gsmsdr: '{images_dir}' has {len(on_disk)} images but {poses_note}; without a pose: {extra[:5]}"
                f"{' ...' if len(extra) > 5 else ''}. The held-out views are counted over all images sorted by file "
                "name, so every image needs a pose: remove these files or re-run COLMAP on all images."
            )

    def read_source(self) -> SceneSource:
        """The scene's cameras, files and points; subclasses choose the pose source."""
        raise NotImplementedError

    def load_scene(self) -> LoadedScene:
        """The whole scene, read and normalised once per parser instance (train and eval splits share it)."""
        if self._scene is None:
            self.check_data_dir()
            source = self.read_source()
            self.check_image_sizes(source.cameras, range(len(source.files)), source.files)
            poses, transform, scale = normalise_poses(source.cameras.c2w, self.config)
            points = None
            if self.config.load_3D_points:
                if source.points is None or source.points[0].shape[0] == 0:
                    CONSOLE.log(
                        f"[yellow]gsmsdr: no 3D points in {source.origin}; the Gaussians start from random points"
                    )
                    points = (torch.zeros((0, 3), dtype=torch.float32), torch.zeros((0, 3), dtype=torch.uint8))
                else:
                    xyz, rgb = source.points
                    points = (transform_points(xyz, transform, scale), torch.from_numpy(rgb))
            self._scene = LoadedScene(source.cameras, list(source.files), poses, transform, scale, points)
        return self._scene

    @staticmethod
    def check_image_sizes(cameras: SceneCameras, indices: Sequence[int], files: Sequence[Path]) -> None:
        """Each file a rescaled copy of its camera (same aspect), all files of the folder at the same scale.

        Reads image headers only; :class:`InputError` naming the file, its size and the expected size.
        """
        idx = [int(i) for i in indices]
        sizes = [read_image_size(Path(f)) for f in files]
        for i, path, size in zip(idx, files, sizes):
            fit_intrinsics(cameras.intrinsics[i], tuple(cameras.sizes[i]), size, f"image file '{path}'")
        check_same_scale(list(files), cameras.sizes[idx], sizes, f"'{cameras.source}'")

    # --- outputs -----------------------------------------------------------------------------------------------

    def make_outputs(
        self, scene: LoadedScene, indices: Sequence[int], files: Sequence[Path], metadata: Dict[str, Any]
    ) -> DataparserOutputs:
        """Outputs for the views ``indices`` of ``scene`` read from ``files``, intrinsics fitted to each file."""
        idx = [int(i) for i in indices]
        files = [Path(f) for f in files]
        cams = scene.cameras
        intrinsics, sizes = [], []
        for i, path in zip(idx, files):
            size = read_image_size(path)
            intrinsics.append(fit_intrinsics(cams.intrinsics[i], tuple(cams.sizes[i]), size, f"image file '{path}'"))
            sizes.append(size)
        intrinsics = torch.from_numpy(np.asarray(intrinsics, dtype=np.float32).reshape(-1, 4))
        sizes = torch.tensor(sizes, dtype=torch.int64).reshape(-1, 2)
        cameras = Cameras(
            camera_to_worlds=scene.poses[idx],
            fx=intrinsics[:, 0:1],
            fy=intrinsics[:, 1:2],
            cx=intrinsics[:, 2:3],
            cy=intrinsics[:, 3:4],
            width=sizes[:, 0:1],
            height=sizes[:, 1:2],
            distortion_params=torch.from_numpy(cams.distortion[idx].astype(np.float32)),
            camera_type=CameraType.PERSPECTIVE,
        )
        if self.config.verify_images:
            check_images_match_cameras(files, cameras)
        extra: Dict[str, Any] = {}
        if scene.points is not None:
            extra = {"points3D_xyz": scene.points[0], "points3D_rgb": scene.points[1]}
        box = float(self.config.scene_scale)
        return DataparserOutputs(
            image_filenames=files,
            cameras=cameras,
            scene_box=SceneBox(aabb=torch.tensor([[-box] * 3, [box] * 3], dtype=torch.float32)),
            dataparser_scale=scene.scale,
            dataparser_transform=scene.transform,
            metadata={
                **extra,
                "image_names": [cams.names[i] for i in idx],
                "pose_source": cams.source,
                "pose_scale": float(scene.scale),
                **metadata,
            },
        )


def split_indices(split: str, train: np.ndarray, test: np.ndarray) -> np.ndarray:
    if split == "train":
        return train
    if split in ("val", "test"):
        return test
    raise ValueError(f"Unknown dataparser split {split!r} (expected train, val or test)")


def find_colmap_model(data: Path, candidates: Sequence[Path]) -> Optional[Path]:
    """The first of ``candidates`` (relative to ``data``) that holds a COLMAP model, or None."""
    for candidate in candidates:
        if has_colmap_model(Path(data) / candidate):
            return Path(data) / candidate
    return None

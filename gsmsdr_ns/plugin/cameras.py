"""Camera conversions between nerfstudio and the rasterizer (pure functions): world-to-camera matrices in gsplat's
OpenCV convention, and a camera's intrinsics at a render downscale, built on the device without host reads; and
the training images' sizes, read from their cameras once."""

from __future__ import annotations

from typing import Dict, Optional, Tuple

import torch
from nerfstudio.cameras.cameras import Cameras
from torch import Tensor

__all__ = ["viewmats_from_camera_to_worlds", "intrinsics_at_scale", "TrainImageSizes"]


def viewmats_from_camera_to_worlds(camera_to_worlds: Tensor) -> Tensor:
    """World-to-camera matrices in gsplat's OpenCV convention from nerfstudio camera-to-world poses.

    Args:
        camera_to_worlds: [C, 3, 4] (or [C, 4, 4]) poses, OpenGL axes (x right, y up, z backwards).

    Returns:
        [C, 4, 4] world-to-camera matrices with OpenCV axes (x right, y down, z forwards).
    """
    if camera_to_worlds.ndim != 3 or camera_to_worlds.shape[-2] not in (3, 4) or camera_to_worlds.shape[-1] != 4:
        raise ValueError(f"expected camera_to_worlds of shape [C, 3, 4], got {tuple(camera_to_worlds.shape)}")
    # constants are built on the device without Python-scalar writes (each would be a host copy per call)
    rotation = torch.cat([camera_to_worlds[:, :3, :1], -camera_to_worlds[:, :3, 1:3]], dim=2)  # negate camera y, z
    translation = camera_to_worlds[:, :3, 3:4]
    rotation_inv = rotation.transpose(1, 2)
    translation_inv = -rotation_inv @ translation
    eye = torch.eye(4, dtype=camera_to_worlds.dtype, device=camera_to_worlds.device)
    bottom = eye[3:].expand(camera_to_worlds.shape[0], 1, 4)
    return torch.cat([torch.cat([rotation_inv, translation_inv], dim=2), bottom], dim=1)


def intrinsics_at_scale(
    camera: Cameras, downscale: int, device: torch.device, full_size: Optional[Tuple[int, int]] = None
) -> Tuple[Tensor, int, int]:
    """Pinhole intrinsics and image size of a single camera rendered ``downscale`` times smaller.

    Matches ``Cameras.rescale_output_resolution(1 / downscale)`` (floor rounding) without mutating the camera.
    ``full_size``: the camera's (width, height) if known; else it is read from the camera (a sync on a GPU).

    Returns:
        K: [1, 3, 3] on ``device``; width; height.
    """
    # built from the camera's own tensors: Cameras.get_intrinsics_matrices fills a CPU matrix, which on a GPU is four
    # device-to-host reads and a copy back every step
    fx, fy, cx, cy = (getattr(camera, name).reshape(-1) for name in ("fx", "fy", "cx", "cy"))
    zero, one = torch.zeros_like(fx), torch.ones_like(fx)
    K = torch.stack([fx, zero, cx, zero, fy, cy, zero, zero, one], dim=-1).reshape(-1, 3, 3).to(device)
    if downscale > 1:
        K = torch.cat([K[:, :2] / downscale, K[:, 2:]], dim=1)
    if full_size is None:
        full_size = int(camera.width.reshape(-1)[0].item()), int(camera.height.reshape(-1)[0].item())
    return K, full_size[0] // downscale, full_size[1] // downscale


class TrainImageSizes:
    """Full (width, height) of each training image (``camera.metadata["cam_idx"]``), read from its camera the first
    time only: training images keep their size, and reading it every step would wait for the device."""

    def __init__(self) -> None:
        self._sizes: Dict[int, Tuple[int, int]] = {}

    def get(self, camera: Cameras) -> Optional[Tuple[int, int]]:
        """The camera's full size; None for a camera without ``cam_idx``."""
        if not camera.metadata or "cam_idx" not in camera.metadata:
            return None
        cam_idx = int(camera.metadata["cam_idx"])
        size = self._sizes.get(cam_idx)
        if size is None:
            size = int(camera.width.reshape(-1)[0].item()), int(camera.height.reshape(-1)[0].item())
            self._sizes[cam_idx] = size
        return size

    def __contains__(self, cam_idx: int) -> bool:
        return cam_idx in self._sizes

    def __iter__(self):
        return iter(self._sizes)

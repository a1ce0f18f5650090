"""The ``gsmsdr`` datamanager: nerfstudio's full-image datamanager reading images with gsmsdr's decoder, with its
training batch marked as the ``data`` timing stage (``gsmsdr_ns.timing_hooks``; a no-op unless a timing recorder is
attached)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, Tuple, Type

import numpy as np
import numpy.typing as npt
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.data.datamanagers.full_images_datamanager import FullImageDatamanager, FullImageDatamanagerConfig
from nerfstudio.data.datasets.base_dataset import InputDataset

from gsmsdr_ns.io.images import read_image
from gsmsdr_ns.timing_hooks import stage


class GSMSDRInputDataset(InputDataset):
    """nerfstudio's ``InputDataset`` decoding images with :func:`gsmsdr_ns.io.images.read_image`: 16-bit files are
    scaled to 8 bits (nerfstudio's loader keeps the low byte of every 16-bit value, which trains on noise), palette
    images become their colours, and a missing, truncated or corrupt file is an InputError naming it."""

    def get_numpy_image(self, image_idx: int) -> npt.NDArray[np.uint8]:
        """[H, W, 3 or 4] uint8 image, resized by ``scale_factor`` as nerfstudio resizes (PIL, bilinear)."""
        image = read_image(self._dataparser_outputs.image_filenames[image_idx])
        if self.scale_factor != 1.0:
            from PIL import Image

            height, width = image.shape[:2]
            size = (int(width * self.scale_factor), int(height * self.scale_factor))
            image = np.asarray(Image.fromarray(image).resize(size, resample=Image.Resampling.BILINEAR))
        return image


class GSMSDRDatamanager(FullImageDatamanager[GSMSDRInputDataset]):
    """``FullImageDatamanager`` over :class:`GSMSDRInputDataset` whose ``next_train`` is the ``data`` stage that
    starts a training step."""

    def next_train(self, step: int) -> Tuple[Cameras, Dict]:
        with stage("data", starts_step=True):
            return super().next_train(step)


@dataclass
class GSMSDRDatamanagerConfig(FullImageDatamanagerConfig):
    """nerfstudio's full-image datamanager settings; builds a :class:`GSMSDRDatamanager`."""

    _target: Type = field(default_factory=lambda: GSMSDRDatamanager)

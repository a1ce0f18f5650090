"""The ``gsmsdr`` datamanager: nerfstudio's full-image datamanager with its training batch marked as the ``data``
timing stage (``gsmsdr_ns.timing_hooks``; a no-op unless a timing recorder is attached)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, Tuple, Type

from nerfstudio.cameras.cameras import Cameras
from nerfstudio.data.datamanagers.full_images_datamanager import FullImageDatamanager, FullImageDatamanagerConfig

from gsmsdr_ns.timing_hooks import stage


class GSMSDRDatamanager(FullImageDatamanager):
    """``FullImageDatamanager`` whose ``next_train`` is the ``data`` stage that starts a training step."""

    def next_train(self, step: int) -> Tuple[Cameras, Dict]:
        with stage("data", starts_step=True):
            return super().next_train(step)


@dataclass
class GSMSDRDatamanagerConfig(FullImageDatamanagerConfig):
    """nerfstudio's full-image datamanager settings; builds a :class:`GSMSDRDatamanager`."""

    _target: Type = field(default_factory=lambda: GSMSDRDatamanager)

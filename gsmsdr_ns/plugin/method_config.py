"""The ``gsmsdr`` TrainerConfig: splatfacto's schedule and optimizers with the gsmsdr dataparser and model.

Runs on whatever device is there: ``machine.device_type`` defaults to CUDA when available, else CPU, so
``ns-train gsmsdr --data <scene>`` works on a CPU-only machine without extra flags.  Images are cached on the
training device (``cache_images="gpu"`` means "the device" in nerfstudio; ``"cpu"`` would pin memory, which needs
CUDA).
"""

from __future__ import annotations

import torch
from nerfstudio.configs.base_config import MachineConfig, ViewerConfig
from nerfstudio.data.datamanagers.full_images_datamanager import FullImageDatamanagerConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig
from nerfstudio.engine.trainer import TrainerConfig
from nerfstudio.pipelines.base_pipeline import VanillaPipelineConfig

from gsmsdr_ns.plugin.auto_dataparser import GSMSDRAutoDataParserConfig
from gsmsdr_ns.plugin.model import GSMSDRModelConfig

MAX_STEPS = 30000


def default_device_type() -> str:
    """ "cuda" when a GPU is visible, else "cpu"."""
    return "cuda" if torch.cuda.is_available() else "cpu"


def _adam(lr: float) -> AdamOptimizerConfig:
    return AdamOptimizerConfig(lr=lr, eps=1e-15)


def _warmup_decay(lr_final: float) -> ExponentialDecaySchedulerConfig:
    return ExponentialDecaySchedulerConfig(lr_final=lr_final, max_steps=MAX_STEPS, warmup_steps=1000, lr_pre_warmup=0)


def gsmsdr_optimizers() -> dict:
    """Per-parameter-group optimizers (keys match ``GSMSDRModel.get_param_groups``), as in splatfacto."""
    return {
        "means": {
            "optimizer": _adam(1.6e-4),
            "scheduler": ExponentialDecaySchedulerConfig(lr_final=1.6e-6, max_steps=MAX_STEPS),
        },
        "features_dc": {"optimizer": _adam(0.0025), "scheduler": None},
        "features_rest": {"optimizer": _adam(0.0025 / 20), "scheduler": None},
        "opacities": {"optimizer": _adam(0.05), "scheduler": None},
        "scales": {"optimizer": _adam(0.005), "scheduler": None},
        "quats": {"optimizer": _adam(0.001), "scheduler": None},
        "camera_opt": {"optimizer": _adam(1e-4), "scheduler": _warmup_decay(5e-7)},
        "bilateral_grid": {"optimizer": _adam(2e-3), "scheduler": _warmup_decay(1e-4)},
    }


def gsmsdr_trainer_config() -> TrainerConfig:
    """A fresh ``gsmsdr`` TrainerConfig (``ns-train gsmsdr``)."""
    return TrainerConfig(
        method_name="gsmsdr",
        steps_per_eval_image=100,
        steps_per_eval_batch=0,
        steps_per_save=2000,
        steps_per_eval_all_images=1000,
        max_num_iterations=MAX_STEPS,
        mixed_precision=False,
        machine=MachineConfig(device_type=default_device_type()),
        pipeline=VanillaPipelineConfig(
            datamanager=FullImageDatamanagerConfig(
                dataparser=GSMSDRAutoDataParserConfig(),
                cache_images="gpu",
                cache_images_type="uint8",
            ),
            model=GSMSDRModelConfig(),
        ),
        optimizers=gsmsdr_optimizers(),
        viewer=ViewerConfig(num_rays_per_chunk=1 << 15),
        vis="viewer",
    )

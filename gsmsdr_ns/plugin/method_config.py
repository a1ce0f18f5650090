"""The method presets, in one place: ``gsmsdr`` (the paper's set-up), ``gsmsdr-lite`` (fast, for CPU and previews)
and ``gsmsdr-cpu`` (real-size captures converged on a CPU).

``gsmsdr``: splatfacto's schedule and optimizers with the gsmsdr dataparser and model, the full-width blur field
(MAAN + HPKO, kernels 5 / 9 / 17 following the 1/4 -> 1/2 -> 1 resolution schedule) trained with Adam at a constant
1e-4 (BAGS: 5e-4; see ``gsmsdr_optimizers``), and the resolution-loss model's residual kernels with Adam at a
constant 1e-4.

``gsmsdr-lite``: the same model with the ``lite`` blur field (half the channels), SH degree 1, kernels 5 / 9 / 13,
7000 steps with the resolution doubling every 1000 steps and densification until step 4000 (learning-rate
schedules shortened to match). Its field has half the channels of the default one, so a blurred-image step costs
less; a sharp-image step does not run the field in either preset.

``gsmsdr-cpu``: one learnt kernel per view and scale (blur field mode ``view``: no feature network) of 9 / 17 / 33
px, with the thin lens for defocus, on the benchmark suites' schedule at 6000 steps (:class:`TrainingSchedule`, 1/4 ->
1/2 -> full resolution over the first half, densification over the first half with a CPU-sized threshold). On the
shaken fern at 458x333 (``configs/bench/real-size.yaml``, blur of 13-27 px) mode ``view`` equalled the MAAN field's
test PSNR with the preset's 17 px kernels (23.72 vs 23.71 dB) at 42 % of its training time; 25 px kernels, which
cover that blur, gained 0.18 dB more (33 px: the same). On the generated 600x400 strong shake (16-32 px) each step
17 -> 25 -> 33 px gained 0.18 dB (20.59, 20.77, 20.95 dB): kernels must cover the blur, and a larger one costs
about the same (a kernel per image is applied by an FFT). Beyond the blur it stops (49 px: 23.93 and 20.95 dB), so
the preset keeps 33 px, the per-pixel limit (``MAX_KERNEL_SIZE``); mode ``view`` takes up to
``MAX_VIEW_KERNEL_SIZE`` for larger captures (``--pipeline.model.blur-field.kernel-sizes 17 33 65`` at 1300 px).
Views that may be shaken are first warped along a learnt camera rotation path (``camera_shake``, rendered with a
``render_margin``): roll and a wide view make a turning camera's blur vary across the photo, which one kernel per
view cannot follow. With the paths the preset gained 0.68 dB on the shaken fern (24.58 against 23.90) and 0.71 dB
on the generated 600x400 strong shake (21.64 against 20.93), seed 0, 3000 steps, at 1.36x and 1.18x the training
time (docs/results/real-size/shake); the fern was still gaining at 3000 steps (+0.40 dB over the last quarter).
At 6000 steps the preset reached 25.44 dB on the fern (plain Gaussians 23.47 at 6000 steps) and 21.81 on the
600x400 scene (flat over its last quarter), whole runs of 58 and 68 min on one thread
(docs/results/real-size/long-shake): the preset trains 6000 steps. The path also translates the camera
(``shake_translation``), for what differs from the render's median depth only (``shake_parallax``: the rotation
carries the blur at that depth, so the two cannot trade off): at 6000 steps 22.25 dB on the 600x400 scene (sharp
bound 23.23) and 25.51 on the fern, at 1.12x the rotation paths' training time on the fern
(docs/results/real-size/shake-fit). An SH degree is unlocked every 1000 steps (degree 3 when full resolution
starts) instead of the suites' every quarter of the run (degree 3 at step 4500): 25.65 / 25.72 dB on the fern
(seeds 0 / 1, against 25.51 / 25.58), its last quarter of the training time +0.17 / +0.06 dB (against +0.23 /
+0.10); 22.27 on the 600x400 scene (22.25).

All train with :class:`GSMSDRTrainer` (nerfstudio's Trainer with atomic checkpoints and checked checkpoint loading).

Runs on whatever device is there: ``machine.device_type`` defaults to CUDA when available, else CPU, so
``ns-train gsmsdr --data <scene>`` works on a CPU-only machine without extra flags.  Images are cached on the
training device (``cache_images="gpu"`` means "the device" in nerfstudio; ``"cpu"`` would pin memory, which needs
CUDA).
"""

from __future__ import annotations

import torch
from nerfstudio.configs.base_config import MachineConfig, ViewerConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig
from nerfstudio.pipelines.base_pipeline import VanillaPipelineConfig

from gsmsdr_ns.blur.degradation_config import DegradationConfig
from gsmsdr_ns.blur.field import BlurFieldConfig
from gsmsdr_ns.plugin.auto_dataparser import GSMSDRAutoDataParserConfig
from gsmsdr_ns.plugin.checkpoint_compat import register_presets
from gsmsdr_ns.plugin.datamanager import GSMSDRDatamanagerConfig
from gsmsdr_ns.plugin.model import GSMSDRModelConfig
from gsmsdr_ns.plugin.schedule import TrainingSchedule
from gsmsdr_ns.plugin.trainer import GSMSDRTrainerConfig

MAX_STEPS = 30000
LITE_MAX_STEPS = 7000
CPU_SCHEDULE = TrainingSchedule(steps=6000, num_downscales=2, densify_grad_thresh=0.002, sh_degree_fraction=1 / 6)
"""``gsmsdr-cpu``'s schedule: the real-size suite's (configs/bench/real-size.yaml) at 6000 steps, with an SH degree
unlocked every 1000 steps (splatfacto's interval; the suites' default unlocks degree 3 at three quarters of the run)."""


def default_device_type() -> str:
    """ "cuda" when a GPU is visible, else "cpu"."""
    return "cuda" if torch.cuda.is_available() else "cpu"


def _adam(lr: float, eps: float = 1e-15) -> AdamOptimizerConfig:
    return AdamOptimizerConfig(lr=lr, eps=eps)


def _warmup_decay(lr_final: float, max_steps: int) -> ExponentialDecaySchedulerConfig:
    return ExponentialDecaySchedulerConfig(lr_final=lr_final, max_steps=max_steps, warmup_steps=1000, lr_pre_warmup=0)


def gsmsdr_optimizers(max_steps: int = MAX_STEPS) -> dict:
    """Per-parameter-group optimizers (keys match ``GSMSDRModel.get_param_groups``): splatfacto's for the Gaussians,
    constant-rate Adam for the blur field (1e-4), its per-view kernels (3e-2) and thin lens (1e-2) and the
    resolution model's residual kernels (1e-4). Groups a scene does not build (a sharp scene has no blur field) are
    simply unused.

    The field's rate is below BAGS' 5e-4 so that its per-pixel heads follow the per-view kernels instead of racing
    them."""
    return {
        "means": {
            "optimizer": _adam(1.6e-4),
            "scheduler": ExponentialDecaySchedulerConfig(lr_final=1.6e-6, max_steps=max_steps),
        },
        "features_dc": {"optimizer": _adam(0.0025), "scheduler": None},
        "features_rest": {"optimizer": _adam(0.0025 / 20), "scheduler": None},
        "opacities": {"optimizer": _adam(0.05), "scheduler": None},
        "scales": {"optimizer": _adam(0.005), "scheduler": None},
        "quats": {"optimizer": _adam(0.001), "scheduler": None},
        "camera_opt": {"optimizer": _adam(1e-4), "scheduler": _warmup_decay(5e-7, max_steps)},
        "bilateral_grid": {"optimizer": _adam(2e-3), "scheduler": _warmup_decay(1e-4, max_steps)},
        "blur_field": {"optimizer": _adam(1e-4, eps=1e-8), "scheduler": None},
        "blur_view_kernels": {"optimizer": _adam(3e-2, eps=1e-8), "scheduler": None},
        "blur_defocus": {"optimizer": _adam(1e-2, eps=1e-8), "scheduler": None},
        "blur_shake": {"optimizer": _adam(1e-1, eps=1e-8), "scheduler": None},
        "resolution_model": {"optimizer": _adam(1e-4, eps=1e-8), "scheduler": None},
    }


def _trainer_config(method_name: str, model: GSMSDRModelConfig, max_steps: int) -> GSMSDRTrainerConfig:
    return GSMSDRTrainerConfig(
        method_name=method_name,
        steps_per_eval_image=100,
        steps_per_eval_batch=0,
        steps_per_save=2000,
        steps_per_eval_all_images=1000,
        max_num_iterations=max_steps,
        mixed_precision=False,
        machine=MachineConfig(device_type=default_device_type()),
        pipeline=VanillaPipelineConfig(
            datamanager=GSMSDRDatamanagerConfig(
                dataparser=GSMSDRAutoDataParserConfig(),
                cache_images="gpu",
                cache_images_type="uint8",
            ),
            model=model,
        ),
        optimizers=gsmsdr_optimizers(max_steps),
        viewer=ViewerConfig(num_rays_per_chunk=1 << 15),
        vis="viewer",
    )


def gsmsdr_trainer_config() -> GSMSDRTrainerConfig:
    """A fresh ``gsmsdr`` trainer config (``ns-train gsmsdr``): the paper's set-up."""
    return _trainer_config("gsmsdr", GSMSDRModelConfig(), MAX_STEPS)


def gsmsdr_lite_trainer_config() -> GSMSDRTrainerConfig:
    """A fresh ``gsmsdr-lite`` trainer config (``ns-train gsmsdr-lite``): fast preset for CPU and previews."""
    model = GSMSDRModelConfig(
        sh_degree=1,
        resolution_schedule=1000,
        stop_split_at=4000,
        blur_field=BlurFieldConfig(size="lite", kernel_sizes=(5, 9, 13)),
    )
    return _trainer_config("gsmsdr-lite", model, LITE_MAX_STEPS)


def gsmsdr_cpu_trainer_config() -> GSMSDRTrainerConfig:
    """A fresh ``gsmsdr-cpu`` trainer config (``ns-train gsmsdr-cpu``): a learnt camera path (rotations, and
    translations for what differs from the render's median depth) and per-view kernels of up to 33 px on views that
    may be shaken (rendered with a margin), the thin lens for defocus, on the 6000-step :data:`CPU_SCHEDULE`, for
    real-size captures on a CPU."""
    model = GSMSDRModelConfig(
        blur_field=BlurFieldConfig(mode="view", kernel_sizes=(9, 17, 33)),
        degradation_model=DegradationConfig(
            render_margin=True, camera_shake=True, shake_translation=True, shake_parallax=True
        ),
    )
    config = _trainer_config("gsmsdr-cpu", model, CPU_SCHEDULE.steps)
    CPU_SCHEDULE.apply(config)
    return config


# checkpoint loading names the preset a checkpoint of another one was trained with (it cannot import this module)
register_presets(gsmsdr_trainer_config, gsmsdr_lite_trainer_config, gsmsdr_cpu_trainer_config)

"""What a bench method is: a preset of ``gsmsdr_ns.plugin.method_config`` (its *base*) and the options it changes
(:class:`MethodSpec`), and how those become a TrainerConfig. The registry of named methods is
``gsmsdr_ns.bench.methods``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, Optional, Tuple

BASES = ("plain", "gsmsdr", "gsmsdr-lite", "gsmsdr-cpu", "sharp")
"""Presets a method starts from (see the module docstring)."""


def base_config(base: str, data: Path, output_dir: Path):
    """The TrainerConfig of the preset ``base`` on ``data``: no viewer, no periodic evaluation or image logging,
    CPU unless CUDA is there (schedules not yet shortened)."""
    from gsmsdr_ns.plugin import method_config as presets

    if base not in BASES:
        raise ValueError(f"unknown base preset {base!r}; valid: {', '.join(BASES)}")
    make = {"gsmsdr-lite": presets.gsmsdr_lite_trainer_config, "gsmsdr-cpu": presets.gsmsdr_cpu_trainer_config}
    config = make.get(base, presets.gsmsdr_trainer_config)()
    if base in ("plain", "sharp"):
        config.pipeline.model.degradation = "sharp"
        set_pose_refinement(config.pipeline.model, "off")  # splatfacto's default
    config.data = Path(data)
    config.pipeline.datamanager.data = Path(data)
    config.output_dir = Path(output_dir)
    config.vis = "tensorboard"
    config.steps_per_eval_image = 0
    config.steps_per_eval_all_images = 0
    config.pipeline.model.viewer_blur_outputs = False  # evaluation renders rgb only (the metrics use rgb alone)
    return config


def set_pose_refinement(model, views: str) -> None:
    """Camera optimizer of a GSMSDRModelConfig: "off", or SO3xR3 on the "degraded" or "all" training views."""
    if views not in ("off", "degraded", "all"):
        raise ValueError(f"pose refinement must be off, degraded or all, got {views!r}")
    model.camera_optimizer = dataclasses.replace(model.camera_optimizer, mode="off" if views == "off" else "SO3xR3")
    if views != "off":
        model.camera_optimizer_views = views


def set_lr_decay(config, group: str, lr_final: float, hold_fraction: float = 0.0) -> None:
    """Give the optimizer group ``group`` of a TrainerConfig an exponential decay to ``lr_final`` over its steps
    (no warm-up), starting after ``hold_fraction`` of them (the preset's rate held until then)."""
    from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig

    from gsmsdr_ns.plugin.lr_schedulers import HeldExponentialDecaySchedulerConfig

    if group not in config.optimizers:
        raise ValueError(f"no optimizer group {group!r}; valid: {', '.join(sorted(config.optimizers))}")
    steps = config.max_num_iterations
    config.optimizers[group]["scheduler"] = (
        HeldExponentialDecaySchedulerConfig(lr_final=lr_final, max_steps=steps, hold_fraction=hold_fraction)
        if hold_fraction > 0
        else ExponentialDecaySchedulerConfig(lr_final=lr_final, max_steps=steps, warmup_steps=0)
    )


@dataclass(frozen=True)
class MethodSpec:
    """How one suite method differs from its base preset."""

    name: str
    """Suite method name (``methods:`` of a suite file)."""
    label: str
    """Row label in the tables."""
    base: str
    """Base preset: plain / sharp (gsmsdr preset with degradation sharp), gsmsdr, gsmsdr-lite."""
    overrides: Tuple[Tuple[str, Any], ...] = ()
    """Fields replaced on the preset's ``BlurFieldConfig`` (the field's architecture) or ``DegradationConfig``
    (everything else), each where it is defined."""
    sharp_data: bool = False
    """Train on the sharp twin of the scene (the upper bound) instead of its degraded images."""
    description: str = ""
    """One line for humans."""
    true_records: bool = False
    """On a scene built from real photos, train on its twin that carries the true degradation records (the scene
    itself has none, so the dataparser estimates them)."""
    degraded_poses: bool = False
    """With ``sharp_data``, on a scene built from real photos: the sharp photos posed and undistorted by the
    degraded photos' structure-from-motion instead of the sharp twin's own (what a perfect deblurring could reach
    with those poses and that camera). Elsewhere the same as ``sharp``."""
    pose_refinement: Optional[str] = None
    """The camera optimizer: None keeps the base preset's (off, as in splatfacto), "off", "degraded" (the views with
    a degradation model) or "all" (every training view)."""
    lr_final: Tuple[Tuple[str, float], ...] = ()
    """(optimizer group, final rate): the group's rate decays exponentially from the preset's to this one over the
    run (the suite's schedule scales the decay to its steps)."""
    lr_hold_fraction: float = 0.0
    """With ``lr_final``: the groups keep the preset's rate for this fraction of the run, then decay."""
    model_overrides: Tuple[Tuple[str, Any], ...] = ()
    """Fields replaced on the preset's ``GSMSDRModelConfig`` itself (the Gaussian model's options, such as
    ``degraded_densify_grad_scale``); an option it does not have raises ValueError."""

    def make_config(self, data: Path, output_dir: Path):
        """The TrainerConfig of this method on ``data`` (schedules not yet shortened)."""
        config = base_config(self.base, data, output_dir)
        model = config.pipeline.model
        if self.overrides:
            model.blur_field, model.degradation_model = apply_overrides(
                model.blur_field, model.degradation_model, dict(self.overrides)
            )
        if self.pose_refinement is not None:
            set_pose_refinement(model, self.pose_refinement)
        for group, final in self.lr_final:
            set_lr_decay(config, group, final, self.lr_hold_fraction)
        if self.model_overrides:
            config.pipeline.model = replace_model_options(config.pipeline.model, dict(self.model_overrides))
        return config

    @property
    def has_blur_field(self) -> bool:
        return self.base in ("gsmsdr", "gsmsdr-lite", "gsmsdr-cpu")

    def modules(self) -> Optional[Dict[str, bool]]:
        """Table 6's check marks (GAKA, SAFM, MCA, RGBD, HPKO) of the gsmsdr-preset blur field, None otherwise."""
        if self.base in ("plain",):
            return dict(GAKA=False, SAFM=False, MCA=False, RGBD=False, HPKO=False)
        if self.base != "gsmsdr":
            return None
        from gsmsdr_ns.blur.degradation_config import DegradationConfig
        from gsmsdr_ns.blur.field import BlurFieldConfig

        mods = apply_overrides(BlurFieldConfig(), DegradationConfig(), dict(self.overrides))[0].modules
        return dict(GAKA=mods.gaka, SAFM=mods.safm, MCA=mods.mca, RGBD=mods.rgbd, HPKO=mods.hpko)


def _check_options(options: Dict[str, Any], *configs) -> None:
    """Raise ValueError naming every key of ``options`` that is a field of none of the dataclasses ``configs``."""
    names = {f.name for config in configs for f in dataclasses.fields(config)}
    unknown = sorted(set(options) - names)
    if unknown:
        kinds = " or ".join(type(config).__name__ for config in configs)
        raise ValueError(f"not an option of {kinds}: {', '.join(unknown)}")


def apply_overrides(blur_field, degradation, overrides: Dict[str, Any]):
    """(blur_field, degradation) with each of ``overrides`` replaced where it is defined: a ``BlurFieldConfig`` field
    on ``blur_field``, a ``DegradationConfig`` field on ``degradation``. An option of neither raises ValueError."""
    _check_options(overrides, blur_field, degradation)
    field_names = {f.name for f in dataclasses.fields(blur_field)}
    on_field = {k: v for k, v in overrides.items() if k in field_names}
    on_degradation = {k: v for k, v in overrides.items() if k not in field_names}
    return dataclasses.replace(blur_field, **on_field), dataclasses.replace(degradation, **on_degradation)


def replace_model_options(model, options: Dict[str, Any]):
    """``model`` (a GSMSDRModelConfig) with each of ``options`` replaced; an option it does not have raises
    ValueError naming it."""
    _check_options(options, model)
    return dataclasses.replace(model, **options)


def make_method(
    name: str,
    label: str,
    base: str,
    description: str,
    sharp_data: bool = False,
    model_overrides: Tuple[Tuple[str, Any], ...] = (),
    **options,
) -> MethodSpec:
    """A :class:`MethodSpec` whose ``options`` (keyword arguments) replace fields of the base preset's blur field or
    degradation model."""
    return MethodSpec(
        name, label, base, tuple(sorted(options.items())), sharp_data, description, model_overrides=model_overrides
    )


__all__ = [
    "BASES",
    "MethodSpec",
    "apply_overrides",
    "base_config",
    "make_method",
    "replace_model_options",
    "set_lr_decay",
    "set_pose_refinement",
]

"""One training schedule: a gsmsdr TrainerConfig's step-dependent schedules scaled to a short step budget.

The presets (``gsmsdr_ns.plugin.method_config``) are written for 30000 (``gsmsdr``) or 7000 (``gsmsdr-lite``) steps.
A shorter run needs the HPKO / resolution schedule, the blur field's warm-up, the refinement (densify / cull) window
and the learning-rate decay scaled to its budget; :class:`TrainingSchedule` does that in one place, for the
benchmark suites (:meth:`TrainingSchedule.bench`, every method the same) and the demo (:meth:`TrainingSchedule.demo`).
The two presets differ only in the fields the demo sets explicitly.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Optional, Tuple

SPLATFACTO_STEPS = 30000
"""Length of splatfacto's schedule, the reference the step-valued splatfacto settings are scaled from."""


@dataclass(frozen=True)
class TrainingSchedule:
    """A step budget and the schedules derived from it (defaults: the benchmark suites' schedule)."""

    steps: int
    """Training steps (``max_num_iterations``)."""
    num_downscales: int = 1
    """Resolution schedule: start at 1 / 2^num_downscales (the HPKO kernel scale follows) and double that often."""
    resolution_fraction: float = 0.5
    """The doublings are spread evenly over this fraction of the steps."""
    blur_warmup_fraction: float = 0.05
    """Blur field skipped for the first fraction of the steps (preset: 250 of 30000 steps, BAGS)."""
    densify_until_fraction: float = 0.5
    """Densification (split / duplicate) stops after this fraction of the steps (splatfacto: 15000 of 30000)."""
    refinements: int = 15
    """Refinement (densify / cull) rounds over the refinement window."""
    refinement_window_fraction: Optional[float] = None
    """Fraction of the steps the refinement rounds are spread over (None: the densification window)."""
    densify_warmup_fraction: Optional[float] = None
    """Steps before the first refinement, as a fraction of the steps (None: one refinement interval)."""
    screen_size_split_until: Optional[int] = 4000
    """Splatfacto's last screen-size split step in its 30000-step schedule, scaled to ``steps`` (None: keep the
    preset's step unscaled)."""
    reset_alpha_every: int = 10**6
    """Opacity reset interval in refinement rounds (10**6: no reset in a short run; splatfacto: 30)."""
    densify_grad_thresh: float = 0.002
    """Higher than splatfacto's 0.0008 to keep the Gaussian count CPU-sized."""
    lr_schedulers: Tuple[str, ...] = ("means", "camera_opt", "bilateral_grid", "blur_shake", "blur_view_kernels")
    """Optimizer groups whose learning-rate scheduler is scaled to ``steps`` (warm-up capped at a tenth of the decay);
    groups without a scheduler keep their constant rate."""
    lr_decay_fraction: float = 1.0
    """The scaled schedulers reach their final rate at this fraction of the steps and hold it after."""
    sh_degree_fraction: float = 0.25
    """Steps between SH degree unlocks, as a fraction of the steps (0.25: degree 3 at three quarters; splatfacto:
    1000 of 30000)."""

    def __post_init__(self) -> None:
        if isinstance(self.steps, bool) or not isinstance(self.steps, int) or self.steps < 1:
            raise ValueError(f"steps must be an integer >= 1, got {self.steps!r}")
        if self.num_downscales < 0:
            raise ValueError(f"num_downscales must be >= 0, got {self.num_downscales}")
        if self.refinements < 1:
            raise ValueError(f"refinements must be >= 1, got {self.refinements}")
        fractions = ("resolution_fraction", "blur_warmup_fraction", "densify_until_fraction",
                     "refinement_window_fraction", "densify_warmup_fraction")  # fmt: skip
        for name in fractions:
            value = getattr(self, name)
            if value is not None and not 0.0 <= value <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {value}")
        for name in ("lr_decay_fraction", "sh_degree_fraction"):
            if not 0.0 < getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in (0, 1], got {getattr(self, name)}")

    @classmethod
    def bench(cls, steps: int, **overrides: Any) -> "TrainingSchedule":
        """The benchmark suites' schedule (every method gets the same one)."""
        return cls(steps, **overrides)

    @classmethod
    def demo(cls, steps: int, **overrides: Any) -> "TrainingSchedule":
        """The demo's schedule: three resolution stages over two thirds of the steps (HPKO 1/4 with 5x5 kernels, 1/2
        with 9x9, then full resolution), refinements over all steps, the preset's screen-size and camera
        learning-rate schedules, an opacity reset every 1000 refinement rounds."""
        values = dict(num_downscales=2, resolution_fraction=2 / 3, refinement_window_fraction=1.0,
                      densify_warmup_fraction=0.1, screen_size_split_until=None, reset_alpha_every=1000,
                      lr_schedulers=("means",))  # fmt: skip
        return cls(steps, **{**values, **overrides})

    def with_steps(self, steps: int) -> "TrainingSchedule":
        return dataclasses.replace(self, steps=steps)

    def apply(self, config) -> None:
        """Scale the step-dependent schedules of the gsmsdr TrainerConfig ``config`` to ``steps`` (in place)."""
        steps = self.steps
        config.max_num_iterations = steps
        config.steps_per_save = steps
        model = config.pipeline.model
        model.num_downscales = self.num_downscales
        doublings = max(self.num_downscales, 1)
        model.resolution_schedule = max(int(steps * self.resolution_fraction) // doublings, 1)
        warmup = max(int(steps * self.blur_warmup_fraction), 1)
        model.degradation_model = dataclasses.replace(model.degradation_model, warmup=warmup)
        model.stop_split_at = max(int(steps * self.densify_until_fraction), 1)
        window = model.stop_split_at
        if self.refinement_window_fraction is not None:
            window = int(steps * self.refinement_window_fraction)
        model.refine_every = max(window // self.refinements, 1)
        if self.densify_warmup_fraction is None:
            model.warmup_length = model.refine_every
        else:
            model.warmup_length = max(int(steps * self.densify_warmup_fraction), 1)
        if self.screen_size_split_until is not None:
            model.stop_screen_size_at = max(steps * self.screen_size_split_until // SPLATFACTO_STEPS, 1)
        model.reset_alpha_every = self.reset_alpha_every
        model.densify_grad_thresh = self.densify_grad_thresh
        model.sh_degree_interval = max(int(steps * self.sh_degree_fraction), 1)
        decay_steps = max(int(steps * self.lr_decay_fraction), 1)
        for name in self.lr_schedulers:
            scheduler = config.optimizers.get(name, {}).get("scheduler")
            if scheduler is not None:
                # nerfstudio's exponential decay holds lr_final after max_steps
                scheduler.max_steps = decay_steps
                scheduler.warmup_steps = min(scheduler.warmup_steps, decay_steps // 10)  # decay_steps <= steps


__all__ = ["SPLATFACTO_STEPS", "TrainingSchedule"]

"""A learning-rate schedule nerfstudio does not have: the initial rate held, then an exponential decay.

nerfstudio's ``ExponentialDecayScheduler`` decays from its warm-up's end; a parameter that must keep moving while the
resolution schedule still changes (the shake paths, the per-view kernels) and settle once it is done needs its rate
held first. :class:`HeldExponentialDecaySchedulerConfig` is that schedule, with the hold a fraction of ``max_steps``
so that :meth:`gsmsdr_ns.plugin.schedule.TrainingSchedule.apply`, which sets ``max_steps``, scales it too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Type

from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig, Scheduler
from torch.optim import Optimizer, lr_scheduler


def held_decay_factor(step: int, hold_steps: int, max_steps: int, final_ratio: float) -> float:
    """Multiplier of the initial rate at ``step``: 1 until ``hold_steps``, then exponential down to ``final_ratio``
    at ``max_steps``, held after."""
    if step <= hold_steps or max_steps <= hold_steps:
        return 1.0 if step <= hold_steps else final_ratio
    t = min((step - hold_steps) / (max_steps - hold_steps), 1.0)
    return math.exp(math.log(final_ratio) * t)


@dataclass
class HeldExponentialDecaySchedulerConfig(ExponentialDecaySchedulerConfig):
    """nerfstudio's exponential decay to ``lr_final`` by ``max_steps``, its start moved to ``hold_fraction`` of
    ``max_steps`` (the rate held until then; ``warmup_steps`` and ``lr_pre_warmup`` are not used)."""

    _target: Type = field(default_factory=lambda: HeldExponentialDecayScheduler)
    hold_fraction: float = 0.5
    """Fraction of ``max_steps`` the initial rate is held before the decay starts."""

    def __post_init__(self) -> None:
        if not 0.0 <= self.hold_fraction < 1.0:
            raise ValueError(f"hold_fraction must be in [0, 1), got {self.hold_fraction}")


class HeldExponentialDecayScheduler(Scheduler):
    """The scheduler of :class:`HeldExponentialDecaySchedulerConfig`."""

    config: HeldExponentialDecaySchedulerConfig

    def get_scheduler(self, optimizer: Optimizer, lr_init: float) -> lr_scheduler.LRScheduler:
        lr_final = lr_init if self.config.lr_final is None else self.config.lr_final
        if lr_final <= 0 or lr_init <= 0:
            raise ValueError(f"held exponential decay needs positive rates, got {lr_init} -> {lr_final}")
        max_steps = self.config.max_steps
        hold_steps = int(max_steps * self.config.hold_fraction)
        ratio = lr_final / lr_init

        def factor(step: int) -> float:
            return held_decay_factor(step, hold_steps, max_steps, ratio)

        return lr_scheduler.LambdaLR(optimizer, lr_lambda=factor)


__all__ = ["HeldExponentialDecayScheduler", "HeldExponentialDecaySchedulerConfig", "held_decay_factor"]

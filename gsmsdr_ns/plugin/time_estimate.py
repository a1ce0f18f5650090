"""The remaining training time ``ns-train`` prints (its "ETA"), from the step times so far and the schedule ahead.

nerfstudio's ETA multiplies the remaining steps by the mean of the last 20 step times. Under a resolution schedule
(gsmsdr and splatfacto start at 1/4 resolution) and while densification grows the Gaussians, that is the cost of a
small, early step: the estimate printed in the first half of a run is a fraction of the time left. Here the steps
ahead are costed from the current step time (the mean since the cost last changed), scaled

* by ``(pixels of the step's resolution stage / current pixels) ** pixel_exponent`` (a step's cost grows slower than
  its pixels: projection, sorting and the optimizer do not scale with them), and
* by ``(Gaussians then / Gaussians now) ** gaussian_exponent``, the Gaussian count extrapolated at its recent growth
  rate until densification stops, constant after.

:class:`TimeEstimate` is fed one training step at a time (``add``) and answers ``remaining()`` in seconds.
"""

from __future__ import annotations

import bisect
from collections import deque
from dataclasses import dataclass, field
from functools import cached_property
from typing import Deque, Dict, List, Optional, Sequence, Tuple

__all__ = ["StepSchedule", "TimeEstimate", "format_duration", "step_schedule_of"]


@dataclass(frozen=True)
class StepSchedule:
    """Where a training run's step cost changes."""

    max_steps: int
    """Steps of the whole run (the last step is ``max_steps - 1``)."""
    stage_starts: Tuple[int, ...]
    """First step of each resolution stage, increasing, starting at 0."""
    stage_pixels: Tuple[float, ...]
    """Mean pixels of a training image in each stage (one per ``stage_starts``)."""
    densify_until: int = 0
    """Step after which the Gaussian count stops growing (0: it does not grow)."""
    phase_starts: Tuple[int, ...] = ()
    """Other steps where the step cost changes (the blur field's and the lens's start)."""

    def __post_init__(self) -> None:
        if self.max_steps < 1:
            raise ValueError(f"max_steps must be >= 1, got {self.max_steps}")
        if not self.stage_starts or self.stage_starts[0] != 0 or list(self.stage_starts) != sorted(self.stage_starts):
            raise ValueError(f"stage_starts must increase from 0, got {self.stage_starts}")
        if len(self.stage_pixels) != len(self.stage_starts) or min(self.stage_pixels) <= 0:
            raise ValueError(f"stage_pixels must be {len(self.stage_starts)} positive values, got {self.stage_pixels}")

    def stage(self, step: int) -> int:
        """Index of the resolution stage ``step`` trains in."""
        return bisect.bisect_right(self.stage_starts, step) - 1

    @cached_property
    def phase_bounds(self) -> Tuple[int, ...]:
        """Sorted steps where a phase of constant cost starts: stage starts, ``phase_starts`` and the end of
        densification, below ``max_steps`` (computed once: the trainer asks every step)."""
        starts = set(self.stage_starts) | set(self.phase_starts) | {self.densify_until}
        return tuple(sorted(s for s in starts if 0 <= s < self.max_steps))


def format_duration(seconds: float) -> str:
    """``1 h 05 m``, ``12 m 30 s`` or ``45 s``."""
    seconds = max(int(round(seconds)), 0)
    hours, rest = divmod(seconds, 3600)
    minutes, secs = divmod(rest, 60)
    if hours:
        return f"{hours} h {minutes:02d} m"
    if minutes:
        return f"{minutes} m {secs:02d} s"
    return f"{secs} s"


@dataclass
class _Phase:
    """Step times of one phase of constant cost: its first ``settle`` steps apart, then the last ``window``."""

    settling: List[float]
    times: Deque[float]


@dataclass
class TimeEstimate:
    """Remaining training time of a run with schedule ``schedule``, from the steps recorded so far.

    The first ``settle`` steps after each cost change are left out of its mean while later ones exist (caches,
    the first kernels at a new size); the mean is over the last ``window`` steps of the current phase.
    """

    schedule: StepSchedule
    pixel_exponent: float = 0.70
    """Step cost ~ pixels ** this across resolution stages (the real-size suite's 3000- and 6000-step traces at
    458x333 and 600x400: 0.5-1.0 per stage change, median 0.73; docs/results/real-size/eta.md)."""
    gaussian_exponent: float = 0.2
    """Step cost ~ Gaussians ** this at one resolution (0.19-0.29 within a resolution stage while densification grew
    the Gaussians 2-6x: gsmsdr-cpu on fern at 458x333, plain on the generated 600x400 scene)."""
    settle: int = 3
    window: int = 100
    growth_window: int = 200
    """Steps over which the Gaussians' growth rate is measured."""
    _phases: Dict[int, _Phase] = field(default_factory=dict, repr=False)
    _last_step: int = field(default=-1, repr=False)
    _gaussians: Deque[Tuple[int, int]] = field(default_factory=deque, repr=False)

    def _phase_start(self, step: int) -> int:
        bounds = self.schedule.phase_bounds
        i = bisect.bisect_right(bounds, step) - 1
        return bounds[i] if i >= 0 else 0

    def add(self, step: int, seconds: float, num_gaussians: int = 0) -> None:
        """Record training step ``step``: it took ``seconds`` and ended with ``num_gaussians`` Gaussians (0: not
        known, the Gaussian term is left out)."""
        phase = self._phases.setdefault(self._phase_start(step), _Phase([], deque(maxlen=self.window)))
        # kept per Gaussian ** exponent, so that a mean over steps while the Gaussians grew is not behind
        unit = float(seconds) / (num_gaussians**self.gaussian_exponent if num_gaussians > 0 else 1.0)
        (phase.settling if len(phase.settling) < self.settle else phase.times).append(unit)
        self._last_step = step
        if num_gaussians > 0:
            self._gaussians.append((step, int(num_gaussians)))
            while self._gaussians[0][0] < step - self.growth_window:
                self._gaussians.popleft()

    def _gaussians_at(self, step: float) -> float:
        """Gaussians at ``step``, extrapolated at the recent growth rate until densification stops (1 when no count
        was recorded)."""
        if not self._gaussians:
            return 1.0
        (s0, n0), (s1, n1) = self._gaussians[0], self._gaussians[-1]
        rate = max((n1 - n0) / (s1 - s0), 0.0) if s1 > s0 else 0.0
        return n1 + rate * max(min(step, self.schedule.densify_until) - s1, 0)

    def remaining(self) -> Optional[float]:
        """Seconds for the steps after the last recorded one (None before any step was recorded)."""
        if self._last_step < 0:
            return None
        sched = self.schedule
        phase = self._phases[self._phase_start(self._last_step)]
        times = phase.times or phase.settling
        unit = sum(times) / len(times)
        pixels_now = sched.stage_pixels[sched.stage(self._last_step)]
        first = self._last_step + 1
        # chunks of constant pixels; while the Gaussians grow, 8 chunks so that their growth is followed
        cuts = {first, sched.max_steps, *(b for b in sched.phase_bounds if b > first)}
        grow_end = min(sched.densify_until, sched.max_steps)
        if grow_end > first:
            cuts.update(first + (grow_end - first) * i // 8 for i in range(1, 8))
        edges = sorted(cuts)
        total = 0.0
        for a, b in zip(edges[:-1], edges[1:]):
            factor = (sched.stage_pixels[sched.stage(a)] / pixels_now) ** self.pixel_exponent
            factor *= self._gaussians_at((a + b - 1) / 2.0) ** self.gaussian_exponent
            total += (b - a) * unit * factor
        return total


def step_schedule_of(model, image_sizes: Sequence[Tuple[int, int]], max_steps: int) -> StepSchedule:
    """The :class:`StepSchedule` of a gsmsdr (or splatfacto) model: its resolution schedule (``num_downscales``
    stages of ``resolution_schedule`` steps, each at twice the previous one's resolution), densification until
    ``stop_split_at``, and, with a degradation model, the steps the blur field and the thin lens start.
    ``image_sizes``: (width, height) of each training image at full resolution."""
    if not image_sizes:
        raise ValueError("image_sizes is empty: no training images")
    config = model.config
    mean_pixels = sum(w * h for w, h in image_sizes) / len(image_sizes)
    downscales = max(int(config.num_downscales), 0)
    every = max(int(config.resolution_schedule), 1)
    starts = [i * every for i in range(downscales + 1) if i == 0 or i * every < max_steps]
    pixels = [mean_pixels / 4 ** (downscales - i) for i in range(len(starts))]
    phases = []
    degradation = getattr(model, "degradation", None)
    if degradation is not None:
        phases = [int(degradation.config.warmup), int(degradation.lens_start)]
    return StepSchedule(max_steps, tuple(starts), tuple(pixels), int(config.stop_split_at), tuple(phases))

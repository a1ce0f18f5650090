"""Non-finite losses and Gaussian parameters, found without a host-device synchronisation per training step.

:class:`NonFiniteRecorder` keeps, on the parameters' device, the first step whose loss terms or Gaussian parameters
were not finite, with those terms and which parameters were bad. Recording issues a fixed handful of device
operations and reads nothing back; :meth:`NonFiniteRecorder.read` and :meth:`NonFiniteRecorder.raise_if_seen` read
the record (one synchronisation), so the model decides how often to pay for it
(``GSMSDRModelConfig.finite_check_every``). Training stops with :class:`NonFiniteLossError`.
"""

from __future__ import annotations

from typing import Dict, List, Mapping, NamedTuple, Optional, Tuple

import torch
from torch import Tensor

__all__ = ["NonFiniteLossError", "NonFiniteRecord", "NonFiniteRecorder", "FiniteCheckMixin"]


class NonFiniteLossError(FloatingPointError):
    """A training loss became NaN or infinite."""


class NonFiniteRecord(NamedTuple):
    """The first step with a non-finite loss term or Gaussian parameter."""

    step: int
    """Training step it happened at."""
    terms: Dict[str, float]
    """Every loss term of that step (the sum of its elements)."""
    bad_params: List[str]
    """Names of the Gaussian parameters holding a NaN or infinity at that step (empty: the loss alone)."""


class NonFiniteRecorder:
    """Device-side record of the first step whose loss terms or parameters were not finite.

    The record is kept per layout of the step's names (loss terms come and go, e.g. the blur mask regulariser only
    on steps where the blur field ran), each with the step it was written at; the first bad step is kept across
    layouts.
    """

    def __init__(self) -> None:
        self._first_step: Optional[Tensor] = None  # [] int64, -1 until a step is bad
        # (loss names, parameter names) -> ([] int64 step recorded, -1: none; [T + P] terms then 1/0 finite flags)
        self._records: Dict[Tuple[Tuple[str, ...], Tuple[str, ...]], Tuple[Tensor, Tensor]] = {}

    def observe(self, step: int, losses: Mapping[str, Tensor], params: Mapping[str, Tensor]) -> None:
        """Check the loss terms and parameters of training step ``step`` on their device; nothing is read back."""
        device = next(iter(params.values())).device
        terms = torch.stack([torch.as_tensor(v, device=device).detach().float().sum() for v in losses.values()])
        params_ok = torch.stack([torch.isfinite(p.detach()).all() for p in params.values()])
        bad = torch.logical_not(torch.isfinite(terms).all() & params_ok.all())
        if self._first_step is None:
            self._first_step = torch.full((), -1, dtype=torch.long, device=device)
        first = bad & (self._first_step < 0)
        self._first_step = torch.where(first, step, self._first_step)
        key = (tuple(losses), tuple(params))
        status = torch.cat([terms, params_ok.to(terms.dtype)])
        recorded_step, recorded = self._records.get(key) or (torch.full_like(self._first_step, -1), status)
        self._records[key] = (torch.where(first, step, recorded_step), torch.where(first, status, recorded))

    def read(self) -> Optional[NonFiniteRecord]:
        """The first bad step seen so far, or None (reads the device: one synchronisation)."""
        if self._first_step is None:
            return None
        step = int(self._first_step)
        if step < 0:
            return None
        for (loss_names, param_names), (recorded_step, status) in self._records.items():
            if int(recorded_step) == step:
                values = status.tolist()
                terms = dict(zip(loss_names, values[: len(loss_names)]))
                bad = [name for name, ok in zip(param_names, values[len(loss_names) :]) if not ok]
                return NonFiniteRecord(step, terms, bad)
        raise AssertionError(f"no record of the non-finite step {step}")  # every first step writes one

    def raise_if_seen(self, step: int, check_every: int, num_gaussians: int) -> None:
        """Raise :class:`NonFiniteLossError` naming the first bad step, its loss terms and its non-finite parameters,
        if there was one (reads the device). ``step``: the current step; ``check_every``: how often this is called
        (named in the message when the bad step is an earlier one); ``num_gaussians``: for the message."""
        record = self.read()
        if record is None:
            return
        terms = ", ".join(f"{name}={value:.4g}" for name, value in record.terms.items())
        late = "" if record.step == step else f", found at step {step} (finite_check_every={check_every})"
        raise NonFiniteLossError(
            f"gsmsdr: non-finite training loss or parameters at step {record.step} ({terms}){late}; non-finite "
            f"Gaussian parameters: {', '.join(record.bad_params) or 'none'}; {num_gaussians} Gaussians. Lower the "
            "learning rates in --optimizers, check the input images and poses, or resume from an earlier checkpoint."
        )


class FiniteCheckMixin:
    """The non-finite check of a splatfacto-style model: it needs ``config.finite_check_every``, ``gauss_params``,
    ``step``, ``num_points`` and a :class:`NonFiniteRecorder` in ``_nonfinite``."""

    def _check_finite(self, loss_dict: Dict[str, Tensor]) -> None:
        """Raise :class:`NonFiniteLossError` if a loss term or a Gaussian parameter has been NaN or infinite.

        Parameters are checked too: a NaN position, scale or rotation only culls its Gaussian, so the loss would
        stay finite while the scene silently decays. Checked on the device every step, read (a sync) on multiples
        of ``finite_check_every``; the error names the first bad step, its loss terms and its bad parameters.
        """
        every = self.finite_check_interval
        if every > 0:
            self._nonfinite.observe(self.step, loss_dict, self.gauss_params)
            if self.step % every == 0:
                self._nonfinite.raise_if_seen(self.step, every, self.num_points)

    @property
    def finite_check_interval(self) -> int:
        """``finite_check_every`` resolved for the parameters' device (see the config)."""
        every = self.config.finite_check_every
        if every is None:
            return 1 if self.gauss_params["means"].device.type == "cpu" else 10
        return int(every)

    def raise_if_nonfinite(self) -> None:
        """Raise NonFiniteLossError if any step since the last read was not finite (one device read); the trainer
        calls it before writing a checkpoint, so no checkpoint holds a NaN the deferred check has not reported."""
        every = self.finite_check_interval
        if every > 0:
            self._nonfinite.raise_if_seen(self.step, every, self.num_points)

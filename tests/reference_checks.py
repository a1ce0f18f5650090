"""Comparison of an operator with its reference implementation in float64: values and first-order gradients."""

from __future__ import annotations

from typing import Sequence

import torch


def assert_matches_reference(
    out: torch.Tensor, ref: torch.Tensor, inputs: Sequence[torch.Tensor], generator: torch.Generator
) -> None:
    """``out`` equals ``ref`` to 1e-12 and their gradients with respect to ``inputs``, for one random output
    gradient drawn from ``generator``, agree to 1e-11 (float64 rounding of different summation orders)."""
    torch.testing.assert_close(out, ref, rtol=1e-12, atol=1e-12)
    grad_out = torch.rand(out.shape, dtype=out.dtype, generator=generator)
    got = torch.autograd.grad(out, tuple(inputs), grad_out)
    want = torch.autograd.grad(ref, tuple(inputs), grad_out)
    for g, w in zip(got, want):
        torch.testing.assert_close(g, w, rtol=1e-11, atol=1e-11)

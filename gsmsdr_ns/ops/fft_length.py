"""FFT lengths that are fast to transform: :func:`fast_fft_length`."""

from __future__ import annotations

__all__ = ["fast_fft_length"]


def fast_fft_length(n: int) -> int:
    """The smallest length >= n whose only prime factors are 2, 3 and 5 (an FFT of a length with a large prime
    factor, e.g. 263, runs many times slower)."""
    best = 1
    while best < n:
        best *= 2
    power5 = 1
    while power5 < 2 * n:
        power35 = power5
        while power35 < 2 * n:
            length = power35
            while length < n:
                length *= 2
            best = min(best, length)
            power35 *= 3
        power5 *= 5
    return best

"""Error and warning types for input data (shared by the core readers and the nerfstudio dataparsers)."""

from __future__ import annotations


class GSMSDRDataError(ValueError):
    """Input data that gsmsdr cannot train on; the message names the file or value and how to fix it."""


class GSMSDRDataWarning(UserWarning):
    """Input data that is usable, but only after a guess (a default hold, unknown degradations, ...)."""

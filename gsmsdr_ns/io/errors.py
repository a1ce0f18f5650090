"""The input-error and input-warning types shared by every reader (core tools and nerfstudio dataparsers)."""

from __future__ import annotations


class InputError(ValueError):
    """Input that gsmsdr cannot use; the message names the file or value and says how to fix it."""


class InputWarning(UserWarning):
    """Input that is usable, but only after a guess (a default hold, unknown degradations, ...)."""


class DiskFullError(OSError):
    """No space left for an output; the message names the file and says how to free space or write elsewhere."""

"""The degradation vocabulary: the effect names records, the simulator and the estimate use, and the per-image
degradation modes a model can be told. Everyone imports them from here."""

from __future__ import annotations

from typing import Literal, get_args

__all__ = ["KNOWN_EFFECTS", "BLUR_EFFECTS", "SHARP_ALIASES", "DegradationMode", "DEGRADATION_MODES"]

KNOWN_EFFECTS = ("motion", "defocus", "mixres", "noise")
"""Effect names, in the order a camera applies them (optics and camera motion, then the sensor)."""
BLUR_EFFECTS = ("motion", "defocus", "mixres")
"""Effects that take detail away (the simulator's ``assignment="one_per_image"`` deals them out; noise applies to
every image)."""
SHARP_ALIASES = ("sharp", "none")
"""Names meaning "no degradation"."""
DegradationMode = Literal["auto", "motion", "defocus", "mixres", "sharp"]
"""What degraded the training images, as a model is told: auto (per image, from the records) or one effect for all."""
DEGRADATION_MODES = get_args(DegradationMode)

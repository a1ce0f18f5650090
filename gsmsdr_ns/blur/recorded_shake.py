"""Camera-shake paths from a generated scene's records: the true path of a ``motion`` record in the conventions the
shake model reads, and a :class:`~gsmsdr_ns.blur.shake.CameraShake` set to them and held fixed
(``DegradationConfig.shake_paths`` "records", a diagnostic of what learning the paths costs)."""

from __future__ import annotations

from typing import Any, Mapping, Optional, Sequence, Tuple

import torch
from torch import Tensor

from gsmsdr_ns.blur.profile import DegradationProfile
from gsmsdr_ns.blur.shake import CameraShake

__all__ = ["recorded_path", "set_recorded_paths"]


def recorded_path(record: Mapping[str, Any], pose_scale: float = 1.0) -> Tuple[Tensor, Tensor, Optional[Tensor]]:
    """The true path of a degradation record's ``motion`` effect (``gsmsdr-synth`` / ``gsmsdr-degrade`` write
    ``times`` in (0, 1), camera-to-reference ``rotvecs`` and, for re-rendered shake, ``translations``) in the
    conventions :func:`shake_sample_grid` reads: the reference camera's rotation at each sample and its translation
    times ``pose_scale`` (the scene's units scaled as the dataparser scaled the poses).

    Returns:
        times [S] in [-1/2, 1/2] (float64), rotvecs [S, 3] (radians), translations [S, 3] or None (float64).
    """
    if "rotvecs" not in record or record.get("pose", "camera_to_reference") != "camera_to_reference":
        raise ValueError("a recorded shake path needs the record's camera-to-reference 'rotvecs'")
    rotvecs = torch.tensor(record["rotvecs"], dtype=torch.float64)
    count = rotvecs.shape[0]
    times = record.get("times")
    tau = torch.tensor(times, dtype=torch.float64) if times is not None else (torch.arange(count) + 0.5) / count
    translations = record.get("translations")
    moved = None if translations is None else torch.tensor(translations, dtype=torch.float64) * float(pose_scale)
    # X_ref = R_c X_t + c_t: the sample's camera reads the reference render turned by R_c^T (rotvec -r), moved by c_t
    return tau - 0.5, -rotvecs, moved


def set_recorded_paths(
    shake: CameraShake,
    profiles: Sequence[DegradationProfile],
    records: Optional[Sequence[Optional[Mapping[str, Any]]]],
    pose_scale: Optional[float],
) -> None:
    """Set every shaken view's path of ``shake`` to the cubic closest to its ``motion`` record's path and stop
    training them. ``profiles`` and ``records`` (None for a view without one) are per training view, in the split's
    order; ``pose_scale`` the dataparser's pose scale (needed to read recorded translations).

    Raises:
        ValueError: a shaken view without a recorded path at an exact mid-exposure pose, or recorded translations
            without a pose scale.
    """
    if records is None or len(records) != len(profiles):
        raise ValueError(
            f"shake_paths 'records' needs one motion record per training view ({len(profiles)}), got "
            f"{'none' if records is None else len(records)}"
        )
    translate = shake.translation_coefficients is not None
    for view, (profile, record) in enumerate(zip(profiles, records)):
        if not profile.motion:
            continue
        if record is None or "rotvecs" not in record or not profile.exact_pose:
            raise ValueError(
                f"shake_paths 'records': training view {view} has no recorded shake path at an exact "
                "mid-exposure pose (only generated and gsmsdr-degrade scenes record one); use shake_paths 'learnt'"
            )
        if translate and record.get("translations") is not None and pose_scale is None:
            raise ValueError(
                "shake_paths 'records': the dataparser gives no pose scale (metadata 'pose_scale') to bring the "
                "recorded translations into the scene's units; use gsmsdr's deblur or scene dataparser"
            )
        times, rotvecs, translations = recorded_path(record, 1.0 if pose_scale is None else pose_scale)
        if translate and translations is None:
            translations = torch.zeros_like(rotvecs)  # a rotation-only record: the camera did not move
        shake.set_path(view, times, rotvecs, translations if translate else None)
    shake.requires_grad_(False)

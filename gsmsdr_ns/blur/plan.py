"""What one training step simulates on top of the sharp render: :class:`DegradationPlan`, made by
:meth:`~gsmsdr_ns.blur.degradation_model.DegradationModel.plan`, and the margin crop it asks for."""

from __future__ import annotations

from typing import NamedTuple, Optional, Tuple

from torch import Tensor

from gsmsdr_ns.blur.hpko import ScaleInfo

__all__ = ["DegradationPlan", "crop_margin"]


class DegradationPlan(NamedTuple):
    """What one training step simulates on top of the sharp render (all empty: a plain splatfacto step)."""

    view_id: Optional[int] = None
    """Index of the training image (``camera.metadata["cam_idx"]``); None for cameras outside the training set."""
    blur_scale: Optional[ScaleInfo] = None
    """HPKO scale the blur field runs at; None: the field is not evaluated."""
    blur_uses_depth: bool = False
    """The blur field reads the rendered depth (the rasterizer must produce it)."""
    resolution_factor: float = 1.0
    """Effective resolution-loss factor at the current render downscale; > 1: the resolution model runs."""
    thin_lens: bool = False
    """The image may be defocused: the blur field's thin lens blurs the render first (needs depth)."""
    render_downscale: int = 1
    """The render's downscale factor (the thin lens's aperture is in full-resolution pixels)."""
    blur_field: bool = True
    """The field's kernels run (after the lens, if any); False: a defocused image is modelled by the thin lens
    alone."""
    shake: bool = False
    """The render is first blurred along the view's learnt camera rotation path (the image may be shaken)."""
    shake_depth: bool = False
    """The shake path moves the camera too: its warp reads the render's depth."""
    margin: int = 0
    """Pixels the render reaches beyond each border of the image (:meth:`DegradationModel.forward` blurs the
    enlarged render, then crops them)."""
    deconvolved_loss: bool = False
    """The image's mean kernel is taken for the deconvolved loss (its weight > 0, and the field runs or the thin lens
    does with ``deconvolved_loss_on_lens``)."""
    kernel_centre_loss: bool = False
    """The field's kernel centres are taken for their regulariser (its weight > 0, the field runs, and the image's
    pose was estimated from the photo)."""
    has_model: bool = False
    """The training image has a degradation model (its profile is not sharp), whether or not it runs at this step."""
    fallback: bool = False
    """The image trains as a plain step (its model does not yet explain the photo better than the sharp render):
    the degradation models run on the detached render and learn alone (:meth:`DegradationModel.with_fallback`)."""

    @property
    def needs_depth(self) -> bool:
        return self.blur_scale is not None and (
            (self.blur_uses_depth and self.blur_field) or self.thin_lens or self.shake_depth
        )

    @property
    def is_plain(self) -> bool:
        """Nothing to simulate: outputs["rgb"] is the sharp render."""
        return self.blur_scale is None and self.resolution_factor <= 1.0


def crop_margin(x: Tensor, margin: int, dims: Tuple[int, int] = (-2, -1)) -> Tensor:
    """``x`` without ``margin`` entries at both ends of the two image dimensions ``dims`` (rows, columns)."""
    if margin <= 0:
        return x
    x = x.narrow(dims[0], margin, x.shape[dims[0]] - 2 * margin)
    return x.narrow(dims[1], margin, x.shape[dims[1]] - 2 * margin)

"""MAAN: the Multi-scale Adaptive Attention Network of GS-MSDR (paper section 3.2), as small ``nn.Module`` s.

Data flow (shapes for a batch of B views at the current render resolution H x W)::

    rgb [B,3,H,W] (+ normalised depth [B,1,H,W])                      inputs detached, as in BAGS
      -> RGBDFeatures: SFE 3x3 conv -> FAN (GAKA -> SAFM) -> FAN       [B, n, H, W]          f_RGB-D
    ContextualFeatures (MCF) = view embedding l(i) ++ positional p(x) ++ f_RGB-D
                                                                       [B, d_view + d_pos + n, H, W]
      -> MCA: spatial-context weights * fuse(4 dilated 3x3 branches) + residual     same shape

Every module here works on [B, C, H, W] feature maps; all convolutions pad so that H x W is preserved.
``BAGSFeatures`` is the plain CNN of BAGS, used instead of the FANs for the "MSD-only" ablation (Table 7).
"""

from __future__ import annotations

import math
from typing import List, Optional, Sequence, Union

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from gsmsdr_ns.ops.depthwise_conv import depthwise_conv2d

__all__ = [
    "ChannelLayerNorm",
    "DepthwiseConv2d",
    "LKA",
    "DWSeparableConv",
    "GAKA",
    "SAFM",
    "FAN",
    "RGBDFeatures",
    "BAGSFeatures",
    "MCA",
    "ContextualFeatures",
    "positional_encoding_2d",
    "normalize_depth",
    "check_bchw",
    "check_view_ids",
    "host_checked_view_ids",
]


def check_bchw(x: Tensor, name: str, channels: Optional[int] = None) -> None:
    """Raise a ValueError naming ``name`` unless x is [B, C, H, W] (with ``channels`` channels when given)."""
    if x.dim() != 4 or (channels is not None and x.shape[1] != channels):
        want = f"[B, {channels if channels is not None else 'C'}, H, W]"
        raise ValueError(f"{name} must have shape {want}, got {list(x.shape)}")


# ------------------------------------------------------------------------------------------------ pure helpers


def positional_encoding_2d(height: int, width: int, channels: int, device=None, dtype=torch.float32) -> Tensor:
    """2D sinusoidal positional encoding p(x) of the pixel centres.

    Pixel centres are normalised to ``u = (x + 0.5) / W``, ``v = (y + 0.5) / H`` in (0, 1), so the encoding of a
    point of the image does not depend on the resolution it is rendered at (all HPKO scales see the same p(x)).
    With F = channels / 4 frequencies ``2^k * pi`` (k = 0..F-1) the channels are
    ``[sin(2^k pi u), cos(2^k pi u)]_k ++ [sin(2^k pi v), cos(2^k pi v)]_k``.

    Returns:
        [1, channels, height, width]; channels = 0 gives an empty tensor.
    """
    if channels % 4 != 0 or channels < 0:
        raise ValueError(f"positional channels must be a non-negative multiple of 4, got {channels}")
    u = (torch.arange(width, device=device, dtype=dtype) + 0.5) / width  # [W]
    v = (torch.arange(height, device=device, dtype=dtype) + 0.5) / height  # [H]
    freqs = math.pi * 2.0 ** torch.arange(channels // 4, device=device, dtype=dtype)  # [F]
    au = u[None, :] * freqs[:, None]  # [F, W]
    av = v[None, :] * freqs[:, None]  # [F, H]
    pu = torch.stack([au.sin(), au.cos()], dim=1).reshape(-1, 1, width).expand(-1, height, width)  # [2F, H, W]
    pv = torch.stack([av.sin(), av.cos()], dim=1).reshape(-1, height, 1).expand(-1, height, width)  # [2F, H, W]
    return torch.cat([pu, pv], dim=0)[None]


def normalize_depth(depth: Tensor, eps: float = 1e-6) -> Tensor:
    """Per-image min-max normalisation of a depth map to [0, 1] (BAGS); NaN / inf become 0 first.

    Args:
        depth: [B, 1, H, W]
    Returns:
        [B, 1, H, W]; a constant depth map becomes all zeros.
    """
    check_bchw(depth, "depth", 1)
    d = torch.nan_to_num(depth, nan=0.0, posinf=0.0, neginf=0.0)
    lo = d.amin(dim=(1, 2, 3), keepdim=True)
    hi = d.amax(dim=(1, 2, 3), keepdim=True)
    return (d - lo) / (hi - lo + eps)


# ------------------------------------------------------------------------------------------------ building blocks


class ChannelLayerNorm(nn.Module):
    """LayerNorm over the channel dimension of a [B, C, H, W] map (per pixel), with a per-channel affine."""

    def __init__(self, channels: int, eps: float = 1e-6) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.ones(channels))
        self.bias = nn.Parameter(torch.zeros(channels))
        self.eps = eps

    def forward(self, x: Tensor) -> Tensor:  # [B, C, H, W] -> [B, C, H, W]
        # torch's fused layer norm over the last dimension of the channels-last view: one pass forward and backward
        # instead of eight elementwise ones (the values of the mean / variance formulation)
        normed = F.layer_norm(x.permute(0, 2, 3, 1), (x.shape[1],), self.weight, self.bias, self.eps)
        return normed.permute(0, 3, 1, 2).contiguous()


class DepthwiseConv2d(nn.Conv2d):
    """Depthwise ``kernel`` x ``kernel`` conv (one filter per channel, size-preserving padding). [B, C, H, W] ->
    [B, C, H, W], the parameters and values of ``nn.Conv2d(C, C, kernel, groups=C, ...)``.

    Computed by :func:`gsmsdr_ns.ops.depthwise_conv.depthwise_conv2d`: on the CPU a C++ kernel whose backward costs
    about its forward (oneDNN's depthwise backward costs several times its forward on the feature grid's maps),
    elsewhere PyTorch's convolution.
    """

    def __init__(self, channels: int, kernel: int, dilation: int = 1) -> None:
        pad = (kernel // 2) * dilation
        super().__init__(channels, channels, kernel, padding=pad, dilation=dilation, groups=channels)

    def forward(self, x: Tensor) -> Tensor:
        return depthwise_conv2d(x, self.weight, self.bias, self.dilation[0])


class LKA(nn.Module):
    """Large-kernel attention (paper eq. 6): ``x * PW(DWD(DW(x)))``.

    ``DW``: depthwise ``kernel`` x ``kernel`` conv; ``DWD``: depthwise ``dilated_kernel`` conv with ``dilation``;
    ``PW``: pointwise 1x1 conv. LKA3 = (3, 5, dil 2): receptive field 11; LKA5 = (5, 7, dil 3): 23 (as in VAN/MAN).
    [B, C, H, W] -> [B, C, H, W].
    """

    def __init__(self, channels: int, kernel: int, dilated_kernel: int, dilation: int) -> None:
        super().__init__()
        self.dw = DepthwiseConv2d(channels, kernel)
        self.dwd = DepthwiseConv2d(channels, dilated_kernel, dilation)
        self.pw = nn.Conv2d(channels, channels, 1)

    def forward(self, x: Tensor) -> Tensor:
        return x * self.pw(self.dwd(self.dw(x)))

    @classmethod
    def lka3(cls, channels: int) -> "LKA":
        return cls(channels, 3, 5, 2)

    @classmethod
    def lka5(cls, channels: int) -> "LKA":
        return cls(channels, 5, 7, 3)


class DWSeparableConv(nn.Module):
    """Depthwise-separable conv: depthwise k x k then pointwise 1x1. [B, C, H, W] -> [B, C_out, H, W]."""

    def __init__(self, channels: int, kernel: int, out_channels: Optional[int] = None) -> None:
        super().__init__()
        self.dw = DepthwiseConv2d(channels, kernel)
        self.pw = nn.Conv2d(channels, out_channels or channels, 1)

    def forward(self, x: Tensor) -> Tensor:
        return self.pw(self.dw(x))


class GAKA(nn.Module):
    """Global-Aware Kernel Attention. [B, n, H, W] -> [B, n, H, W].

    ``LN -> 1x1 (n -> 2n) -> split`` into an attention half ``a`` and a transform half ``t`` (n channels each).
    Both halves are split again into two channel groups of sizes ``n1 = n // 2``, ``n2 = n - n1``:

    * attention branch: LKA3 on the first group, LKA5 on the second (the two decompositions alternate over the
      channel groups, as MAN's multi-scale LKA does);
    * transform branch: X3 / X5 = 3x3 / 5x5 depthwise-separable convs on the groups of ``t``, recalibrated by
      elementwise multiplication with the matching LKA attention map.

    The recalibrated groups are concatenated, fused by a 1x1 conv, passed through ReLU and added back with a
    learnable per-channel scale: ``out = x + scale * ReLU(1x1([X3(t1) * LKA3(a1), X5(t2) * LKA5(a2)]))``.
    """

    def __init__(self, n: int, scale_init: float = 0.1) -> None:
        super().__init__()
        if n < 2:
            raise ValueError(f"GAKA needs at least 2 channels, got {n}")
        self.n1, self.n2 = n // 2, n - n // 2
        self.norm = ChannelLayerNorm(n)
        self.expand = nn.Conv2d(n, 2 * n, 1)
        self.lka3, self.lka5 = LKA.lka3(self.n1), LKA.lka5(self.n2)
        self.x3, self.x5 = DWSeparableConv(self.n1, 3), DWSeparableConv(self.n2, 5)
        self.fuse = nn.Conv2d(n, n, 1)
        self.scale = nn.Parameter(torch.full((1, n, 1, 1), float(scale_init)))

    def forward(self, x: Tensor) -> Tensor:
        a, t = self.expand(self.norm(x)).chunk(2, dim=1)  # [B, n, H, W] each
        a1, a2 = a.split([self.n1, self.n2], dim=1)
        t1, t2 = t.split([self.n1, self.n2], dim=1)
        y = torch.cat([self.x3(t1) * self.lka3(a1), self.x5(t2) * self.lka5(a2)], dim=1)
        return x + self.scale * F.relu(self.fuse(y))


class SAFM(nn.Module):
    """Spatial Adaptive Fusion Module. [B, n, H, W] -> [B, n, H, W].

    ``LN -> 1x1 (n -> 2n) -> split`` into gate ``g`` and feature ``f``; the gate passes a 7x7 depthwise-separable
    conv; ``out = x + scale * ReLU(1x1(f * DWSep7(g)))``. The "dimensionality reduction" of the paper is the
    split of the 2n expansion into two n-channel halves followed by the n -> n 1x1 projection (as in MAN's GSAU).
    """

    def __init__(self, n: int, scale_init: float = 0.1) -> None:
        super().__init__()
        self.norm = ChannelLayerNorm(n)
        self.expand = nn.Conv2d(n, 2 * n, 1)
        self.gate = DWSeparableConv(n, 7)
        self.reduce = nn.Conv2d(n, n, 1)
        self.scale = nn.Parameter(torch.full((1, n, 1, 1), float(scale_init)))

    def forward(self, x: Tensor) -> Tensor:
        g, f = self.expand(self.norm(x)).chunk(2, dim=1)
        return x + self.scale * F.relu(self.reduce(f * self.gate(g)))


class FAN(nn.Module):
    """Feature Attention Network: GAKA then SAFM; either can be ablated (both off: identity). [B,n,H,W] -> same."""

    def __init__(self, n: int, gaka: bool = True, safm: bool = True, scale_init: float = 0.1) -> None:
        super().__init__()
        self.gaka = GAKA(n, scale_init) if gaka else None
        self.safm = SAFM(n, scale_init) if safm else None

    def forward(self, x: Tensor) -> Tensor:
        if self.gaka is not None:
            x = self.gaka(x)
        if self.safm is not None:
            x = self.safm(x)
        return x


class RGBDFeatures(nn.Module):
    """f_RGB-D (paper eq. 7): shallow 3x3 conv (SFE) then ``num_fans`` FANs. [B, in_ch, H, W] -> [B, n, H, W].

    ``in_ch`` is 4 for RGB + normalised depth, 3 when depth is not used.
    """

    def __init__(
        self, in_ch: int, n: int, num_fans: int = 2, gaka: bool = True, safm: bool = True, scale_init: float = 0.1
    ) -> None:
        super().__init__()
        self.in_ch, self.out_ch = in_ch, n
        self.sfe = nn.Conv2d(in_ch, n, 3, padding=1)
        self.fans = nn.Sequential(*[FAN(n, gaka, safm, scale_init) for _ in range(num_fans)])

    def forward(self, x: Tensor) -> Tensor:
        check_bchw(x, "RGB-D input", self.in_ch)
        return self.fans(self.sfe(x))


class _InstanceNorm2d(nn.InstanceNorm2d):
    """``nn.InstanceNorm2d`` that also accepts a single pixel while training.

    PyTorch refuses a 1 x 1 map in training mode; its instance statistics are the pixel itself, so the normalised
    output is exactly 0 (what the formula gives, with a zero gradient). Same parameters and buffers (none by
    default) as the parent, so checkpoints are unchanged.
    """

    def forward(self, x: Tensor) -> Tensor:
        if self.training and not self.track_running_stats and x.shape[-2] * x.shape[-1] == 1:
            out = x - x  # (x - mean) / sqrt(var + eps) with mean = x, var = 0
            if self.affine:
                out = out + self.bias[:, None, None]
            return out
        return super().forward(x)


class BAGSFeatures(nn.Module):
    """BAGS' plain CNN: Conv5x5 ReLU IN, Conv5x5 ReLU IN, Conv3x3. [B, in_ch, H, W] -> [B, out_ch, H, W]."""

    def __init__(self, in_ch: int, out_ch: int = 32, width: int = 64) -> None:
        super().__init__()
        self.in_ch, self.out_ch = in_ch, out_ch
        self.net = nn.Sequential(
            nn.Conv2d(in_ch, width, 5, padding=2),
            nn.ReLU(),
            _InstanceNorm2d(width),
            nn.Conv2d(width, width, 5, padding=2),
            nn.ReLU(),
            _InstanceNorm2d(width),
            nn.Conv2d(width, out_ch, 3, padding=1),
        )

    def forward(self, x: Tensor) -> Tensor:
        check_bchw(x, "RGB-D input", self.in_ch)
        return self.net(x)


# ------------------------------------------------------------------------------------------------ MCF and MCA


_HOST_CHECKED_BOUND = "_gsmsdr_view_ids_below"  # attribute of a tensor made by host_checked_view_ids


def host_checked_view_ids(view_ids: Sequence[int], num_views: int, device: torch.device) -> Tensor:
    """[B] int64 tensor of ``view_ids`` on ``device``, checked to lie in [0, num_views) here, on the host.

    :func:`check_view_ids` trusts such a tensor (for any bound >= ``num_views``) instead of reading its values back
    from the device: training steps build their view ids once with this and reuse them, so checking them costs no
    host-device synchronisation. Do not modify the returned tensor in place.
    """
    ids = [int(i) for i in view_ids]
    bad = [i for i in ids if not 0 <= i < num_views]
    if bad:
        raise ValueError(f"view_ids must lie in [0, {num_views}), got {ids}")
    tensor = torch.tensor(ids, dtype=torch.long, device=device)
    setattr(tensor, _HOST_CHECKED_BOUND, int(num_views))
    return tensor


def check_view_ids(view_ids: Tensor, batch: int, num_views: int) -> None:
    """Raise ValueError unless ``view_ids`` is [batch] with every id in [0, num_views).

    The values are read back (a host-device synchronisation on a GPU) unless ``view_ids`` came from
    :func:`host_checked_view_ids` with a bound of at most ``num_views``.
    """
    if view_ids.shape != (batch,):
        raise ValueError(f"view_ids must have shape [{batch}], got {list(view_ids.shape)}")
    checked_below = getattr(view_ids, _HOST_CHECKED_BOUND, None)
    if checked_below is not None and checked_below <= num_views:
        return
    if view_ids.numel() and (int(view_ids.min()) < 0 or int(view_ids.max()) >= num_views):
        raise ValueError(f"view_ids must lie in [0, {num_views}), got {view_ids.tolist()}")


class ContextualFeatures(nn.Module):
    """Multi-modal Contextual Features (paper eq. 8): ``l(i) ++ p(x) ++ f_RGB-D(x, i)``.

    Args:
        num_views: number of training views (rows of the view embedding).
        view_dim: d_view, width of the learnable per-view embedding l(i) (0: none).
        pos_channels: channels of the 2D sinusoidal encoding p(x) (multiple of 4; 0: none).
        rgbd: the image feature network (``RGBDFeatures`` or ``BAGSFeatures``); its ``in_ch`` decides whether the
            normalised depth is used (4) or not (3).
        detach_inputs: feed the network detached copies of render and depth (BAGS): the blur field then changes
            the Gaussians only through the kernels it applies, not through its own inputs.

    ``forward(render [B,3,H,W], depth [B,1,H,W] | None, view_ids [B]) -> [B, out_channels, H, W]``.
    """

    def __init__(
        self,
        num_views: int,
        view_dim: int,
        pos_channels: int,
        rgbd: Union[RGBDFeatures, BAGSFeatures],
        detach_inputs: bool = True,
    ) -> None:
        super().__init__()
        if num_views < 1:
            raise ValueError(f"num_views must be >= 1, got {num_views}")
        positional_encoding_2d(1, 1, pos_channels)  # validates pos_channels
        self.num_views, self.view_dim, self.pos_channels = num_views, view_dim, pos_channels
        self.view_embedding = nn.Embedding(num_views, view_dim) if view_dim > 0 else None
        self.rgbd = rgbd
        self.detach_inputs = detach_inputs
        self.uses_depth = rgbd.in_ch == 4
        self.out_channels = view_dim + pos_channels + rgbd.out_ch

    def forward(self, render: Tensor, depth: Optional[Tensor], view_ids: Tensor) -> Tensor:
        check_bchw(render, "render", 3)
        B, _, H, W = render.shape
        check_view_ids(view_ids, B, self.num_views)
        x = render.detach() if self.detach_inputs else render
        if self.uses_depth:
            if depth is None:
                raise ValueError("this blur field uses depth (rgbd on): pass depth [B, 1, H, W]")
            check_bchw(depth, "depth", 1)
            if depth.shape[-2:] != render.shape[-2:] or depth.shape[0] != B:
                raise ValueError(f"depth {list(depth.shape)} does not match render {list(render.shape)}")
            d = depth.detach() if self.detach_inputs else depth
            x = torch.cat([x, normalize_depth(d).to(x.dtype)], dim=1)
        parts: List[Tensor] = []
        if self.view_embedding is not None:
            parts.append(self.view_embedding(view_ids.long())[:, :, None, None].expand(-1, -1, H, W))
        if self.pos_channels:
            pe = positional_encoding_2d(H, W, self.pos_channels, render.device, render.dtype)
            parts.append(pe.expand(B, -1, -1, -1))
        parts.append(self.rgbd(x))
        return torch.cat(parts, dim=1)


class MCA(nn.Module):
    """Multi-modal Context Adapter. [B, C, H, W] -> [B, C, H, W].

    * adaptive spatial context pooling: ``AdaptiveAvgPool(P x P) -> 1x1 (C -> C/r) -> LN -> ReLU -> 1x1 (-> C)
      -> sigmoid``, bilinearly upsampled to H x W: region-specific weights w in (0, 1);
    * multi-scale branches (paper eqs. 9-10): the channels are split into 4 groups X_i and
      ``B_i = ReLU(LN(Conv3x3_{dilation=i}(X_i)))``, i = 1..4;
    * ``F_fused = w * 1x1(B_1 ++ .. ++ B_4)`` and ``F_MCA = F_fused + X`` (residual).
    """

    def __init__(self, channels: int, pool_size: int = 8, reduction: int = 4) -> None:
        super().__init__()
        if channels < 4:
            raise ValueError(f"MCA needs at least 4 channels, got {channels}")
        self.pool_size = pool_size
        hidden = max(channels // reduction, 4)
        self.context = nn.Sequential(
            nn.AdaptiveAvgPool2d(pool_size),
            nn.Conv2d(channels, hidden, 1),
            ChannelLayerNorm(hidden),
            nn.ReLU(),
            nn.Conv2d(hidden, channels, 1),
            nn.Sigmoid(),
        )
        self.groups = [channels // 4 + (1 if i < channels % 4 else 0) for i in range(4)]
        self.branches = nn.ModuleList(
            nn.Sequential(nn.Conv2d(c, c, 3, padding=d, dilation=d), ChannelLayerNorm(c), nn.ReLU())
            for d, c in zip(range(1, 5), self.groups)
        )
        self.fuse = nn.Conv2d(channels, channels, 1)

    def forward(self, x: Tensor) -> Tensor:
        H, W = x.shape[-2:]
        w = F.interpolate(self.context(x), size=(H, W), mode="bilinear", align_corners=False)
        b = torch.cat([branch(xi) for branch, xi in zip(self.branches, x.split(self.groups, dim=1))], dim=1)
        return w * self.fuse(b) + x

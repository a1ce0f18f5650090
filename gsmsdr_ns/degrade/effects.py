"""One view's degradation: draw the effect parameters from per-view random streams, apply the kernels, and
return the exact parameters for degradation.json.

Images here are float32 tensors [1, 3, H, W]; motion and defocus work in linear light when asked (the caller
converts), mixres and noise on the stored values.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from functools import lru_cache

import numpy as np
import torch
from kornia.color import rgb_to_linear_rgb
from torch import Tensor

from ..data.mixres import mixres_factors
from ..ops.mixres import apply_mixres
from ..synth.config import SynthSceneConfig
from ..synth.raycast import render_view
from ..synth.scene import Scene, build_scene
from .config import DefocusConfig, MixresConfig, MotionConfig, NoiseConfig
from .kernels import (
    add_noise,
    apply_defocus,
    convolve_psf,
    defocus_radius,
    disk_blur,
    homography_blur,
    motion_kernel_from_trajectory,
    path_extent,
    plane_homography,
    radius_levels,
    rotational_shake_blur,
)
from .trajectory import border_reach_px, calibrated_shake, pixel_paths, probe_points, sample_times, smooth_path

STREAMS = {"motion": 1, "defocus": 2, "mixres": 3, "noise": 4, "assignment": 5}
"""Random stream ids: view i's effect e draws from default_rng([seed, STREAMS[e], i])."""

# R2 low-discrepancy sequence: sub-pixel offsets of successive re-rendered sub-frames (temporal anti-aliasing).
_R2 = (0.7548776662466927, 0.5698402909980532)


def view_rng(seed: int, effect: str, index: int) -> np.random.Generator:
    """Independent random stream per (seed, effect, view): adding an effect leaves the others' draws unchanged."""
    return np.random.default_rng([seed, STREAMS[effect], index])


@dataclass
class ViewContext:
    """What the effects know about the view being degraded."""

    K: np.ndarray  # [3, 3]
    width: int
    height: int
    c2w: np.ndarray  # [4, 4] OpenCV camera-to-world (reference = mid-exposure pose)
    depth: np.ndarray | None  # [H, W] z-depth of the sharp view, if known
    synth_config: SynthSceneConfig | None  # procedural scene to re-render, if any
    px_scale: float  # multiplies pixel-valued parameters (width / px_reference_width)
    linear_light: bool = True  # images handed to the blur effects are linear light (re-renders get decoded too)


def _r(x: float, digits: int = 8) -> float:
    return float(round(float(x), digits))


def _num_samples(extent_px: float, cfg: MotionConfig) -> int:
    return int(np.clip(math.ceil(extent_px / cfg.sample_spacing_px) + 1, 2, cfg.max_samples))


@lru_cache(maxsize=2)
def _scene(config_json: str) -> Scene:
    return build_scene(SynthSceneConfig(**json.loads(config_json)))


def scene_for(cfg: SynthSceneConfig) -> Scene:
    """Build (once per process) the procedural scene of a generator config."""
    return _scene(json.dumps(asdict(cfg), sort_keys=True))


def motion_effect(image: Tensor, ctx: ViewContext, cfg: MotionConfig, rng: np.random.Generator) -> tuple[Tensor, dict]:
    """Camera shake. image [1, 3, H, W] (ignored by the trajectory model, which re-renders) -> (image, record)."""
    model = cfg.model
    if model == "auto":
        model = "trajectory" if ctx.synth_config is not None else "rotational_shake"
    if model == "trajectory" and ctx.synth_config is None:
        raise ValueError("motion model 'trajectory' re-renders the view and needs a generated scene (scene.json)")
    target = float(rng.uniform(cfg.min_blur_px, cfg.max_blur_px)) * ctx.px_scale
    T = _num_samples(target, cfg)
    if model == "kernel":
        path = smooth_path(rng, sample_times(T), 2, cfg.curvature)
        ext = float(path_extent(torch.as_tensor(path)[:, None]).max())
        path = path * (target / ext if ext > 0 else 0.0)
        kernel = motion_kernel_from_trajectory(path)
        out = convolve_psf(image, kernel.to(image.dtype))
        rec = {"model": "kernel", "blur_px": _r(target), "samples": T, "kernel_size": int(kernel.shape[-1]),
               "border_reach_px": float(kernel.shape[-1] // 2),
               "trajectory_px": np.round(path, 6).tolist()}  # fmt: skip
        return out, rec
    if model == "rotational_shake":
        traj, ext = calibrated_shake(
            rng, ctx.K, ctx.width, ctx.height, target, T, cfg.curvature, cfg.roll_fraction, 0.0, None
        )
        R, _ = traj.reference_to_camera()
        out = rotational_shake_blur(image, ctx.K, R)
        reach = border_reach_px(ctx.K, traj, ctx.width, ctx.height)
        rec = {"model": "rotational_shake", "blur_px": _r(target), "max_displacement_px": _r(ext, 4), "samples": T,
               "border_reach_px": _r(reach, 4), "reference": "mid_exposure", "pose": "camera_to_reference",
               **traj.to_json()}  # fmt: skip
        rec.pop("translations")
        return out, rec
    return _trajectory_motion(ctx, cfg, rng, target, T, image.dtype)


def _trajectory_motion(
    ctx: ViewContext, cfg: MotionConfig, rng: np.random.Generator, target: float, T: int, dtype: torch.dtype
) -> tuple[Tensor, dict]:
    """Re-render sub-frames along a 6-DoF shake and average them (in linear light if ctx.linear_light).

    n_kf sub-frames are rendered (one per keyframe_spacing_px of blur); every exposure sample in a sub-frame's
    time interval is that sub-frame warped by the homography of the plane at its median depth, so the average
    has no ghost copies. Sub-frames are rendered with a margin so the warps never sample outside them.
    """
    scene = scene_for(ctx.synth_config)
    depth = ctx.depth
    if depth is None and cfg.translation_fraction > 0:
        _, depth = render_view(scene, ctx.c2w, ctx.K, ctx.width, ctx.height, 1)
        depth = depth.astype(np.float64)
    supersample = cfg.render_supersample or ctx.synth_config.supersample
    n_kf = int(np.clip(math.ceil(target / cfg.keyframe_spacing_px), 1, T))
    per = math.ceil(T / n_kf)
    T = n_kf * per
    traj, ext = calibrated_shake(
        rng, ctx.K, ctx.width, ctx.height, target, T, cfg.curvature, cfg.roll_fraction, cfg.translation_fraction, depth
    )
    Rc = traj.rotations()  # camera-to-reference
    tc = torch.as_tensor(traj.translations, dtype=torch.float64)
    uv = probe_points(ctx.width, ctx.height)
    inv_d = np.zeros(len(uv)) if depth is None else 1.0 / depth[
        np.clip(uv[:, 1].astype(int), 0, ctx.height - 1), np.clip(uv[:, 0].astype(int), 0, ctx.width - 1)]  # fmt: skip
    paths = pixel_paths(ctx.K, traj, uv, inv_d)  # [T, N, 2]
    out = torch.zeros(1, 3, ctx.height, ctx.width, dtype=dtype)
    for k in range(n_kf):
        j0, jk = k * per, k * per + per // 2
        lo, hi = j0, j0 + per
        margin = int(math.ceil(float((paths[lo:hi] - paths[jk]).norm(dim=-1).max()))) + 2
        jx, jy = ((0.5 + k * _R2[0]) % 1.0) - 0.5, ((0.5 + k * _R2[1]) % 1.0) - 0.5
        K_big = ctx.K.copy()
        K_big[0, 2] += margin + jx
        K_big[1, 2] += margin + jy
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = Rc[jk].numpy(), tc[jk].numpy()
        rgb, sub_depth = render_view(
            scene, ctx.c2w @ pose, K_big, ctx.width + 2 * margin, ctx.height + 2 * margin, supersample
        )
        finite = np.isfinite(sub_depth)
        plane = float(np.median(sub_depth[finite])) if finite.any() else 1.0
        # keyframe camera -> sample camera j: X_j = Rc_j^T (Rc_k X_k + tc_k - tc_j)
        Rj_t = Rc[lo:hi].transpose(-1, -2)
        R = Rj_t @ Rc[jk]
        t = (Rj_t @ (tc[jk] - tc[lo:hi])[..., None])[..., 0]
        H = plane_homography(K_big, ctx.K, R, t, plane)
        sub = torch.from_numpy(rgb).permute(2, 0, 1)[None].to(dtype)
        sub = rgb_to_linear_rgb(sub) if ctx.linear_light else sub
        out += homography_blur(sub, H, dsize=(ctx.height, ctx.width), padding_mode="border")
    out = out / n_kf
    rec = {"model": "trajectory", "blur_px": _r(target), "max_displacement_px": _r(ext, 4), "samples": T,
           "keyframes": n_kf, "render_supersample": supersample, "reference": "mid_exposure",
           "pose": "camera_to_reference", **traj.to_json()}  # fmt: skip
    return out, rec


def defocus_effect(
    image: Tensor, ctx: ViewContext, cfg: DefocusConfig, rng: np.random.Generator
) -> tuple[Tensor, dict]:
    """Thin-lens (depth known) or disk defocus. image [1, 3, H, W] -> (image, record)."""
    model = cfg.model
    if model == "auto":
        model = "thin_lens" if ctx.depth is not None else "disk"
    if model == "thin_lens" and ctx.depth is None:
        raise ValueError("defocus model 'thin_lens' needs a depth map (depth/<stem>.npy)")
    coc = float(rng.uniform(cfg.min_coc_px, cfg.max_coc_px)) * ctx.px_scale
    if model == "disk":
        return disk_blur(image, 0.5 * coc), {"model": "disk", "radius_px": _r(0.5 * coc), "max_coc_px": _r(coc),
                                             "border_reach_px": _r(0.5 * coc)}  # fmt: skip
    q = float(rng.uniform(cfg.focus_quantile_min, cfg.focus_quantile_max))
    depth = torch.as_tensor(ctx.depth, dtype=torch.float64)
    finite = depth[torch.isfinite(depth)]
    d_f = float(torch.quantile(finite, q)) if finite.numel() else 1.0
    inv = 1.0 / depth
    f_px = float(ctx.K[0, 0])
    spread = float((1.0 / d_f - inv).abs().max())
    aperture = coc / (f_px * spread) if spread > 0 else 0.0
    r = defocus_radius(depth, f_px, aperture, d_f, signed=True)
    out = apply_defocus(image, r[None, None].to(image.dtype), cfg.radius_step_px, cfg.radius_rel_step)
    levels = radius_levels(float(r.abs().max()), cfg.radius_step_px, cfg.radius_rel_step)
    rec = {"model": "thin_lens", "focus_distance": _r(d_f), "focus_quantile": _r(q, 6), "aperture": _r(aperture, 10),
           "max_coc_px": _r(coc), "focal_px": _r(f_px), "radius_step_px": cfg.radius_step_px,
           "radius_levels": len(levels), "border_reach_px": _r(float(r.abs().max()), 4)}  # fmt: skip
    return out, rec


def mixres_effect(image: Tensor, factor: int, cfg: MixresConfig) -> tuple[Tensor, dict]:
    """Downscale by `factor` and upsample back. -> (image, record)."""
    H, W = image.shape[-2:]
    rec = {"factor": int(factor), "size": [max(1, round(W / factor)), max(1, round(H / factor))],
           "downsample": "bilinear_antialias", "upsample": cfg.upsample}  # fmt: skip
    return apply_mixres(image, int(factor), cfg.upsample), rec


def noise_effect(image: Tensor, cfg: NoiseConfig, rng: np.random.Generator) -> tuple[Tensor, dict]:
    """Poisson-Gaussian noise from a per-view torch generator seeded by `rng`. -> (image, record)."""
    seed = int(rng.integers(2**63 - 1))
    gen = torch.Generator().manual_seed(seed)
    rec = {"model": "poisson_gaussian" if cfg.gain > 0 else "gaussian", "sigma": cfg.sigma, "gain": cfg.gain,
           "clipped": True, "seed": seed}  # fmt: skip
    return add_noise(image, cfg.sigma, cfg.gain, gen), rec


def sample_assignment(n: int, seed: int, choices: int) -> np.ndarray:
    """Balanced random assignment of n views to `choices` groups (sizes differ by at most one) -> [n] int."""
    return mixres_factors(n, [seed, STREAMS["assignment"]], tuple(range(choices)))


__all__ = [
    "STREAMS",
    "ViewContext",
    "view_rng",
    "motion_effect",
    "defocus_effect",
    "mixres_effect",
    "noise_effect",
    "sample_assignment",
    "scene_for",
]

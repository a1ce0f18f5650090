"""The bench's one evaluation definition; every bench path (suite runs, their PSNR-vs-time curves, ``run_method``)
uses :func:`evaluate_test_views`.

On the held-out sharp test views (the pipeline's eval split, ``fixed_indices_eval_dataloader``, which is what
ns-eval uses; ground truth from ``images_test/``), each view's sharp render (eval mode: no simulated degradation)
against its sharp ground truth, both composited on the render's background, RGB clamped to [0, 1]:

* PSNR = -10 log10(MSE) over all pixels and channels, in float64;
* SSIM = ``skimage.metrics.structural_similarity(data_range=1.0, channel_axis=2, gaussian_weights=True, sigma=1.5,
  use_sample_covariance=False)``: the SSIM paper's 11x11 Gaussian window (sigma 1.5), K1 0.01, K2 0.03, averaged
  over RGB;
* LPIPS = torchmetrics' ``LearnedPerceptualImagePatchSimilarity(net_type="alex", normalize=True)`` on [0, 1]
  images, only when torchvision's AlexNet weights are already in the torch hub cache (nothing is downloaded),
  else NaN;

each then averaged over the test views. With a :class:`~gsmsdr_ns.plugin.pose_alignment.PoseAlignmentConfig`, each
view is also rendered at its aligned pose (the scene frozen, the test camera's pose optimised on the photometric loss
against its ground truth, :func:`~gsmsdr_ns.plugin.pose_alignment.align_camera`) and the same metrics are reported
with the suffix ``_aligned``, plus ``pose_correction_deg``, the mean rotation of the corrections. (The plugin model's
own eval metrics, used by ns-eval, come from splatfacto's torchmetrics PSNR / SSIM; the bench keeps scikit-image's
SSIM so its tables stay comparable.)
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple


def make_lpips(device) -> Optional[Any]:
    """torchmetrics' LPIPS (AlexNet) when its backbone weights are in the torch hub cache, else None."""
    from gsmsdr_ns.plugin.lpips import lpips_backbone_cache_path

    if not lpips_backbone_cache_path().is_file():
        return None
    from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity

    return LearnedPerceptualImagePatchSimilarity(normalize=True).to(device)


def evaluate_test_views(run, lpips=None, align=None, renders_to: Optional[Path] = None) -> Dict[str, Any]:
    """Mean PSNR / SSIM / LPIPS (see the module docstring) of the test views of ``run`` (an
    :class:`gsmsdr_ns.bench.training.InProcessRun`), ``num_views`` and each view's PSNR (``psnr_views``); with
    ``align`` (a :class:`~gsmsdr_ns.plugin.pose_alignment.PoseAlignmentConfig`) also the metrics at the aligned test
    poses. With ``renders_to``, that folder (replaced as a whole) receives each view's render and ground truth,
    ``<index>_render.png`` and ``<index>_gt.png`` (8 bit, in the eval dataloader's order).

    Renders with the random state restored, in eval mode, then back to train mode: training continues exactly as
    without the evaluation.
    """
    import numpy as np
    import torch

    from gsmsdr_ns.plugin.pose_alignment import aligned_camera, frozen_for_alignment

    pipeline, model = run.pipeline, run.model
    devices = [torch.cuda.current_device()] if torch.cuda.is_available() else []
    given: List[Dict[str, float]] = []
    aligned: List[Dict[str, float]] = []
    corrections: List[float] = []
    images: List[Any] = []
    pipeline.eval()
    try:
        with torch.random.fork_rng(devices=devices):
            for camera, batch in pipeline.datamanager.fixed_indices_eval_dataloader:
                with torch.no_grad():
                    outputs = model.get_outputs_for_camera(camera)
                gt = model.composite_with_background(model.get_gt_img(batch["image"]), outputs["background"])
                gt = gt[..., :3].clamp(0.0, 1.0)
                given.append(_image_metrics(outputs["rgb"], gt, lpips, model.device))
                if renders_to is not None:
                    images.append((_to_uint8(outputs["rgb"]), _to_uint8(gt)))
                if align is None:
                    continue
                camera = camera.to(model.device)
                with frozen_for_alignment(model):
                    moved_camera, correction = aligned_camera(model, camera, gt, align)
                    with torch.no_grad():
                        moved = model.get_outputs_for_camera(moved_camera)
                aligned.append(_image_metrics(moved["rgb"], gt, lpips, model.device))
                corrections.append(correction.rotation_degrees)
    finally:
        pipeline.train()
    if not given:
        raise RuntimeError("the scene has no test views to evaluate")
    names = ("psnr", "ssim", "lpips")
    out = {name: float(np.mean([m[name] for m in given])) for name in names}
    out["num_views"] = len(given)
    out["psnr_views"] = [round(m["psnr"], 4) for m in given]
    if renders_to is not None:
        _write_renders(Path(renders_to), images)
    if align is not None:
        out.update({f"{name}_aligned": float(np.mean([m[name] for m in aligned])) for name in names})
        out["pose_correction_deg"] = float(np.mean(corrections))
    return out


def _to_uint8(image) -> Any:
    """[H, W, >=3] float image in [0, 1] -> [H, W, 3] uint8 numpy array."""
    return (image[..., :3].detach().clamp(0.0, 1.0) * 255.0).round().byte().cpu().numpy()


def _write_renders(folder: Path, images: Sequence[Tuple[Any, Any]]) -> None:
    """``folder`` replaced by one holding ``<index>_render.png`` / ``<index>_gt.png`` per (render, gt) pair."""
    from gsmsdr_ns.io.atomic import atomic_dir
    from gsmsdr_ns.io.images import write_image

    folder.parent.mkdir(parents=True, exist_ok=True)
    with atomic_dir(folder) as tmp:
        for index, (render, gt) in enumerate(images):
            write_image(tmp / f"{index:03d}_render.png", render)
            write_image(tmp / f"{index:03d}_gt.png", gt)


def _image_metrics(rgb, gt, lpips, device) -> Dict[str, float]:
    """PSNR / SSIM / LPIPS (NaN without ``lpips``) of one render against its ground truth, both [H, W, 3]."""
    import torch
    from skimage.metrics import structural_similarity

    pred = rgb[..., :3].detach().clamp(0.0, 1.0)
    mse = torch.mean((pred.double() - gt.double()) ** 2).clamp_min(1e-12)
    g, p = gt.double().cpu().numpy(), pred.double().cpu().numpy()
    ssim = structural_similarity(g, p, data_range=1.0, channel_axis=2, gaussian_weights=True, sigma=1.5,
                                 use_sample_covariance=False)  # fmt: skip
    value = float("nan")
    if lpips is not None:
        to_nchw = lambda x: x.permute(2, 0, 1)[None].float().to(device)  # noqa: E731
        with torch.no_grad():
            value = float(lpips(to_nchw(pred), to_nchw(gt)))
    return {"psnr": float(-10.0 * torch.log10(mse)), "ssim": float(ssim), "lpips": value}


def train_view_psnr(run) -> float:
    """Mean PSNR over the training views of the training-mode ``rgb`` (the simulated degradation when the view has a
    degradation model, else the render) against the degraded training image: how well a method fits what it was
    given. Rendered with gradients enabled (splatfacto's training forward retains the 2D means' gradients) and the
    random state restored, so training could continue unchanged."""
    import numpy as np
    import torch

    model = run.model
    datamanager = run.pipeline.datamanager
    cameras = datamanager.train_dataset.cameras
    values = []
    model.train()
    with torch.random.fork_rng(devices=[]):
        for index, data in enumerate(datamanager.cached_train):
            camera = cameras[index : index + 1].to(model.device)
            camera.metadata = {**(camera.metadata or {}), "cam_idx": index}
            outputs = model(camera)
            rgb = outputs["rgb"].detach()
            gt = model.composite_with_background(model.get_gt_img(data["image"]), outputs["background"])
            mse = torch.mean((rgb - gt[..., :3]) ** 2).clamp_min(1e-10)
            values.append(float(-10.0 * torch.log10(mse)))
            del outputs
    model.info = {}  # drop the graph of the last render
    return float(np.mean(values))


def learnt_shake_paths(run) -> Optional[Dict[str, Any]]:
    """The camera-shake paths a run learnt (None without a shake model), in the conventions of
    :func:`~gsmsdr_ns.blur.shake.shake_sample_grid`: per training view (the split's order) the rotation vectors
    [T, 3] (radians) the render is warped by, parallax offsets included (they read the median depth of the view's
    render, rendered here), and the translations [T, 3] (scene units of the dataparser's scaled poses); with the
    sample ``times`` in [-1/2, 1/2] and the dataparser's ``pose_scale``. What :mod:`tools.shake.path_error` compares
    with the recorded paths."""
    import torch

    from gsmsdr_ns.blur.shake import shake_sample_times

    model = run.model
    shake = model.degradation.camera_shake
    if shake is None:
        return None
    datamanager = run.pipeline.datamanager
    cameras = datamanager.train_dataset.cameras
    metadata = datamanager.train_dataset.metadata or {}
    names = metadata.get("image_names") or [Path(f).name for f in datamanager.train_dataset.image_filenames]
    views: List[Dict[str, Any]] = []
    model.eval()
    with torch.no_grad(), torch.random.fork_rng(devices=[]):
        for index, profile in enumerate(model.degradation.profiles):
            ids = model.degradation.view_ids(index, model.device)
            centred = not profile.exact_pose
            rotvecs, translations = shake.rotvecs(ids, centred), shake.translations(ids, centred)
            median_depth = None
            if shake.parallax and shake.translation_coefficients is not None:
                camera = cameras[index : index + 1].to(model.device)
                depth = model.get_outputs(camera)["depth"][..., 0].clamp_min(1e-3)
                median_depth = float(depth.median())
                rotvecs = shake.warped_rotvecs(ids, centred, translations, depth)
            views.append({"name": names[index], "motion": profile.motion, "centred": centred,
                          "median_depth": median_depth, "rotvecs": rotvecs.cpu().tolist(),
                          "translations": translations.cpu().tolist()})  # fmt: skip
    model.train()
    return {"times": shake_sample_times(shake.num_samples).tolist(), "pose_scale": metadata.get("pose_scale"),
            "views": views}  # fmt: skip


__all__ = ["evaluate_test_views", "learnt_shake_paths", "make_lpips", "train_view_psnr"]

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

each then averaged over the test views. (The plugin model's own eval metrics, used by ns-eval, come from
splatfacto's torchmetrics PSNR / SSIM; the bench keeps scikit-image's SSIM so its tables stay comparable.)
"""

from __future__ import annotations

from typing import Any, Dict, Optional


def make_lpips(device) -> Optional[Any]:
    """torchmetrics' LPIPS (AlexNet) when its backbone weights are in the torch hub cache, else None."""
    from gsmsdr_ns.plugin.lpips import lpips_backbone_cache_path

    if not lpips_backbone_cache_path().is_file():
        return None
    from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity

    return LearnedPerceptualImagePatchSimilarity(normalize=True).to(device)


def evaluate_test_views(run, lpips=None) -> Dict[str, float]:
    """Mean PSNR / SSIM / LPIPS (see the module docstring) of the test views of ``run`` (an
    :class:`gsmsdr_ns.bench.training.InProcessRun`), and ``num_views``.

    Renders without gradients and with the random state restored, in eval mode, then back to train mode: training
    continues exactly as without the evaluation.
    """
    import numpy as np
    import torch
    from skimage.metrics import structural_similarity

    pipeline, model = run.pipeline, run.model
    devices = [torch.cuda.current_device()] if torch.cuda.is_available() else []
    psnrs, ssims, lpipss = [], [], []
    pipeline.eval()
    try:
        with torch.random.fork_rng(devices=devices), torch.no_grad():
            for camera, batch in pipeline.datamanager.fixed_indices_eval_dataloader:
                outputs = model.get_outputs_for_camera(camera)
                gt = model.composite_with_background(model.get_gt_img(batch["image"]), outputs["background"])
                gt = gt[..., :3].clamp(0.0, 1.0)
                pred = outputs["rgb"][..., :3].clamp(0.0, 1.0)
                mse = torch.mean((pred.double() - gt.double()) ** 2).clamp_min(1e-12)
                psnrs.append(float(-10.0 * torch.log10(mse)))
                g, p = gt.double().cpu().numpy(), pred.double().cpu().numpy()
                ssims.append(float(structural_similarity(
                    g, p, data_range=1.0, channel_axis=2, gaussian_weights=True, sigma=1.5,
                    use_sample_covariance=False)))  # fmt: skip
                if lpips is not None:
                    to_nchw = lambda x: x.permute(2, 0, 1)[None].float().to(model.device)  # noqa: E731
                    lpipss.append(float(lpips(to_nchw(pred), to_nchw(gt))))
    finally:
        pipeline.train()
    if not psnrs:
        raise RuntimeError("the scene has no test views to evaluate")
    return {
        "psnr": float(np.mean(psnrs)),
        "ssim": float(np.mean(ssims)),
        "lpips": float(np.mean(lpipss)) if lpipss else float("nan"),
        "num_views": len(psnrs),
    }


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


__all__ = ["evaluate_test_views", "make_lpips", "train_view_psnr"]

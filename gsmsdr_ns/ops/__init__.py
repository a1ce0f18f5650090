"""Differentiable image operators shared by training (``blur/``), simulation (``degrade/``) and estimation: pure
functions on [B, C, H, W] tensors with shapes in their docstrings, each with a PyTorch reference or twin and, on the
CPU, a C++/OpenMP kernel (``csrc/``, built on first use by :mod:`gsmsdr_ns._cpp_ext`).

* :mod:`.pixel_kernels`: per-pixel K x K kernels (``apply_pixel_kernels``), the blur field's kernel application;
* :mod:`.grid_kernels`: kernels predicted on a coarse grid, applied at every pixel without a dense copy;
* :mod:`.depthwise_conv`: the depthwise convolution of the blur field's feature network;
* :mod:`.disk_kernels`: a thin lens's per-pixel disk kernels (reference); :mod:`.disk_defocus`: the same, fused;
* :mod:`.mixres`: the mixed-resolution down-up operator (``apply_mixres``, ``resolution_loss``);
* :mod:`.deconvolved_loss`: the residual weighted by the inverse of an image's mean blur;
* :mod:`.splat`: bilinear splatting of weighted points onto a grid (motion kernels from paths);
* :mod:`.ssim`: splatfacto's training SSIM with its five filtered maps in two grouped convolutions.

Imports only torch, kornia and the standard library (never ``blur``, ``degrade``, ``data`` or nerfstudio).
"""

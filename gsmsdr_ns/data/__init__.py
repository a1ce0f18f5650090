"""What a scene is, without nerfstudio: layouts, scene cameras (COLMAP / LLFF), holdout rules, degradation
metadata, mixres caches. File formats themselves (COLMAP models, images, atomic writes) are read and written by
``gsmsdr_ns.io``.

Everything here works on plain files and numpy / torch arrays, so it can be tested (and used by tools such as
``gsmsdr-degrade``) without importing the nerfstudio trainer. ``gsmsdr_ns.plugin`` turns the results into
nerfstudio ``DataparserOutputs``.

Conventions used throughout:

* image lists are sorted by file name (= capture order in the Deblur-NeRF and Mip-NeRF 360 layouts);
* camera-to-world matrices are 4x4 in OpenCV camera axes (x right, y down, z forward) and in the world frame of
  the file they came from (COLMAP's, for ``sparse/0`` and ``poses_bounds.npy``);
* intrinsics are ``fx, fy, cx, cy`` in pixels for the image size stored next to them (pixel centres at +0.5).
"""

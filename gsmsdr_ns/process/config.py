"""Options of ``gsmsdr-process``: structure-from-motion on a folder of photos with pycolmap."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional

MatchingMode = Literal["auto", "exhaustive", "sequential"]
CameraModel = Literal["SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"]
CameraMode = Literal["auto", "single", "per-folder", "per-image"]
Device = Literal["auto", "cpu", "cuda"]


@dataclass
class ProcessConfig:
    """How photos become a posed, undistorted scene (SIFT -> matching -> incremental mapping -> undistortion)."""

    matching: MatchingMode = "auto"
    """Which image pairs are matched: every pair ("exhaustive"), neighbours in file-name order ("sequential", for
    video frames), or "auto" (exhaustive up to --exhaustive-max-images photos, sequential above)."""
    exhaustive_max_images: int = 100
    """Largest photo count that "auto" matches exhaustively (the pair count grows quadratically)."""
    sequential_overlap: int = 10
    """Sequential matching: each frame is matched with this many following frames."""
    quadratic_overlap: bool = True
    """Sequential matching: also match frames 2^k apart, which closes loops without a vocabulary tree."""
    vocab_tree: Optional[Path] = None
    """Sequential matching: a COLMAP vocabulary-tree file; when given, loop detection by image retrieval is on."""
    max_image_size: int = 1000
    """Longest side (pixels) that SIFT sees; larger photos are downscaled for feature extraction only (the written
    images keep their resolution)."""
    estimate_affine_shape: bool = True
    """Affine-adapted SIFT features (slower, more matches on blurred and oblique views)."""
    domain_size_pooling: bool = False
    """SIFT descriptors pooled over several support sizes (1.2-1.7x the SfM time); on blurred fern photos it moved
    the pose errors either way (docs/results/sfm), so it is off by default."""
    max_num_features: int = 8192
    """Most SIFT features kept per photo."""
    camera_model: CameraModel = "SIMPLE_RADIAL"
    """COLMAP camera model estimated during mapping; the output is always undistorted to PINHOLE."""
    camera_mode: CameraMode = "auto"
    """Which photos share intrinsics: "auto" (one camera per distinct image size, i.e. per device in a mixed
    capture), "single" (all photos, one size), "per-folder" or "per-image"."""
    min_registered_fraction: float = 0.5
    """The run fails when the kept model registers fewer than this fraction of the photos."""
    min_registered: int = 3
    """The run fails when the kept model registers fewer photos than this."""
    hold: Optional[int] = None
    """Write a ``hold=N`` file: every N-th photo in file-name order is held out for evaluation (Deblur-NeRF rule;
    the scene is then read as a Deblur-NeRF scene)."""
    num_downscales: int = 0
    """Also write ``images_2/``, ``images_4/``, ... (this many halvings) for ``--downscale-factor`` training."""
    device: Device = "auto"
    """Where SIFT extraction and matching run ("auto": the GPU when pycolmap was built with CUDA)."""
    num_threads: int = -1
    """CPU threads for pycolmap (-1: all cores)."""
    seed: int = 0
    """Random seed of pycolmap's RANSAC and mapper."""
    verbose: bool = False
    """Show pycolmap's own log lines."""

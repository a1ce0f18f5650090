"""``mixres-data``: the mixed-resolution protocol (GS-MSDR paper, section 4.2) on a COLMAP / Mip-NeRF 360 scene.

Views sorted by file name; every ``eval_interval``-th one (index % 8 == 0) is a test view, read untouched from the
image folder (``images/``, or ``images_N/`` with ``downscale_factor N`` as the "full" resolution). The other
views are split at random (``seed``) into four equal groups, downscaled 4x, 3x, 2x and 1x and upsampled back to
the full size; those images are cached under ``<scene>/.gsmsdr_cache/`` (or ``cache_path``; see
``gsmsdr_ns.data.mixres``) and reused.

``metadata["degradations"]`` holds one record per image of the split (``mixres_factor`` and
``effects["mixres"]["factor"]`` for training views; factor 1 for the test views), ``metadata["mixres_cache"]``
the cache folder.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional, Tuple, Type

from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from nerfstudio.utils.rich_utils import CONSOLE

from gsmsdr_ns.data.degradation import sharp_record
from gsmsdr_ns.data.layout import holdout_split
from gsmsdr_ns.data.mixres import MIXRES_FACTORS, MixresImages, cache_dir_for, group_sizes, mixres_cache
from gsmsdr_ns.io.errors import InputError
from gsmsdr_ns.plugin.scene_parser import (
    SceneSource,
    SortedSceneParser,
    SortedSceneParserConfig,
    find_colmap_model,
    split_indices,
)

COLMAP_CANDIDATES = (Path("sparse/0"), Path("colmap/sparse/0"))


@dataclass
class MixresDataParserConfig(SortedSceneParserConfig):
    """COLMAP scene with training views at mixed resolutions (4x/3x/2x/1x groups), sharp full-resolution tests."""

    _target: Type = field(default_factory=lambda: MixresDataParser)
    colmap_path: Optional[Path] = None
    """COLMAP model directory relative to the data path; None looks for sparse/0, then colmap/sparse/0."""
    eval_interval: int = 8
    """Every eval_interval-th view in file-name order (index % eval_interval == 0) is a test view."""
    seed: int = 0
    """Seed of the random assignment of training views to the resolution groups (and of the cache's name)."""
    factors: Tuple[int, ...] = MIXRES_FACTORS
    """Downscale factor of each group; the training views are split into len(factors) equal groups."""
    cache_path: Optional[Path] = None
    """Folder for the degraded training images; None: ``<data>/.gsmsdr_cache`` (use another place when the scene
    directory is read-only)."""


class MixresDataParser(SortedSceneParser):
    """Reads a COLMAP scene under the mixed-resolution protocol (see the module docstring)."""

    config: MixresDataParserConfig

    def __init__(self, config: MixresDataParserConfig):
        super().__init__(config)
        self._train_images: Optional[MixresImages] = None

    def read_source(self) -> SceneSource:
        data = Path(self.config.data)
        candidates = [self.config.colmap_path] if self.config.colmap_path is not None else list(COLMAP_CANDIDATES)
        recon = find_colmap_model(data, candidates)
        if recon is None:
            looked = " or ".join(f"'{data / c}'" for c in candidates)
            raise InputError(
                f"gsmsdr: mixres-data needs a COLMAP model: none in {looked} (cameras + images .bin/.txt). Run "
                "COLMAP on the images (Mip-NeRF 360 scenes ship sparse/0)."
            )
        return self.colmap_source(recon)

    def train_images(self, names: List[str], files: List[Path]) -> MixresImages:
        if self._train_images is None:
            factors = tuple(int(f) for f in self.config.factors)
            if not factors or min(factors) < 1:
                raise InputError(f"gsmsdr: mixres factors must be integers >= 1, got {list(self.config.factors)}.")
            images_dir = self.images_dir().name
            data = Path(self.config.data)
            cache = cache_dir_for(data, self.config.seed, images_dir)
            if self.config.cache_path is not None:
                cache = Path(self.config.cache_path) / cache.name
            try:
                self._train_images = mixres_cache(
                    data,
                    cache,
                    names,
                    files,
                    seed=self.config.seed,
                    factors=factors,
                    params={"eval_interval": int(self.config.eval_interval), "images_dir": images_dir},
                    log=lambda msg: CONSOLE.log(f"gsmsdr: {msg}"),
                )
            except PermissionError as err:
                raise InputError(
                    f"gsmsdr: cannot write the mixed-resolution cache '{cache}': {err}. Point "
                    "--pipeline.datamanager.dataparser.cache-path at a writable folder."
                ) from err
            counts = group_sizes(self._train_images.factors, factors)
            sizes = ", ".join(f"{n} at 1/{f}" for n, f in zip(counts, factors))
            CONSOLE.log(f"gsmsdr: mixed-resolution training views (seed {self.config.seed}): {sizes}")
        return self._train_images

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        if self.config.eval_interval < 2:
            raise InputError(
                f"gsmsdr: eval_interval must be >= 2 (every N-th view is a test view), got {self.config.eval_interval}."
            )
        scene = self.load_scene()
        names = scene.cameras.names
        train, test = holdout_split(len(names), self.config.eval_interval)
        indices = split_indices(split, train, test)
        if len(indices) == 0:
            raise InputError(
                f"gsmsdr: the {split} split of '{self.config.data}' is empty ({len(names)} views, every "
                f"{self.config.eval_interval}th held out)."
            )
        if split == "train":
            images = self.train_images([names[i] for i in train], [scene.files[i] for i in train])
            files = images.files
            records = [
                {"name": names[i], "split": "train", "degraded": factor > 1,
                 "effects": {"mixres": {"factor": factor}}, "mixres_factor": factor}
                for i, factor in zip(train, images.factors)
            ]  # fmt: skip
            cache = str(images.cache_dir)
        else:
            files = [scene.files[i] for i in indices]
            records = [{**sharp_record(names[i], split), "ground_truth": files[k].parent.name} for k, i in
                       enumerate(indices)]  # fmt: skip
            cache = None
        metadata = {"degradations": records, "hold": int(self.config.eval_interval), "mixres_cache": cache}
        return self.make_outputs(scene, indices, files, metadata)

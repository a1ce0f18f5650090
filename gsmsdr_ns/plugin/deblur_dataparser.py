"""``deblur-nerf-data``: scenes in the Deblur-NeRF layout (also what ``gsmsdr-degrade`` writes).

Layout::

    <scene>/images/ or images_N/   every view; sorted by file name, the views whose index % N == 0 are test views
    <scene>/images_test/           optional sharp twin of every view (same names), the evaluation ground truth
    <scene>/sparse/0/              COLMAP model; or, without one, poses_bounds.npy (LLFF, rows in file-name order)
    <scene>/hold=N                 empty file giving N (default 8, with a warning, when absent)
    <scene>/degradation.json       optional: which training views are degraded and how

Splits: ``train`` = the views with index % N != 0 (the degraded ones); ``val`` and ``test`` = the held-out sharp
views, read from ``images_test/`` (``images_test_N/`` first when reading ``images_N/``) when it exists, else from
the image folder. ``metadata["degradations"]`` holds one record per image of the split, in the split's order (see
``gsmsdr_ns.data.degradation``); ``metadata["hold"]`` the interval.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Tuple, Type

from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs

from gsmsdr_ns.data.degradation import load_degradation_json, match_entries, record_from_entry, sharp_record
from gsmsdr_ns.data.layout import DEFAULT_HOLD, hold_files, holdout_split, read_hold
from gsmsdr_ns.io.errors import InputError, InputWarning
from gsmsdr_ns.io.images import read_image_size, resolve_image
from gsmsdr_ns.plugin.scene_parser import (
    POSES_BOUNDS,
    SceneSource,
    SortedSceneParser,
    SortedSceneParserConfig,
    find_colmap_model,
    split_indices,
)


@dataclass
class DeblurNerfDataParserConfig(SortedSceneParserConfig):
    """Deblur-NeRF layout: blurry training views, sharp held-out test views (hold=N), optional sharp twins."""

    _target: Type = field(default_factory=lambda: DeblurNerfDataParser)
    colmap_path: Path = Path("sparse/0")
    """COLMAP model directory, relative to the data path."""
    pose_source: Literal["auto", "colmap", "poses_bounds"] = "auto"
    """Where camera poses come from: "auto" uses the COLMAP model when there is one, else poses_bounds.npy."""
    test_images_path: Path = Path("images_test")
    """Folder of sharp twins (evaluation ground truth), relative to the data path; used when it exists."""
    default_hold: int = DEFAULT_HOLD
    """Holdout interval when the scene has no ``hold=N`` file (and degradation.json names none)."""
    degradation_file: Path = Path("degradation.json")
    """Per-image degradation description, relative to the data path; optional."""


class DeblurNerfDataParser(SortedSceneParser):
    """Reads the Deblur-NeRF layout (see the module docstring)."""

    config: DeblurNerfDataParserConfig

    def __init__(self, config: DeblurNerfDataParserConfig):
        super().__init__(config)
        self._hold: Optional[Tuple[int, str]] = None
        self._degradation: Optional[Tuple[Optional[Dict[str, Any]], Dict[str, Optional[Dict[str, Any]]]]] = None

    # --- cameras -----------------------------------------------------------------------------------------------

    def read_source(self) -> SceneSource:
        data = Path(self.config.data)
        recon = data / self.config.colmap_path
        poses_bounds = data / POSES_BOUNDS
        source = self.config.pose_source
        if source == "auto":
            if find_colmap_model(data, [self.config.colmap_path]) is not None:
                source = "colmap"
            elif poses_bounds.is_file():
                source = "poses_bounds"
            else:
                raise InputError(
                    f"gsmsdr: '{data}' has no camera poses: no COLMAP model in '{recon}' (cameras + images .bin/.txt) "
                    f"and no '{poses_bounds}'. A Deblur-NeRF scene needs one of them; run COLMAP on the images, or "
                    "set --pipeline.datamanager.dataparser.colmap-path if the model lives elsewhere."
                )
        if source == "colmap":
            return self.colmap_source(recon)
        if not poses_bounds.is_file():
            raise InputError(f"gsmsdr: pose_source is poses_bounds but '{poses_bounds}' does not exist.")
        return self.read_llff(poses_bounds)

    # --- hold and degradation.json -----------------------------------------------------------------------------

    def degradation(self, names: List[str]):
        """(degradation.json document or None, name -> entry) for the scene's images."""
        if self._degradation is None:
            path = Path(self.config.data) / self.config.degradation_file
            if path.is_file():
                doc = load_degradation_json(path)
                self._degradation = (doc, match_entries(doc, names, path))
            else:
                self._degradation = (None, {name: None for name in names})
        return self._degradation

    def hold(self, names: List[str]) -> Tuple[int, str]:
        """The holdout interval and its origin; the hold file and degradation.json must agree with each other."""
        if self._hold is None:
            data = Path(self.config.data)
            doc, entries = self.degradation(names)
            doc_hold = doc.get("hold") if doc is not None else None
            json_path = data / self.config.degradation_file
            if doc_hold is not None and not hold_files(data):
                if not isinstance(doc_hold, int) or isinstance(doc_hold, bool) or doc_hold < 1:
                    raise InputError(f"gsmsdr: '{json_path}' has hold {doc_hold!r}; it must be an integer >= 1.")
                hold, origin = doc_hold, str(json_path)
            else:
                hold, origin = read_hold(data, self.config.default_hold)
                if doc_hold is not None and doc_hold != hold:
                    raise InputError(
                        f"gsmsdr: the holdout interval of '{data}' is {hold} ({origin}) but '{json_path}' says hold "
                        f"{doc_hold}. Make them agree (re-create the scene with gsmsdr-degrade)."
                    )
            for index, name in enumerate(names):
                entry = entries.get(name)
                expected = "test" if index % hold == 0 else "train"
                if entry is not None and entry.get("split") not in (None, expected):
                    raise InputError(
                        f"gsmsdr: '{json_path}' puts image '{name}' (index {index} in file-name order) in the "
                        f"{entry['split']} split, but hold={hold} makes it a {expected} view. The file does not belong "
                        "to this image set (added or removed images shift the held-out views)."
                    )
            self._hold = (hold, origin)
        return self._hold

    # --- splits ------------------------------------------------------------------------------------------------

    def test_images_dir(self) -> Optional[Path]:
        data = Path(self.config.data)
        base = data / self.config.test_images_path
        factor = int(self.config.downscale_factor)
        if factor > 1 and Path(f"{base}_{factor}").is_dir():
            return Path(f"{base}_{factor}")
        return base if base.is_dir() else None

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        scene = self.load_scene()
        names = scene.cameras.names
        hold, hold_origin = self.hold(names)
        train, test = holdout_split(len(names), hold)
        indices = split_indices(split, train, test)
        if len(indices) == 0:
            raise InputError(
                f"gsmsdr: the {split} split of '{self.config.data}' is empty: {len(names)} views with hold={hold} "
                f"({hold_origin}). Use a hold interval between 2 and the number of views."
            )
        doc, entries = self.degradation(names)
        if split == "train":
            files = [scene.files[i] for i in indices]
            records = [record_from_entry(names[i], "train", entries.get(names[i])) for i in indices]
        else:
            twins = self.test_images_dir()
            if twins is not None:
                files = [resolve_image(twins, names[i], f"'{self.images_dir()}' (its sharp twin)") for i in indices]
                self.check_image_sizes(scene.cameras, indices, files)
                self._warn_if_twins_differ_in_size(files, [scene.files[i] for i in indices])
            else:
                files = [scene.files[i] for i in indices]
            records = [
                {**sharp_record(names[i], split), "ground_truth": str(Path(f).parent.name)}
                for i, f in zip(indices, files)
            ]
        metadata = {
            "degradations": records,
            "hold": hold,
            "degradation_info": None if doc is None else {k: v for k, v in doc.items() if k != "images"},
        }
        return self.make_outputs(scene, indices, files, metadata)

    def _warn_if_twins_differ_in_size(self, twins: List[Path], originals: List[Path]) -> None:
        if not twins:
            return
        twin_size, own_size = read_image_size(twins[0]), read_image_size(originals[0])
        if twin_size != own_size:
            warnings.warn(
                f"gsmsdr: the sharp twins in '{twins[0].parent}' are {twin_size[0]}x{twin_size[1]} px but the "
                f"training images in '{originals[0].parent}' are {own_size[0]}x{own_size[1]} px; evaluating at the "
                "twins' size.",
                InputWarning,
                stacklevel=3,
            )

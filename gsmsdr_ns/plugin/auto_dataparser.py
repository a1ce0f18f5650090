"""``gsmsdr-data``: recognise the scene layout and hand over to the reader it needs.

``gsmsdr_ns.data.layout.detect_layout`` decides (Deblur-NeRF markers -> ``deblur-nerf-data``; ``sparse/0`` ->
the validating COLMAP reader; ``transforms.json`` -> nerfstudio's ``nerfstudio-data``; ``colmap/sparse/0`` ->
the COLMAP reader; ``poses_bounds.npy`` alone -> ``deblur-nerf-data``); the choice and its reason are logged as
one line, once per parser. Each reader keeps its own nested options (``--pipeline.datamanager.dataparser.deblur.*``,
``.colmap.*``, ``.nerfstudio.*``); their ``data`` is replaced by this parser's. Naming a dataparser on the
command line (``ns-train gsmsdr ... deblur-nerf-data``) bypasses the detection altogether.

A transforms.json scene is checked before nerfstudio's reader sees it (``gsmsdr_ns.data.transforms``: frames,
poses that are rotations, image files present) and its images are decoded once per split after it (a truncated
file fails with its name before training).

Training images without a degradation record (a COLMAP or transforms.json scene, or a Deblur-NeRF scene without
``degradation.json``) get an estimated record (``gsmsdr_ns.estimate``: sharp / motion / defocus / lower resolution,
judged against the other photos of the scene, cached in ``<scene>/degradation.estimated.json``), so sharp photos
train as plain splatfacto steps and only degraded ones pay for a degradation model; images the estimate cannot
decide stay unknown. ``--pipeline.datamanager.dataparser.estimate-degradations False`` keeps them all unknown.
"""

from __future__ import annotations

import dataclasses
import re
import warnings
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Type

from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataParserConfig, DataparserOutputs
from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig
from nerfstudio.utils.rich_utils import CONSOLE

from gsmsdr_ns.data.degradation import record_from_entry, unknown_record
from gsmsdr_ns.data.layout import LayoutChoice, detect_layout
from gsmsdr_ns.data.transforms import check_transforms_json, transforms_file
from gsmsdr_ns.io.errors import InputError, InputWarning
from gsmsdr_ns.plugin.dataparser import GSMSDRDataParserConfig, check_image_files
from gsmsdr_ns.plugin.deblur_dataparser import DeblurNerfDataParserConfig


@dataclass
class GSMSDRAutoDataParserConfig(DataParserConfig):
    """Any supported scene: Deblur-NeRF / degraded, COLMAP / Mip-NeRF 360, nerfstudio transforms.json, LLFF."""

    _target: Type = field(default_factory=lambda: GSMSDRAutoDataParser)
    data: Path = Path()
    """Scene directory (or a transforms .json file)."""
    deblur: DeblurNerfDataParserConfig = field(default_factory=DeblurNerfDataParserConfig)
    """Options of the Deblur-NeRF / LLFF reader, used when the scene has that layout."""
    colmap: GSMSDRDataParserConfig = field(default_factory=lambda: GSMSDRDataParserConfig(load_3D_points=True))
    """Options of the COLMAP reader, used for COLMAP / Mip-NeRF 360 scenes (its colmap_path is detected)."""
    nerfstudio: NerfstudioDataParserConfig = field(default_factory=NerfstudioDataParserConfig)
    """Options of nerfstudio's reader, used for transforms.json scenes."""
    estimate_degradations: bool = True
    """Estimate a degradation record for each training image that has none (cached next to the images' folder)."""
    refuse_copied_test_views: bool = True
    """Refuse a scene whose test split holds a copy (byte-identical, re-encoded or resized) of a training image: its
    score would measure memory. False: warn only. Costs one decode of every image when the splits are read."""
    verify_images: bool = True
    """For transforms.json scenes: decode every image of a split once while parsing, so missing, truncated or
    corrupt files fail before training with their name (the other readers have their own verify_images)."""


class GSMSDRAutoDataParser(DataParser):
    """Detects the layout once, logs the choice, and delegates every split to the chosen reader."""

    config: GSMSDRAutoDataParserConfig

    def __init__(self, config: GSMSDRAutoDataParserConfig):
        super().__init__(config)
        self.config = config
        self.choice: Optional[LayoutChoice] = None
        self._delegate: Optional[DataParser] = None

    @property
    def delegate(self) -> DataParser:
        if self._delegate is None:
            data = Path(self.config.data)
            choice = detect_layout(data)
            if choice.reader == "deblur-nerf-data":
                sub = dataclasses.replace(self.config.deblur, data=data)
            elif choice.reader == "colmap":
                sub = dataclasses.replace(self.config.colmap, data=data, colmap_path=choice.colmap_path)
            else:
                sub = dataclasses.replace(self.config.nerfstudio, data=data)
                check_transforms_json(data, sub.downscale_factor)  # before nerfstudio's asserts
            CONSOLE.print(
                f"gsmsdr-data: reading '{data}' with {choice.reader} ({choice.reason})",
                soft_wrap=True,
                markup=False,
                highlight=False,
            )
            self.choice, self._delegate = choice, sub.setup()
        return self._delegate

    def _check_copied_test_views(self, train: List[Path], test: List[Path]) -> None:
        from gsmsdr_ns.process.duplicates import copies_across

        pairs = copies_across(train, test)
        if not pairs:
            return
        message = _copied_test_views_message(pairs, Path(self.config.data))
        if self.config.refuse_copied_test_views:
            raise InputError(message)
        warnings.warn(InputWarning(message), stacklevel=2)

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        outputs = self.delegate.get_dataparser_outputs(split=split, **kwargs)
        if self.choice is not None and self.choice.reader == "nerfstudio-data" and self.config.verify_images:
            check_image_files(outputs.image_filenames, f"'{transforms_file(self.config.data)}'")
        if split == "train":
            self._train_images = list(outputs.image_filenames)
        elif getattr(self, "_train_images", None):
            self._check_copied_test_views(self._train_images, list(outputs.image_filenames))
        if split == "train" and self.config.estimate_degradations:
            records = outputs.metadata.get("degradations")
            if records is None:
                records = [unknown_record(Path(f).name, "train") for f in outputs.image_filenames]
            if any(r["degraded"] is None for r in records):
                outputs.metadata["degradations"] = estimated_records(outputs.image_filenames, records)
        return outputs


def _copied_test_views_message(pairs, data: Path) -> str:
    shown = ", ".join(f"'{test.name}' (= training image '{train}')" for test, train in pairs[:10])
    more = f", ... ({len(pairs)} in all)" if len(pairs) > 10 else ""
    return (
        f"gsmsdr: test view(s) of '{data}' that copy a training image: {shown}{more}. Their scores would measure "
        "memory, not reconstruction: remove the copies (or retake those views). "
        "--pipeline.datamanager.dataparser.refuse-copied-test-views False trains anyway."
    )


def estimate_folder(folder: Path, names: List[str]) -> Path:
    """The folder whose copies of the training images the estimate judges: ``images/`` when training reads a
    downscaled ``images_N/`` and ``images/`` holds every one of them (blur a few pixels wide at full size is a
    pixel or less after downscaling, too little to tell from sharp), else ``folder`` itself."""
    full = folder.parent / "images"
    if re.fullmatch(r"images_\d+", folder.name) and full.is_dir() and all((full / n).is_file() for n in names):
        return full
    return folder


def estimated_records(image_filenames: List[Path], records: List[Dict[str, Any]]) -> List[Dict[str, Any]]:
    """``records`` with every unknown one (``degraded`` None) replaced by the estimate of its image.

    The estimate judges each photo against the others in its folder, at full size when the folder is a downscaled
    copy (:func:`estimate_folder`), with ``estimate_scene_records`` (cached beside the folder; a reused cache is
    checked against the degradation.json schema); images it leaves undecided stay unknown. Logs one line with the
    counts per label.
    """
    from gsmsdr_ns.estimate.records import CACHE_FILE, estimate_scene_records

    folders = {Path(f).parent for f in image_filenames}
    if len(folders) != 1:
        CONSOLE.print(f"gsmsdr-data: training images span {len(folders)} folders; not estimating their degradation")
        return records
    folder = estimate_folder(folders.pop(), [Path(f).name for f in image_filenames])
    entries = estimate_scene_records(folder.parent, folder.name)
    estimated, counts = [], Counter()
    for path, record in zip(image_filenames, records):
        entry = entries.get(Path(path).name)
        if record["degraded"] is not None or entry is None:
            estimated.append(record)
            continue
        label = entry.get("estimate", {}).get("label", "unknown")
        if label == "unknown" and entry.get("effects"):
            label = "blurred (kind unknown)"  # both blur models, as an unknown image would get, but no resolution model
        counts[label] += 1
        decided = label != "unknown"
        estimated.append(record_from_entry(record["name"], "train", entry) if decided else record)
    summary = ", ".join(f"{n} {label}" for label, n in sorted(counts.items()))
    CONSOLE.print(
        f"gsmsdr-data: no degradation records for {sum(counts.values())} training images; estimated from the photos: "
        f"{summary} (judged on {folder}; cached in {folder.parent / CACHE_FILE}; write a degradation.json to "
        "override)",
        soft_wrap=True,
        markup=False,
        highlight=False,
    )
    return estimated

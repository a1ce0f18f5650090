"""``gsmsdr-data``: recognise the scene layout and hand over to the reader it needs.

``gsmsdr_ns.data.layout.detect_layout`` decides (Deblur-NeRF markers -> ``deblur-nerf-data``; ``sparse/0`` ->
the validating COLMAP reader; ``transforms.json`` -> nerfstudio's ``nerfstudio-data``; ``colmap/sparse/0`` ->
the COLMAP reader; ``poses_bounds.npy`` alone -> ``deblur-nerf-data``); the choice and its reason are logged as
one line, once per parser. Each reader keeps its own nested options (``--pipeline.datamanager.dataparser.deblur.*``,
``.colmap.*``, ``.nerfstudio.*``); their ``data`` is replaced by this parser's. Naming a dataparser on the
command line (``ns-train gsmsdr ... deblur-nerf-data``) bypasses the detection altogether.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Type

from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataParserConfig, DataparserOutputs
from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig
from nerfstudio.utils.rich_utils import CONSOLE

from gsmsdr_ns.data.layout import LayoutChoice, detect_layout
from gsmsdr_ns.plugin.dataparser import GSMSDRDataParserConfig
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
            CONSOLE.print(
                f"gsmsdr-data: reading '{data}' with {choice.reader} ({choice.reason})",
                soft_wrap=True,
                markup=False,
                highlight=False,
            )
            self.choice, self._delegate = choice, sub.setup()
        return self._delegate

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        return self.delegate.get_dataparser_outputs(split=split, **kwargs)

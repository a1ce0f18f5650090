"""nerfstudio entry points (``nerfstudio.dataparser_configs``): ``deblur-nerf-data``, ``mixres-data``, ``gsmsdr-data``.

nerfstudio imports this module while it builds its dataparser union (``nerfstudio.configs.dataparser_configs``),
which the datamanager configs import in turn: importing a datamanager or the method config from here would be a
circular import. Only the dataparser modules are imported.
"""

from nerfstudio.plugins.registry_dataparser import DataParserSpecification

from gsmsdr_ns.plugin.auto_dataparser import GSMSDRAutoDataParserConfig
from gsmsdr_ns.plugin.deblur_dataparser import DeblurNerfDataParserConfig
from gsmsdr_ns.plugin.mixres_dataparser import MixresDataParserConfig

deblur_nerf_data = DataParserSpecification(
    config=DeblurNerfDataParserConfig(),
    description="Deblur-NeRF layout (hold=N, images_test/, degradation.json; sparse/0 or poses_bounds.npy)",
)
mixres_data = DataParserSpecification(
    config=MixresDataParserConfig(),
    description="COLMAP / Mip-NeRF 360 scene under the mixed-resolution protocol (4x/3x/2x/1x training groups)",
)
gsmsdr_data = DataParserSpecification(
    config=GSMSDRAutoDataParserConfig(),
    description="gsmsdr auto: detects Deblur-NeRF, COLMAP / Mip-NeRF 360, transforms.json or LLFF scenes",
)

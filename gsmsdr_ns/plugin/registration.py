"""nerfstudio entry point (``nerfstudio.method_configs``): ``gsmsdr = gsmsdr_ns.plugin.registration:gsmsdr_method``.

Only the MethodSpecification lives here. nerfstudio imports this module while it discovers methods (also inside
``nerfstudio.configs.method_configs``), so it must not import that module (circular import) and the renderer is
imported lazily by the model on first use.
"""

from nerfstudio.plugins.types import MethodSpecification

from gsmsdr_ns.plugin.method_config import gsmsdr_trainer_config

gsmsdr_method = MethodSpecification(
    config=gsmsdr_trainer_config(),
    description="GS-MSDR: Gaussian splatting for blurred / mixed-resolution photos (CPU or GPU renderer)",
)

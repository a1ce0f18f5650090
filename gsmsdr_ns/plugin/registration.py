"""nerfstudio entry points (``nerfstudio.method_configs``): ``gsmsdr``, ``gsmsdr-lite`` and ``gsmsdr-cpu`` =
``gsmsdr_ns.plugin.registration:gsmsdr_method`` / ``gsmsdr_lite_method`` / ``gsmsdr_cpu_method``.

Only the MethodSpecifications live here (the presets are in ``method_config``). nerfstudio imports this module while
it discovers methods (also inside ``nerfstudio.configs.method_configs``), so it must not import that module (circular
import) and the renderer is imported lazily by the model on first use.
"""

from nerfstudio.plugins.types import MethodSpecification

from gsmsdr_ns.plugin.method_config import (
    gsmsdr_cpu_trainer_config,
    gsmsdr_lite_trainer_config,
    gsmsdr_trainer_config,
)

gsmsdr_method = MethodSpecification(
    config=gsmsdr_trainer_config(),
    description="GS-MSDR: Gaussian splatting for blurred / mixed-resolution photos (CPU or GPU renderer)",
)

gsmsdr_lite_method = MethodSpecification(
    config=gsmsdr_lite_trainer_config(),
    description="GS-MSDR lite: fast preset for CPU and previews (lite blur field, SH degree 1, 7000 steps)",
)

gsmsdr_cpu_method = MethodSpecification(
    config=gsmsdr_cpu_trainer_config(),
    description="GS-MSDR CPU: real-size captures on a CPU (a learnt kernel up to 33 px per view, thin lens, 3k steps)",
)

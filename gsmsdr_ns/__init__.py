"""gsmsdr-ns: GS-MSDR deblurring Gaussian splatting as a nerfstudio plugin.

The core packages (`render`, `synth`, later `blur` and `degrade`) import without the nerfstudio trainer;
`gsmsdr_ns.plugin` is the thin nerfstudio glue layer.
"""

__version__ = "0.1.0"

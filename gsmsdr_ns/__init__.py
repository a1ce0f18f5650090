"""gsmsdr-ns: GS-MSDR deblurring Gaussian splatting as a nerfstudio plugin.

The core packages (`render`, `blur`, `degrade`, `synth`, `data`) import without the nerfstudio trainer;
`gsmsdr_ns.plugin` is the thin nerfstudio glue layer and `gsmsdr_ns.bench` drives nerfstudio's trainer for benchmarks.
"""

__version__ = "0.1.0"

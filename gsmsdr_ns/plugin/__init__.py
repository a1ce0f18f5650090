"""nerfstudio glue for GS-MSDR: dataparser, model and the ``gsmsdr`` method config.

Importing this package (nerfstudio does so while discovering methods and while reading a run's ``config.yml``)
allow-lists the numpy scalar types that nerfstudio checkpoints contain, so ``ns-eval``, ``ns-viewer`` and
``ns-train --load-dir`` load them under torch's ``weights_only=True`` default (see ``checkpoint.py``).
"""

from gsmsdr_ns.plugin.checkpoint import register_checkpoint_safe_globals

register_checkpoint_safe_globals()

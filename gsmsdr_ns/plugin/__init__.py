"""nerfstudio glue for GS-MSDR: dataparser, model, trainer and the ``gsmsdr`` method configs.

Importing this package (nerfstudio does so while discovering methods and while reading a run's ``config.yml``):

* allow-lists the numpy scalar types that nerfstudio checkpoints contain, so ``ns-eval``, ``ns-viewer`` and
  ``ns-train --load-dir`` load them under torch's ``weights_only=True`` default (see ``checkpoint_io.py``);
* installs the exception hook that prints gsmsdr's own errors (bad input, full disk) as one line without a
  traceback in ``ns-train``, ``ns-eval`` and ``ns-viewer`` (``GSMSDR_DEBUG=1`` keeps the traceback; see
  ``gsmsdr_ns._cli``). Other exceptions print as before.
"""

from gsmsdr_ns._cli import install_excepthook
from gsmsdr_ns.plugin.checkpoint_io import register_checkpoint_safe_globals

register_checkpoint_safe_globals()
install_excepthook()

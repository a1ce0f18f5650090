"""Input and output without nerfstudio: the one COLMAP reader / writer, image reader / writer, atomic writes,
dataclass configs from YAML, where photo sets live, and the one input-error type.

* :mod:`gsmsdr_ns.io.errors` - :class:`InputError` (bad input; the message names the file and the fix) and
  :class:`InputWarning`;
* :mod:`gsmsdr_ns.io.colmap` - :func:`read_colmap` -> :class:`ColmapModel`, :func:`write_colmap_model`;
* :mod:`gsmsdr_ns.io.images` - :func:`read_image`, :func:`read_image_float`, :func:`read_image_size`,
  :func:`write_image`, folder listing;
* :mod:`gsmsdr_ns.io.atomic` - files and folders that appear complete or not at all;
* :mod:`gsmsdr_ns.io.config` - :func:`load_dataclass`, :func:`read_yaml_mapping`;
* :mod:`gsmsdr_ns.io.photo_sets` - :func:`find_photo_set`: real photo sets under $GSMSDR_DATA_DIR or
  ``shared/data/``.
"""

from gsmsdr_ns.io.errors import InputError, InputWarning

__all__ = ["InputError", "InputWarning"]

"""cva_confidence_ros: per-pixel confidence for dense stereo matching with CVA-Net.

Layers (nothing in the core imports rclpy):

* core: :mod:`.matching` (cost volumes), :mod:`.confidence` (confidence methods),
  :mod:`.model` (CVA-Net), :mod:`.metrics` (the paper's ROC/AUC protocol);
* I/O: :mod:`.datasets` (stereo data sets), :mod:`msg_tools` (rosbag2);
* on top: :mod:`.pipeline` (matcher + confidence, shared by node and tools), :mod:`.node`,
  :mod:`.cloud_filter` (point clouds cut at a confidence threshold downstream).
"""

from cva_confidence_ros.errors import (
    BagError,
    ConfigError,
    CVAError,
    DataError,
    InputError,
    ModelError,
)
from cva_confidence_ros.jit import ensure_jit_cache as _ensure_jit_cache

try:
    # Before any numba kernel is defined: a read-only install with no writable home made
    # every import of a kernel module fail (numba's 'cannot cache function').
    _ensure_jit_cache()
except ConfigError as _error:
    import warnings

    warnings.warn(str(_error), RuntimeWarning, stacklevel=2)

__version__ = '0.1.0'

__all__ = [
    'BagError',
    'CVAError',
    'ConfigError',
    'DataError',
    'InputError',
    'ModelError',
    '__version__',
]

"""CVA-Net, CVA-Net-Lite and CVA-Net-Fast: the networks, their inference (whole, per pixel,
sparse + filled) and weights I/O."""

from __future__ import annotations

from cva_confidence_ros.model.complexity import dense_macs, macs_per_pixel
from cva_confidence_ros.model.fast import CVANetFast, FoldedCVANetFast
from cva_confidence_ros.model.inference import (
    PAD,
    FoldedCVANet,
    fold_batchnorm,
    pad_cost_volume,
    predict_confidence,
    predict_confidence_at,
    resolve_device,
    tile_shape,
)
from cva_confidence_ros.model.lite import CVANetLite, FoldedCVANetLite
from cva_confidence_ros.model.network import (
    PATCH_SIZE,
    CVANet,
    expected_parameter_count,
    keras_parameter_count,
)
from cva_confidence_ros.model.sparse import (
    SparseConfig,
    SparseEvaluator,
    SparseResult,
    sparse_confidence,
)
from cva_confidence_ros.model.weights import (
    ARCHITECTURES,
    architecture_of,
    default_weights_path,
    load_weights,
    save_weights,
    weights_file_name,
    weights_search_dirs,
)

__all__ = [
    'ARCHITECTURES',
    'PAD',
    'PATCH_SIZE',
    'CVANet',
    'CVANetFast',
    'CVANetLite',
    'FoldedCVANet',
    'FoldedCVANetFast',
    'FoldedCVANetLite',
    'architecture_of',
    'SparseConfig',
    'SparseEvaluator',
    'SparseResult',
    'default_weights_path',
    'dense_macs',
    'expected_parameter_count',
    'fold_batchnorm',
    'keras_parameter_count',
    'load_weights',
    'macs_per_pixel',
    'pad_cost_volume',
    'predict_confidence',
    'predict_confidence_at',
    'resolve_device',
    'save_weights',
    'sparse_confidence',
    'tile_shape',
    'weights_file_name',
    'weights_search_dirs',
]

# Architectures registered on import: the baselines that read the disparity map (CCNN, LFN,
# LGC-Net), so that load_weights knows them wherever the package is used.
from cva_confidence_ros.model import baselines  # noqa: E402, F401

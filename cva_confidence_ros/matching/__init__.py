"""Dense stereo matching: cost volumes, winner-takes-all and sub-pixel disparity, left–right
check, speckle filter.

One cost-volume layout everywhere (see docs/ARCHITECTURE.md): (D, H, W) float32 in [0, 1],
0 = perfect match, entry [d, y, x] = cost of left (y, x) with right (y, x − d), 1.0 where
x − d < 0. The right-reference volume (``view='right'``) pairs right (y, x) with left
(y, x + d), 1.0 where x + d ≥ W.

Matchers live in :data:`MATCHERS`; adding one is one module with a :class:`Matcher` subclass
and one ``MATCHERS.add`` line below.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from cva_confidence_ros.errors import MemoryShortfallError
from cva_confidence_ros.matching.base import (
    VIEWS,
    Matcher,
    check_image_pair,
    check_max_disparity,
    check_view,
)
from cva_confidence_ros.matching.census_bm import CensusBlockMatcher, CensusBMConfig
from cva_confidence_ros.matching.census_sgm import CensusSGMConfig, CensusSGMMatcher
from cva_confidence_ros.matching.disparity import left_right_check, wta_disparity
from cva_confidence_ros.matching.mccnn_fast import MCCNNFastConfig, MCCNNFastMatcher
from cva_confidence_ros.matching.speckle import remove_speckles
from cva_confidence_ros.matching.subpixel import SUBPIXEL_METHODS, refine_subpixel
from cva_confidence_ros.registry import Registry

__all__ = [
    'MATCHERS',
    'SUBPIXEL_METHODS',
    'VIEWS',
    'CensusBMConfig',
    'CensusBlockMatcher',
    'CensusSGMConfig',
    'CensusSGMMatcher',
    'MCCNNFastConfig',
    'MCCNNFastMatcher',
    'Matcher',
    'compute_cost_volume',
    'left_right_check',
    'refine_subpixel',
    'remove_speckles',
    'wta_disparity',
]

#: Matcher classes by name.
MATCHERS: Registry[type[Matcher]] = Registry('matcher')
MATCHERS.add('census_bm', CensusBlockMatcher)
MATCHERS.add('census_sgm', CensusSGMMatcher)
MATCHERS.add('mccnn_fast', MCCNNFastMatcher)


def compute_cost_volume(
    left: np.ndarray,
    right: np.ndarray,
    matcher: str,
    max_disparity: int,
    view: str = 'left',
    **params: Any,
) -> np.ndarray:
    """Matching-cost volume of a rectified stereo pair.

    Args:
        left: (H, W) gray or (H, W, 3) RGB uint8 left image (float arrays with finite values in
            [0, 255] are rounded to uint8).
        right: Right image, same shape as ``left``.
        matcher: Registered name: ``census_bm``, ``census_sgm`` or ``mccnn_fast``.
        max_disparity: D, the number of disparities 0 … D − 1; 1 ≤ D < W.
        view: ``'left'``: entry [d, y, x] is the cost of left (y, x) with right (y, x − d), 1.0
            where x − d < 0. ``'right'``: cost of right (y, x) with left (y, x + d), 1.0 where
            x + d ≥ W.
        **params: Fields of the matcher's config dataclass (``window`` for census_bm; ``p1``,
            ``p2`` for census_sgm; ``device``, ``weights`` for mccnn_fast).

    Returns:
        (D, H, W) float32 C-contiguous costs in [0, 1], 0 = perfect match.

    Raises:
        InputError: Images that are not arrays, of different shapes, empty, of another dtype,
            or with NaN/inf or out-of-range float values.
        MemoryShortfallError: A volume (with the matcher's work arrays) larger than the memory
            available (``memory.available_memory``); an InputError too.
        ConfigError: Unknown matcher, view or parameter, bad parameter values, or
            max_disparity not an integer in [1, W).
    """
    matcher_class = MATCHERS.get(matcher)
    view = check_view(view)
    instance = matcher_class.from_params(**params)
    left_u8, right_u8 = check_image_pair(left, right)
    depth = check_max_disparity(max_disparity, left_u8.shape[1])
    from cva_confidence_ros.memory import CHECK_SWITCH, shortfall

    height, width = left_u8.shape[:2]
    # Python ints: H·W·D of a 2448×2048 pair at D = 512 is 2.6e9, past int32.
    # MC-CNN's features live where its network runs: on a GPU they take no host memory.
    on_host = getattr(instance.config, 'device', 'cpu') == 'cpu' or not _cuda_available()
    need = matcher_class.bytes_per_voxel * depth * height * width + (
        matcher_class.bytes_per_pixel * height * width if on_host else 0)
    available = shortfall(need)
    if available is not None:
        # Refused before allocating: numpy's lazy allocation succeeds, and the kernel's OOM
        # killer ends the process once the volume is written.
        raise MemoryShortfallError(
            f'the {matcher} cost volume of a {width}×{height} px pair at max_disparity = '
            f'{depth} needs at least {need / 1e9:.2f} GB, but {available / 1e9:.2f} GB of '
            f'memory are available; use a smaller max_disparity or shrink the pair '
            f'(datasets.resize_image; cva-evaluate --downsample) '
            f'({CHECK_SWITCH}=0 in the environment turns this check off)'
        )
    from cva_confidence_ros.jit import start_numba_threads

    start_numba_threads()  # keeps a user's torch.set_num_threads (as a pipeline does)
    return instance.compute(left_u8, right_u8, depth, view)


def _cuda_available() -> bool:
    import torch

    return torch.cuda.is_available()

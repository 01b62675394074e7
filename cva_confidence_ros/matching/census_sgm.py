"""Census + Semi-Global Matching: 5×5 census Hamming costs optimised along 8 paths."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cva_confidence_ros.checks import is_int
from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.matching.base import Matcher
from cva_confidence_ros.matching.census import CENSUS_BITS, census_views
from cva_confidence_ros.matching.sgm import MAX_ACCUMULATED, SGM_PATHS, census_sgm_volume

__all__ = ['CensusSGMConfig', 'CensusSGMMatcher']

#: Largest P2 for which S ≤ 8·(24 + P2) still fits the uint16 accumulator.
MAX_P2 = MAX_ACCUMULATED // SGM_PATHS - CENSUS_BITS


@dataclass(frozen=True)
class CensusSGMConfig:
    """Parameters of :class:`CensusSGMMatcher`, in Hamming-distance units (0…24 per pixel).

    Attributes:
        p1: Penalty of a disparity change of ±1 between neighbours along a path (≥ 0).
        p2: Penalty of a larger jump (p1 ≤ p2 ≤ 8167).
    """

    p1: int = 4
    p2: int = 32

    def __post_init__(self) -> None:
        if not is_int(self.p1) or not is_int(self.p2):
            raise ConfigError(f'p1 and p2 must be integers; got p1={self.p1!r}, p2={self.p2!r}')
        if not 0 <= self.p1 <= self.p2 <= MAX_P2:
            raise ConfigError(
                f'penalties must satisfy 0 ≤ p1 ≤ p2 ≤ {MAX_P2}; got p1={self.p1}, p2={self.p2}'
            )
        # Python ints: with a narrow numpy integer (np.uint8(200)) the normalisation
        # 8·(24 + p2) would wrap around in its dtype and scale the volume by inf or a wrong value.
        object.__setattr__(self, 'p1', int(self.p1))
        object.__setattr__(self, 'p2', int(self.p2))


class CensusSGMMatcher(Matcher):
    """5×5 census, per-pixel Hamming cost C ∈ [0, 24], aggregated by 8-path SGM.

    The volume is S / (8·(Cmax + P2)) with Cmax = 24: each path cost L_r is at most Cmax + P2
    (see :mod:`cva_confidence_ros.matching.sgm`), so the sum over the 8 paths is at most
    8·(Cmax + P2) and the result lies in [0, 1]. Along the paths, a disparity whose partner pixel
    is outside the image costs Cmax; in the returned volume those entries are 1.0.
    """

    Config = CensusSGMConfig
    # The volume, and the uint8 Hamming costs and uint16 sums kept between frames.
    bytes_per_voxel = 4 + 1 + 2
    config: CensusSGMConfig

    def compute(
        self, left: np.ndarray, right: np.ndarray, max_disparity: int, view: str
    ) -> np.ndarray:
        """(D, H, W) float32 costs in [0, 1]; 1.0 where the partner pixel is outside the image.

        See :meth:`Matcher.compute` for the arguments.
        """
        ref, other, step = census_views(left, right, view)
        return census_sgm_volume(
            ref, other, int(max_disparity), step, self.config.p1, self.config.p2
        )

"""Census block matching: 5×5 census, Hamming distance, summed over a square support window."""

from __future__ import annotations

from dataclasses import dataclass

from numba import njit, prange
import numpy as np

from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.matching.base import Matcher
from cva_confidence_ros.matching.census import (
    CENSUS_BITS,
    census_views,
    popcount,
    valid_range,
)

__all__ = ['CensusBMConfig', 'CensusBlockMatcher']


@dataclass(frozen=True)
class CensusBMConfig:
    """Parameters of :class:`CensusBlockMatcher`.

    Attributes:
        window: Side of the square support region the Hamming costs are summed over (odd, 1…15).
    """

    window: int = 5

    def __post_init__(self) -> None:
        if (
            isinstance(self.window, bool)
            or not isinstance(self.window, (int, np.integer))
            or not 1 <= self.window <= 15
            or self.window % 2 == 0
        ):
            raise ConfigError(f'window must be an odd integer in [1, 15]; got {self.window!r}')
        # An unsigned numpy integer (np.uint8(5) from a parameter file) would reach the kernel
        # as such: numba types its arithmetic with signed indices as float and cannot compile.
        object.__setattr__(self, 'window', int(self.window))


@njit(cache=True, fastmath=True)
def _window_row(
    ref: np.ndarray,
    other: np.ndarray,
    shift: int,
    lo: int,
    hi: int,
    radius: int,
    padded: np.ndarray,
    out: np.ndarray,
) -> None:
    """Horizontal window sums of one row of Hamming costs (partner of x is x + shift).

    ``padded`` (W + 2·radius + 1 cells) receives the costs with the border cells repeated, then
    their running sum, so that each window sum is one difference.
    """
    width = out.shape[0]
    # Cells whose partner lies outside the image count as the worst cost, so a support region
    # cut by the border is not mistaken for a good match.
    costs = padded[radius + 1:radius + 1 + width]
    costs[:lo] = CENSUS_BITS
    costs[hi:] = CENSUS_BITS
    inside = costs[lo:hi]
    ref_in = ref[lo:hi]
    other_in = other[lo + shift:hi + shift]
    for x in range(hi - lo):
        # numba's stubs type an intrinsic's call with the typing context as an argument
        inside[x] = popcount(ref_in[x] ^ other_in[x])  # type: ignore[call-arg]
    padded[0] = 0
    padded[1:radius + 1] = costs[0]
    padded[radius + 1 + width:] = costs[width - 1]
    for i in range(1, padded.shape[0]):
        padded[i] += padded[i - 1]
    upper = padded[2 * radius + 1:2 * radius + 1 + width]
    lower = padded[0:width]
    for x in range(width):
        out[x] = upper[x] - lower[x]


@njit(cache=True, parallel=True, fastmath=True)
def _block_kernel(
    codes_ref: np.ndarray, codes_other: np.ndarray, step: int, radius: int, volume: np.ndarray
) -> None:
    depth, height, width = volume.shape
    size = 2 * radius + 1
    scale = np.float32(1.0 / (CENSUS_BITS * size * size))
    for d in prange(depth):
        lo, hi = valid_range(width, d, step)
        shift = step * d
        padded = np.empty(width + 2 * radius + 1, np.int32)
        # Ring of the last `size` horizontal window sums; the vertical sum slides over it.
        ring = np.empty((size, width), np.int32)
        column = np.zeros(width, np.int32)
        for yy in range(-radius, radius):
            src = min(max(yy, 0), height - 1)
            slot = ring[(yy + size) % size]
            _window_row(codes_ref[src], codes_other[src], shift, lo, hi, radius, padded, slot)
            for x in range(width):
                column[x] += slot[x]
        for y in range(height):
            src = min(y + radius, height - 1)
            slot = ring[(y + radius) % size]
            _window_row(codes_ref[src], codes_other[src], shift, lo, hi, radius, padded, slot)
            row = volume[d, y]
            for x in range(width):
                column[x] += slot[x]
                row[x] = column[x] * scale
            for x in range(lo):
                row[x] = 1.0
            for x in range(hi, width):
                row[x] = 1.0
            oldest = ring[(y - radius + size) % size]
            for x in range(width):
                column[x] -= oldest[x]


class CensusBlockMatcher(Matcher):
    """5×5 census transform + Hamming distance + box aggregation (block matching).

    Cost of a pixel pair = sum of the per-pixel Hamming distances over a ``window``×``window``
    support region around it, divided by its largest possible value, 24 bits × window² (600 for
    the default 5×5). Window cells outside the image repeat the nearest border cell; cells whose
    partner pixel is outside the image count 24 bits.
    """

    Config = CensusBMConfig
    config: CensusBMConfig

    def compute(
        self, left: np.ndarray, right: np.ndarray, max_disparity: int, view: str
    ) -> np.ndarray:
        """(D, H, W) float32 costs in [0, 1]; 1.0 where the partner pixel is outside the image.

        See :meth:`Matcher.compute` for the arguments.
        """
        ref, other, step = census_views(left, right, view)
        height, width = ref.shape
        # Allocated by numpy, not inside the kernel: numpy asks the kernel for huge pages on
        # large arrays, which makes first-touch page faults of the volume several times cheaper.
        volume = np.empty((int(max_disparity), height, width), np.float32)
        _block_kernel(ref, other, step, self.config.window // 2, volume)
        return volume

"""Speckle filter: drop small islands of disparity that agree with nothing around them.

A speckle is a connected region of pixels (4-neighbours whose disparities differ by at most
``max_range``) of at most ``max_size`` pixels. Wrong disparities tend to come as such islands
(a repeated pattern, a texture-less patch, an occlusion border), right ones as parts of large
smooth surfaces. stereo_image_proc calls the two parameters ``speckle_size`` and
``speckle_range``, after OpenCV's ``filterSpeckles``.

Applied to the pixels a confidence threshold keeps, the filter sees what the network cannot:
CVA-Net judges a 13×13 neighbourhood of the cost volume, the filter whole regions of the
kept disparity map. On the develop split it removes wrong disparities that the threshold
keeps (README, *Speckle filter*).
"""

from __future__ import annotations

import math

from numba import njit
import numpy as np

from cva_confidence_ros.checks import is_int, is_real
from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.matching.disparity import check_disparity

__all__ = ['remove_speckles']


# One pass over the image; every kept pixel is queued once. ``flags`` holds 0 (not kept or in a
# speckle), 1 (kept, in no region yet) and 2 (in a region); flat indices keep the inner loop
# short. A region is grown to its end even after it is known to be large, so that none of its
# pixels seeds a second, smaller one.
@njit(cache=True)
def _remove_speckles(
    disparity: np.ndarray, flags: np.ndarray, max_size: int, max_range: float
) -> None:
    height, width = disparity.shape
    count = height * width
    values = disparity.ravel()
    state = flags.ravel()
    region = np.empty(count, np.int32)  # the queue and, once grown, the region's pixels
    for seed in range(count):
        if state[seed] != 1:
            continue
        state[seed] = 2
        region[0] = seed
        size = 1
        head = 0
        while head < size:
            index = region[head]
            head += 1
            value = values[index]
            x = index % width
            for step in range(4):
                if step == 0:
                    if x == 0:
                        continue
                    other = index - 1
                elif step == 1:
                    if x == width - 1:
                        continue
                    other = index + 1
                elif step == 2:
                    if index < width:
                        continue
                    other = index - width
                else:
                    other = index + width
                    if other >= count:
                        continue
                if state[other] == 1 and abs(values[other] - value) <= max_range:
                    state[other] = 2
                    region[size] = other
                    size += 1
        if size <= max_size:
            for i in range(size):
                state[region[i]] = 0


def remove_speckles(
    disparity: np.ndarray,
    keep: np.ndarray | None = None,
    max_size: int = 100,
    max_range: float = 1.0,
) -> np.ndarray:
    """The pixels of ``keep`` that do not lie in a speckle of ``disparity``.

    Regions are grown over the pixels of ``keep`` alone (4-neighbours, disparities at most
    ``max_range`` apart, compared in float32, no rounding); a region of ``max_size`` pixels or
    fewer is dropped. So a pixel dropped by a confidence threshold splits regions, and a
    confident island in an unconfident surround counts as small.

    Args:
        disparity: (H, W) float disparity (NaN = none).
        keep: (H, W) bool, the pixels to consider (e.g. confidence ≥ threshold); None = every
            finite disparity. Pixels with a non-finite disparity are never kept.
        max_size: Largest region that is dropped, in pixels (≥ 0; 0 returns ``keep``).
        max_range: Largest disparity step between two neighbours of one region, in pixels
            (finite, ≥ 0).

    Returns:
        (H, W) bool: ``keep`` (and finite disparity) without the speckles.

    Raises:
        InputError: ``disparity`` not a non-empty 2-D numeric array, ``keep`` not a bool array
            of its shape.
        ConfigError: ``max_size`` not an integer ≥ 0, ``max_range`` not a finite number ≥ 0.
    """
    values = check_disparity('disparity', disparity)
    if keep is None:
        mask = np.isfinite(values)
    else:
        if not isinstance(keep, np.ndarray) or keep.dtype != np.bool_:
            got = keep.dtype if isinstance(keep, np.ndarray) else type(keep).__name__
            raise InputError(f'keep must be a bool numpy array; got {got}')
        if keep.shape != values.shape:
            raise InputError(
                f'keep must have the shape of disparity {values.shape}; got {keep.shape}'
            )
        mask = keep & np.isfinite(values)
    if not is_int(max_size) or max_size < 0:
        raise ConfigError(f'max_size must be an integer ≥ 0; got {max_size!r}')
    if not is_real(max_range) or not (math.isfinite(max_range) and max_range >= 0):
        raise ConfigError(f'max_range must be a finite number ≥ 0; got {max_range!r}')
    if max_size == 0:
        return mask
    # C order: the kernel works on flat views, and ravel() of a Fortran-ordered array (a
    # transposed disparity map gives one) is a copy, whose updates would be lost.
    flags = mask.astype(np.uint8, order='C')
    # No region is larger than the image: a larger max_size (10**20 for 'no limit') means the
    # same, and one beyond int64 stopped numba's typing with a TypingError.
    size = min(int(max_size), values.size)
    _remove_speckles(np.ascontiguousarray(values), flags, size, float(max_range))
    return flags != 0

"""Disparity from a cost volume (winner-takes-all) and the left–right consistency check."""

from __future__ import annotations

import math

from numba import njit
import numpy as np

from cva_confidence_ros.checks import is_real
from cva_confidence_ros.errors import ConfigError, InputError

__all__ = ['check_cost_volume', 'check_disparity', 'left_right_check', 'wta_disparity']


# Serial: the scan is memory-bound, and parallel kernels compile far slower. No fastmath, so
# that the NaN test survives optimisation. The planes are visited in memory order, with the
# running minimum of the whole image kept, so that the volume streams through once.
@njit(cache=True)
def _argmin_depth(volume: np.ndarray, out: np.ndarray) -> bool | np.bool_:
    depth, height, width = volume.shape
    best = volume[0].copy()
    out[:, :] = 0.0
    nan_seen = np.zeros(width, np.uint8)
    for y in range(height):
        row = best[y]
        for x in range(width):
            nan_seen[x] |= row[x] != row[x]
    for d in range(1, depth):
        value_d = np.float32(d)
        for y in range(height):
            row = volume[d, y]
            low = best[y]
            index = out[y]
            for x in range(width):
                value = row[x]
                nan_seen[x] |= value != value
                # strict '<' keeps the smallest disparity among equal costs, like np.argmin
                smaller = value < low[x]
                low[x] = value if smaller else low[x]
                index[x] = value_d if smaller else index[x]
    return nan_seen.any()


def check_cost_volume(cost_volume: object) -> np.ndarray:
    """A non-empty (D, H, W) float array as C-contiguous float32, or float64 when it has 64 bits
    or more (no copy if it is one of them).

    Raises:
        InputError: Not a numpy array, not 3-D, empty, or not float.
    """
    if not isinstance(cost_volume, np.ndarray):
        raise InputError(
            f'cost_volume must be a (D, H, W) numpy array; got {type(cost_volume).__name__}'
        )
    if cost_volume.ndim != 3 or 0 in cost_volume.shape:
        raise InputError(
            f'cost_volume must be a non-empty (D, H, W) array; got shape {cost_volume.shape}'
        )
    if cost_volume.dtype.kind != 'f':
        raise InputError(f'cost_volume must be float (float32); got dtype {cost_volume.dtype}')
    # float64 stays float64: rounded to float32, costs a hair apart became equal (the winner
    # went to the smaller d, a sub-pixel curve went flat) and costs beyond 3.4e38 became inf.
    dtype = np.float64 if cost_volume.dtype.itemsize >= 8 else np.float32
    return np.ascontiguousarray(cost_volume, dtype=dtype)


def wta_disparity(cost_volume: np.ndarray) -> np.ndarray:
    """Winner-takes-all disparity: the d of the lowest cost of every pixel.

    Args:
        cost_volume: (D, H, W) float cost volume (float32 and float64 are used without a
            copy, each in its own precision), lower = better. Ties go to the smallest d.

    Returns:
        (H, W) float32 disparities, integers in [0, D − 1].

    Raises:
        InputError: Not a non-empty 3-D float array, or NaN costs.
    """
    volume = check_cost_volume(cost_volume)
    disparity = np.empty(volume.shape[1:], np.float32)
    if _argmin_depth(volume, disparity):
        nans = int(np.count_nonzero(np.isnan(volume)))
        raise InputError(f'cost_volume must not contain NaN; got {nans} NaN entries')
    return disparity


def check_disparity(name: str, disparity: object) -> np.ndarray:
    """A non-empty (H, W) float or integer array as float32 (no copy if it is one).

    Raises:
        InputError: Not a numpy array, not 2-D, empty, or of another dtype; ``name`` says
            which argument.
    """
    if not isinstance(disparity, np.ndarray):
        raise InputError(f'{name} must be an (H, W) numpy array; got {type(disparity).__name__}')
    if disparity.ndim != 2 or disparity.size == 0:
        raise InputError(f'{name} must be a non-empty (H, W) array; got shape {disparity.shape}')
    if disparity.dtype.kind not in 'fiu':
        raise InputError(f'{name} must be a float (or integer) array; got dtype {disparity.dtype}')
    return disparity.astype(np.float32, copy=False)


def left_right_check(
    disp_left: np.ndarray, disp_right: np.ndarray, max_diff: float = 1.0
) -> np.ndarray:
    """Left–right consistency of two disparity maps.

    A left pixel (y, x) with disparity d is consistent when its partner column
    x_r = x − round(d) lies in the image and |d − disp_right[y, x_r]| ≤ ``max_diff``.

    Args:
        disp_left: (H, W) float disparity of the left view (NaN = unknown).
        disp_right: (H, W) float disparity of the right view (``view='right'`` volume).
        max_diff: Largest accepted difference in pixels (finite, ≥ 0).

    Returns:
        (H, W) bool, True = consistent; False where either disparity is NaN/inf or the partner
        column is outside the image.

    Raises:
        InputError: Not 2-D numeric arrays, or different shapes.
        ConfigError: ``max_diff`` negative or not finite.
    """
    left = check_disparity('disp_left', disp_left)
    right = check_disparity('disp_right', disp_right)
    if left.shape != right.shape:
        raise InputError(
            f'disp_left and disp_right must have the same shape; got {left.shape} and '
            f'{right.shape}'
        )
    # A numpy complex is an np.number: its imaginary part was dropped with a ComplexWarning.
    if not is_real(max_diff):
        raise ConfigError(f'max_diff must be a real number; got {type(max_diff).__name__}')
    try:
        tolerance = float(max_diff)
    except OverflowError:  # an int beyond float64: no finite tolerance
        tolerance = math.inf
    if not math.isfinite(tolerance) or tolerance < 0:
        raise ConfigError(f'max_diff must be finite and ≥ 0; got {max_diff}')
    height, width = left.shape
    finite = np.isfinite(left)
    columns = np.arange(width, dtype=np.float64)[None, :] - np.rint(np.where(finite, left, 0.0))
    inside = finite & (columns >= 0) & (columns < width)
    partner = np.clip(columns, 0, width - 1).astype(np.intp)
    rows = np.arange(height)[:, None]
    matched = right[rows, partner]
    with np.errstate(invalid='ignore'):
        close = np.abs(left - matched) <= tolerance
    return inside & np.isfinite(matched) & close

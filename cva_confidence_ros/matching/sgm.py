"""Semi-Global Matching (Hirschmüller 2008) over 8 paths, as numba kernels.

For each path direction r the aggregated cost follows the recursion

    L_r(p, d) = C(p, d) + min(L_r(p − r, d), L_r(p − r, d ± 1) + P1, min_k L_r(p − r, k) + P2)
                − min_k L_r(p − r, k),

starting with L_r(p, d) = C(p, d) where p − r leaves the image, and the result is
S(p, d) = Σ_r L_r(p, d) over the 8 directions (horizontal, vertical and both diagonals, both
ways). Since the middle term is at most min_k L_r(p − r, k) + P2, every L_r ≤ Cmax + P2 and
S ≤ 8·(Cmax + P2).

Internally costs are (H, W, D), so that the recursion runs along contiguous disparities, and
path costs are int16 (p2 is bounded so that they fit), so that it runs 16 disparities per AVX2
instruction. Like OpenCV's SGBM the 8 paths are run as two sweeps over the image: top-down and
left-to-right for the 4 paths arriving from the left and from above, bottom-up and right-to-left
for the other 4. The two sweeps run in parallel into separate uint16 accumulators, which a
final pass adds, transposes to (D, H, W) and scales.
"""

from __future__ import annotations

from numba import njit, prange
import numpy as np

from cva_confidence_ros.errors import InputError
from cva_confidence_ros.matching.census import CENSUS_BITS, hamming_cost_volume

__all__ = ['SGM_PATHS', 'sgm_aggregate']

#: Number of path directions that are summed.
SGM_PATHS = 8

# Stands in for L at d = −1 and d = D so the recursion needs no bounds tests. Since
# 8·(Cmax + p2) ≤ 65535 (so Cmax + 2·p2 < 16384), every L_r, L_r + p2 and _OUTSIDE + p1 fits
# int16.
_OUTSIDE = np.int16(1 << 14)
# S ≤ 8·(Cmax + P2) must fit the uint16 accumulators (their sum is taken in float32).
MAX_ACCUMULATED = np.iinfo(np.uint16).max


@njit(cache=True, fastmath=True, inline='always')
def _start(cost: np.ndarray, out: np.ndarray) -> int:
    """First pixel of a path: L = C. ``out`` has D + 2 cells; cells 0 and D + 1 stay outside."""
    depth = cost.shape[0]
    inner = out[1:depth + 1]
    best = np.int32(_OUTSIDE)
    for d in range(depth):
        value = np.int16(cost[d])
        inner[d] = value
        best = min(best, value)
    return best


@njit(cache=True, fastmath=True, inline='always')
def _step(
    cost: np.ndarray, prev: np.ndarray, prev_min: int, p1: np.int16, p2: np.int16,
    out: np.ndarray,
) -> int:
    """One path step: ``out`` = L_r(p, ·) from ``prev`` = L_r(p − r, ·); returns min_k of it.

    ``prev`` and ``out`` have D + 2 cells; cells 0 and D + 1 hold :data:`_OUTSIDE`.
    """
    depth = cost.shape[0]
    below = prev[0:depth]
    same = prev[1:depth + 1]
    above = prev[2:depth + 2]
    inner = out[1:depth + 1]
    base = np.int16(prev_min)
    jump = np.int16(base + p2)
    best = np.int16(_OUTSIDE)
    for d in range(depth):
        value = min(same[d], np.int16(min(below[d], above[d]) + p1), jump)
        value = np.int16(np.int16(cost[d]) + np.int16(value - base))
        inner[d] = value
        best = min(best, value)
    return best


@njit(cache=True, fastmath=True)
def _sweep(
    costs: np.ndarray, p1: np.int16, p2: np.int16, backward: bool, acc: np.ndarray
) -> None:
    """acc = sum of 4 paths: those arriving from the left and from the row above (forward
    sweep: top-down, left to right) or from the right and the row below (backward sweep)."""
    height, width, depth = costs.shape
    sign = -1 if backward else 1
    # lines[parity, path, x]: L of the previous / current row for the paths arriving from
    # (y ∓ 1, x), (y ∓ 1, x ∓ 1) and (y ∓ 1, x ± 1); along[parity]: the in-row path.
    lines = np.full((2, 3, width, depth + 2), _OUTSIDE, np.int16)
    minima = np.empty((2, 3, width), np.int32)
    along = np.full((2, depth + 2), _OUTSIDE, np.int16)
    for i in range(height):
        y = height - 1 - i if backward else i
        cur = i & 1
        prev = 1 - cur
        along_min = 0
        for j in range(width):
            x = width - 1 - j if backward else j
            cost = costs[y, x]
            # the in-row path alternates its two buffers per pixel, the others per row
            here = j & 1
            if j == 0:
                along_min = _start(cost, along[here])
            else:
                along_min = _step(cost, along[1 - here], along_min, p1, p2, along[here])
            if i == 0:
                minima[cur, 0, x] = _start(cost, lines[cur, 0, x])
            else:
                minima[cur, 0, x] = _step(
                    cost, lines[prev, 0, x], minima[prev, 0, x], p1, p2, lines[cur, 0, x]
                )
            source = x - sign
            if i == 0 or j == 0:
                minima[cur, 1, x] = _start(cost, lines[cur, 1, x])
            else:
                minima[cur, 1, x] = _step(
                    cost, lines[prev, 1, source], minima[prev, 1, source], p1, p2,
                    lines[cur, 1, x],
                )
            source = x + sign
            if i == 0 or j == width - 1:
                minima[cur, 2, x] = _start(cost, lines[cur, 2, x])
            else:
                minima[cur, 2, x] = _step(
                    cost, lines[prev, 2, source], minima[prev, 2, source], p1, p2,
                    lines[cur, 2, x],
                )
            target = acc[y, x]
            path_a = along[here, 1:depth + 1]
            path_b = lines[cur, 0, x, 1:depth + 1]
            path_c = lines[cur, 1, x, 1:depth + 1]
            path_d = lines[cur, 2, x, 1:depth + 1]
            for d in range(depth):
                target[d] = np.uint16(path_a[d]) + np.uint16(path_b[d]) + np.uint16(
                    path_c[d]
                ) + np.uint16(path_d[d])


@njit(cache=True, parallel=True, fastmath=True)
def _both_sweeps(costs: np.ndarray, p1: np.int16, p2: np.int16, acc: np.ndarray) -> None:
    # The two sweeps are independent; each writes its own accumulator.
    for task in prange(2):
        _sweep(costs, p1, p2, task == 1, acc[task])


@njit(cache=True, parallel=True, fastmath=True)
def _combine(acc: np.ndarray, scale: np.float32, step: int, volume: np.ndarray) -> None:
    """volume[d, y, x] = (acc[0] + acc[1])[y, x, d] · scale, 1.0 where x + step·d is outside."""
    _, height, width, depth = acc.shape
    for y in prange(height):
        forward = acc[0, y]
        backward = acc[1, y]
        for d in range(depth):
            row = volume[d, y]
            for x in range(width):
                row[x] = np.float32(np.int32(forward[x, d]) + np.int32(backward[x, d])) * scale
            if step < 0:
                for x in range(min(d, width)):
                    row[x] = 1.0
            else:
                for x in range(max(width - d, 0), width):
                    row[x] = 1.0


def aggregate_hwd(costs: np.ndarray, p1: int, p2: int) -> np.ndarray:
    """The two sweeps over (H, W, D) uint8 costs.

    Args:
        costs: (H, W, D) uint8 matching costs C, C-contiguous.
        p1: Penalty of a disparity change of 1 (0 ≤ p1 ≤ p2).
        p2: Penalty of a larger change; 8·(max C + p2) ≤ 65535.

    Returns:
        (2, H, W, D) uint16 partial sums (forward sweep, backward sweep); S is their sum.
    """
    height, width, depth = costs.shape
    acc = np.empty((2, height, width, depth), np.uint16)
    _both_sweeps(costs, np.int16(p1), np.int16(p2), acc)
    return acc


def census_sgm_volume(
    codes_ref: np.ndarray, codes_other: np.ndarray, depth: int, step: int, p1: int, p2: int
) -> np.ndarray:
    """SGM over census Hamming costs, normalised to [0, 1] (the engine of ``census_sgm``).

    Args:
        codes_ref: (H, W) uint32 census codes of the reference view.
        codes_other: (H, W) uint32 census codes of the other view.
        depth: D.
        step: −1 when the partner of x is x − d (left reference), +1 when it is x + d.
        p1: Penalty of a disparity change of 1 (0 ≤ p1 ≤ p2).
        p2: Penalty of a larger change (8·(24 + p2) ≤ 65535).

    Returns:
        (D, H, W) float32 S / (8·(24 + p2)), 1.0 where the partner pixel is outside the image.
    """
    costs = hamming_cost_volume(codes_ref, codes_other, depth, step, layout='hwd')
    acc = aggregate_hwd(costs, p1, p2)
    del costs
    height, width = codes_ref.shape
    # numpy (not the kernel) allocates the volume: it requests huge pages for large arrays,
    # which makes the first-touch page faults several times cheaper.
    volume = np.empty((depth, height, width), np.float32)
    scale = np.float32(1.0 / (SGM_PATHS * (CENSUS_BITS + p2)))
    _combine(acc, scale, int(step), volume)
    return volume


def sgm_aggregate(costs: np.ndarray, p1: int, p2: int) -> np.ndarray:
    """Sum of the 8 SGM path costs of a cost volume (unnormalised).

    Args:
        costs: (D, H, W) integer matching costs in [0, 255].
        p1: Penalty of a disparity change of 1 (≥ 0).
        p2: Penalty of a larger change (≥ p1).

    Returns:
        (D, H, W) int32 S = Σ_r L_r over the 8 directions, each L_r ≤ max C + p2.

    Raises:
        InputError: Not a 3-D integer array in [0, 255], or penalties whose sum bound
            8·(max C + p2) does not fit the uint16 accumulator.
    """
    costs = np.asarray(costs)
    if costs.ndim != 3 or costs.dtype.kind not in 'iu' or 0 in costs.shape:
        raise InputError(
            f'sgm_aggregate expects a non-empty (D, H, W) integer array; got shape '
            f'{costs.shape} and dtype {costs.dtype}'
        )
    if costs.min() < 0 or costs.max() > 255:
        raise InputError(
            f'sgm_aggregate expects costs in [0, 255]; got [{costs.min()}, {costs.max()}]'
        )
    if not 0 <= p1 <= p2:
        raise InputError(f'sgm_aggregate expects 0 ≤ p1 ≤ p2; got p1={p1}, p2={p2}')
    bound = SGM_PATHS * (int(costs.max()) + int(p2))
    if bound > MAX_ACCUMULATED:
        raise InputError(
            f'8·(max cost + p2) must be ≤ {MAX_ACCUMULATED}; got {bound} (p2={p2})'
        )
    hwd = np.ascontiguousarray(costs.transpose(1, 2, 0), dtype=np.uint8)
    acc = aggregate_hwd(hwd, int(p1), int(p2))
    total = acc[0].astype(np.int32) + acc[1]
    return np.ascontiguousarray(total.transpose(2, 0, 1))

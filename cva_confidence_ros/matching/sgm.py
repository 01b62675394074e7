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
for the other 4. The two sweeps run in parallel in two phases: first each covers its half of
the rows and stores the row sums (uint16), then each goes on into the other's half and adds,
transposes to (D, H, W) and scales finished rows while they are still in cache.
"""

from __future__ import annotations

from collections.abc import Iterator
import contextlib
import threading

from numba import njit, prange
import numpy as np

from cva_confidence_ros.checks import is_int
from cva_confidence_ros.errors import InputError
from cva_confidence_ros.matching.census import CENSUS_BITS, hamming_cost_volume

__all__ = ['SGM_PATHS', 'preserved_scratch', 'sgm_aggregate']

#: Number of path directions that are summed.
SGM_PATHS = 8

# Stands in for L at d = −1 and d = D so the recursion needs no bounds tests. Since
# 8·(Cmax + p2) ≤ 65535 (so Cmax + 2·p2 < 16384), every L_r, L_r + p2 and _OUTSIDE + p1 fits
# int16.
_OUTSIDE = np.int16(1 << 14)
# The bound S ≤ 8·(Cmax + P2) is kept within uint16 (the stored 4-path sums are half of it).
MAX_ACCUMULATED = np.iinfo(np.uint16).max


@njit(cache=True, fastmath=True, inline='always')
def _start(cost: np.ndarray, out: np.ndarray) -> np.signedinteger:
    """First pixel of a path: L = C. ``out`` has D + 2 cells; cells 0 and D + 1 stay outside."""
    depth = cost.shape[0]
    inner = out[1:depth + 1]
    best: np.signedinteger = np.int32(_OUTSIDE)
    for d in range(depth):
        value = np.int16(cost[d])
        inner[d] = value
        best = min(best, value)
    return best


@njit(cache=True, fastmath=True, inline='always')
def _step(
    cost: np.ndarray, prev: np.ndarray, prev_min: int | np.signedinteger, p1: np.int16,
    p2: np.int16, out: np.ndarray,
) -> np.int16:
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
def _sweep_rows(
    costs: np.ndarray,
    p1: np.int16,
    p2: np.int16,
    backward: bool,
    first: int,
    stop: int,
    lines: np.ndarray,
    minima: np.ndarray,
    acc: np.ndarray,
    combine: bool,
    volume: np.ndarray,
    scale: np.float32,
    step: int,
) -> None:
    """Rows ``first`` ≤ i < ``stop`` of one sweep: the 4 paths arriving from the left and from
    the row above (forward: y = i, left to right) or from the right and the row below
    (backward: y = H − 1 − i, right to left).

    The sum of the 4 paths of row y goes to ``acc[y]``, or, with ``combine``, is added to
    ``acc[y]`` (the other sweep's sum there) and written as ``volume[:, y, :]`` scaled by
    ``scale``, with 1.0 where the partner x + step·d is outside the image (step 0: nowhere).
    ``lines`` (2, 3, W, D + 2) int16 and ``minima`` (2, 3, W) carry the path costs of the
    last row from one call to the next.
    """
    height, width, depth = costs.shape
    sign = -1 if backward else 1
    # lines[parity, path, x]: L of the previous / current row for the paths arriving from
    # (y ∓ 1, x), (y ∓ 1, x ∓ 1) and (y ∓ 1, x ± 1); along[parity]: the in-row path.
    along = np.full((2, depth + 2), _OUTSIDE, np.int16)
    row_sum = np.empty((width if combine else 0, depth), np.uint16)
    for i in range(first, stop):
        y = height - 1 - i if backward else i
        cur = i & 1
        prev = 1 - cur
        along_min: int | np.signedinteger = 0
        sums = row_sum if combine else acc[y]
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
            target = sums[x]
            path_a = along[here, 1:depth + 1]
            path_b = lines[cur, 0, x, 1:depth + 1]
            path_c = lines[cur, 1, x, 1:depth + 1]
            path_d = lines[cur, 2, x, 1:depth + 1]
            for d in range(depth):
                target[d] = np.uint16(path_a[d]) + np.uint16(path_b[d]) + np.uint16(
                    path_c[d]
                ) + np.uint16(path_d[d])
        if combine:
            other = acc[y]
            for d in range(depth):
                plane_row = volume[d, y]
                for x in range(width):
                    total = np.int32(row_sum[x, d]) + np.int32(other[x, d])
                    plane_row[x] = np.float32(total) * scale
                if step < 0:
                    for x in range(min(d, width)):
                        plane_row[x] = 1.0
                elif step > 0:
                    for x in range(max(width - d, 0), width):
                        plane_row[x] = 1.0


@njit(cache=True, parallel=True, fastmath=True)
def _sweep_phase(
    costs: np.ndarray,
    p1: np.int16,
    p2: np.int16,
    second: bool,
    lines: np.ndarray,
    minima: np.ndarray,
    acc: np.ndarray,
    volume: np.ndarray,
    scale: np.float32,
    step: int,
) -> None:
    """One of the two phases in which the forward and the backward sweep run side by side.

    Phase 1: the forward sweep covers the top half of the rows and the backward sweep the
    bottom half, each storing its row sums in ``acc``. Phase 2: each sweep goes on into the
    half the other has done, adds that half's stored sums to its own fresh ones and writes the
    finished rows of ``volume``, so no separate pass over a second accumulator is needed.
    """
    height = costs.shape[0]
    half = (height + 1) // 2
    for task in prange(2):
        backward = task == 1
        own = height - half if backward else half
        first, stop = (own, height) if second else (0, own)
        _sweep_rows(
            costs, p1, p2, backward, first, stop, lines[task], minima[task], acc, second,
            volume, scale, step,
        )


class _Scratch(threading.local):
    """Per-thread work arrays of the last image size, reused from frame to frame.

    A stream of same-sized frames then allocates (and page-faults) only the returned volume,
    not the Hamming costs, the accumulator and the path buffers (≈ 120 MB at 640×480,
    D = 128), which stay resident between frames of the same thread.
    """

    def __init__(self) -> None:
        self.arrays: dict[str, np.ndarray] = {}

    def get(
        self, name: str, shape: tuple[int, ...], dtype: type, fill: int | None = None
    ) -> np.ndarray:
        """An array of this shape and dtype; ``fill`` only applies when it is new."""
        array = self.arrays.get(name)
        if array is None or array.shape != shape or array.dtype != dtype:
            self.arrays.pop(name, None)  # free the old one before allocating the new one
            array = np.empty(shape, dtype) if fill is None else np.full(shape, fill, dtype)
            self.arrays[name] = array
        return array


_SCRATCH = _Scratch()


@contextlib.contextmanager
def preserved_scratch() -> Iterator[None]:
    """Keep this thread's work arrays across the block (a warm-up on a small image), so that
    the next full-size frame finds the ones of its own size and does not allocate them again."""
    saved = dict(_SCRATCH.arrays)
    try:
        yield
    finally:
        _SCRATCH.arrays = saved


def aggregate_hwd(
    costs: np.ndarray,
    p1: int,
    p2: int,
    volume: np.ndarray,
    scale: float = 1.0,
    step: int = 0,
) -> np.ndarray:
    """8-path SGM of (H, W, D) uint8 costs, written to a (D, H, W) float32 volume.

    Args:
        costs: (H, W, D) uint8 matching costs C, C-contiguous.
        p1: Penalty of a disparity change of 1 (0 ≤ p1 ≤ p2).
        p2: Penalty of a larger change; 8·(max C + p2) ≤ 65535.
        volume: C-contiguous (D, H, W) float32 array that receives S · ``scale``.
        scale: Factor applied to S.
        step: −1 (left reference) or +1 (right reference): entries whose partner x + step·d
            is outside the image are set to 1.0; 0 leaves every entry S · ``scale``.

    Returns:
        ``volume``.
    """
    height, width, depth = costs.shape
    # The padding cells (d = −1 and d = D) of the path buffers are never written, so a
    # reused buffer keeps them at _OUTSIDE.
    lines = _SCRATCH.get('lines', (2, 2, 3, width, depth + 2), np.int16, fill=int(_OUTSIDE))
    minima = _SCRATCH.get('minima', (2, 2, 3, width), np.int32)
    acc = _SCRATCH.get('acc', (height, width, depth), np.uint16)
    pen1, pen2 = np.int16(p1), np.int16(p2)
    scale32, step_int = np.float32(scale), int(step)
    _sweep_phase(costs, pen1, pen2, False, lines, minima, acc, volume, scale32, step_int)
    _sweep_phase(costs, pen1, pen2, True, lines, minima, acc, volume, scale32, step_int)
    return volume


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
    height, width = codes_ref.shape
    costs = _SCRATCH.get('costs', (height, width, depth), np.uint8)
    hamming_cost_volume(codes_ref, codes_other, depth, step, layout='hwd', out=costs)
    # numpy (not the kernel) allocates the volume: it requests huge pages for large arrays,
    # which makes the first-touch page faults several times cheaper.
    volume = np.empty((depth, height, width), np.float32)
    # int(): 8·(24 + p2) in a narrow numpy integer type of p2 would wrap around
    scale = 1.0 / (SGM_PATHS * (CENSUS_BITS + int(p2)))
    return aggregate_hwd(costs, p1, p2, volume, scale, step)


def sgm_aggregate(costs: np.ndarray, p1: int, p2: int) -> np.ndarray:
    """Sum of the 8 SGM path costs of a cost volume (unnormalised).

    Args:
        costs: (D, H, W) integer matching costs in [0, 255].
        p1: Penalty of a disparity change of 1 (≥ 0).
        p2: Penalty of a larger change (≥ p1).

    Returns:
        (D, H, W) int32 S = Σ_r L_r over the 8 directions, each L_r ≤ max C + p2.

    Raises:
        InputError: Not a 3-D integer array in [0, 255], penalties that are not integers
            with 0 ≤ p1 ≤ p2, or penalties whose sum bound
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
    # int16 penalties: a fractional one would be truncated without a word.
    if not is_int(p1) or not is_int(p2):
        raise InputError(f'sgm_aggregate expects integer penalties; got p1={p1!r}, p2={p2!r}')
    if not 0 <= p1 <= p2:
        raise InputError(f'sgm_aggregate expects 0 ≤ p1 ≤ p2; got p1={p1}, p2={p2}')
    bound = SGM_PATHS * (int(costs.max()) + int(p2))
    if bound > MAX_ACCUMULATED:
        raise InputError(
            f'8·(max cost + p2) must be ≤ {MAX_ACCUMULATED}; got {bound} (p2={p2})'
        )
    hwd = np.ascontiguousarray(costs.transpose(1, 2, 0), dtype=np.uint8)
    total = np.empty(costs.shape, np.float32)
    # S < 2**24, so float32 holds it exactly
    aggregate_hwd(hwd, int(p1), int(p2), total)
    return total.astype(np.int32)

"""5×5 census transform and per-pixel Hamming matching costs (numba kernels).

The census code of a pixel has one bit per neighbour of its 5×5 window (24 bits): the bit is 1
where the neighbour is darker than the centre. Neighbours are taken in raster order (row by row,
left to right, the centre skipped) and the first neighbour is the most significant bit (bit 23).
Pixels outside the image take the value of the nearest border pixel (replicate padding).
"""

from __future__ import annotations

from typing import Any

from numba import njit, types
from numba.extending import intrinsic
import numpy as np

from cva_confidence_ros.checks import is_int
from cva_confidence_ros.errors import InputError
from cva_confidence_ros.matching.base import to_gray

__all__ = [
    'CENSUS_BITS',
    'census_transform',
    'hamming_cost_volume',
    'hamming_distance',
]

CENSUS_RADIUS = 2
#: Bits of a 5×5 census code (the centre is not compared with itself).
CENSUS_BITS = (2 * CENSUS_RADIUS + 1) ** 2 - 1


@intrinsic
def popcount(typingctx: Any, value: Any) -> tuple[Any, Any]:
    """Number of set bits of a uint32 (LLVM ``ctpop``: one instruction, or a nibble lookup
    that vectorises, where the CPU has no population count)."""
    signature = types.uint32(types.uint32)

    def codegen(context: Any, builder: Any, sig: Any, args: Any) -> Any:
        return builder.ctpop(args[0])

    return signature, codegen


# Serial: a 640×480 census takes a few milliseconds, and parallel kernels compile far slower.
@njit(cache=True)
def _census_kernel(gray: np.ndarray) -> np.ndarray:
    height, width = gray.shape
    codes = np.empty((height, width), np.uint32)
    for y in range(height):
        for x in range(width):
            centre = gray[y, x]
            code = 0
            for dy in range(-CENSUS_RADIUS, CENSUS_RADIUS + 1):
                yy = min(max(y + dy, 0), height - 1)
                for dx in range(-CENSUS_RADIUS, CENSUS_RADIUS + 1):
                    if dy == 0 and dx == 0:
                        continue
                    xx = min(max(x + dx, 0), width - 1)
                    code = (code << 1) | (1 if gray[yy, xx] < centre else 0)
            codes[y, x] = code
    return codes


def census_transform(gray: np.ndarray) -> np.ndarray:
    """5×5 census transform of a gray image.

    Args:
        gray: (H, W) uint8 image.

    Returns:
        (H, W) uint32 codes in [0, 2**24): bit 23 − k is 1 where the k-th neighbour (raster
        order, centre skipped) is strictly darker than the centre; replicate padding at borders.

    Raises:
        InputError: Not a non-empty 2-D uint8 array.
    """
    if not isinstance(gray, np.ndarray) or gray.ndim != 2 or gray.dtype != np.uint8:
        got = (gray.shape, gray.dtype) if isinstance(gray, np.ndarray) else type(gray).__name__
        raise InputError(f'census_transform expects an (H, W) uint8 array; got {got}')
    if gray.size == 0:
        raise InputError(f'census_transform expects a non-empty image; got shape {gray.shape}')
    return _census_kernel(np.ascontiguousarray(gray))


def census_views(
    left: np.ndarray, right: np.ndarray, view: str
) -> tuple[np.ndarray, np.ndarray, int]:
    """Census codes of the reference and the other image, and the partner-column step.

    Args:
        left: (H, W) or (H, W, 3) uint8 left image.
        right: Same shape as ``left``.
        view: ``'left'`` (partner at x − d, step −1) or ``'right'`` (partner at x + d, step 1).

    Returns:
        ``(ref, other, step)``: (H, W) uint32 census codes of both images and the step.
    """
    codes_left = census_transform(to_gray(left))
    codes_right = census_transform(to_gray(right))
    if view == 'left':
        return codes_left, codes_right, -1
    return codes_right, codes_left, 1


def _check_codes(name: str, codes: object) -> np.ndarray:
    """``codes`` as an array of integers in [0, 2**24) (census codes), or InputError.

    Codes with more bits than a census code would give Hamming costs above
    :data:`CENSUS_BITS` (worse than a partner outside the image, and past the bound SGM's
    accumulator is sized for); float or negative ones would be cast to uint32 silently.
    """
    array = np.asarray(codes)
    if array.dtype.kind not in 'iu':
        raise InputError(f'{name} must hold integer census codes; got dtype {array.dtype}')
    if array.size and (array.min() < 0 or array.max() >= 1 << CENSUS_BITS):
        raise InputError(
            f'{name} must hold census codes in [0, 2**{CENSUS_BITS}); got values in '
            f'[{array.min()}, {array.max()}]'
        )
    return array


def hamming_distance(code_a: np.ndarray, code_b: np.ndarray) -> np.ndarray:
    """Number of differing bits of two census code arrays (same shape), as uint8.

    Raises:
        InputError: Arrays of different shapes, or not census codes (integers in
            [0, 2**24)).
    """
    code_a, code_b = _check_codes('code_a', code_a), _check_codes('code_b', code_b)
    if code_a.shape != code_b.shape:
        raise InputError(
            f'code_a and code_b must have the same shape; got {code_a.shape} and {code_b.shape}'
        )
    xor = np.bitwise_xor(code_a.astype(np.uint32), code_b.astype(np.uint32))
    return _popcount_array(xor.ravel()).reshape(xor.shape)


@njit(cache=True)
def _popcount_array(values: np.ndarray) -> np.ndarray:
    out = np.empty(values.shape[0], np.uint8)
    for i in range(values.shape[0]):
        # numba's stubs type an intrinsic's call with the typing context as an argument
        out[i] = popcount(values[i])  # type: ignore[call-arg]
    return out


def check_depth_and_step(depth: int, step: int) -> None:
    """InputError unless ``depth`` is an integer ≥ 1 and ``step`` ±1: the cost kernels read
    the other view at x + step·d and do not check bounds."""
    if not is_int(depth) or depth < 1:
        raise InputError(f'depth must be an integer ≥ 1; got {depth!r}')
    if step not in (-1, 1):
        raise InputError(f'step must be -1 or 1; got {step!r}')


@njit(cache=True, inline='always')
def valid_range(width: int, disparity: int, step: int) -> tuple[int, int]:
    """[lo, hi) of the x whose partner x + step·d lies inside [0, width)."""
    if step < 0:
        return min(disparity, width), width
    return 0, max(width - disparity, 0)


@njit(cache=True, fastmath=True)
def _hamming_hwd_kernel(
    codes_ref: np.ndarray, codes_other: np.ndarray, step: int, costs: np.ndarray
) -> None:
    height, width, depth = costs.shape
    # The other view's codes of a row in the order the disparities visit them (reversed for
    # a left reference), so that the partners of x for d = 0, 1, … are contiguous.
    partners = np.empty(width, np.uint32)
    for y in range(height):
        for k in range(width):
            partners[k] = codes_other[y, width - 1 - k if step < 0 else k]
        for x in range(width):
            if step < 0:
                first, inside = width - 1 - x, min(depth, x + 1)
            else:
                first, inside = x, min(depth, width - x)
            ref = codes_ref[y, x]
            target = costs[y, x]
            row = partners[first:first + inside]
            for d in range(inside):
                # numba's stubs type an intrinsic's call with the typing context as an argument
                target[d] = popcount(ref ^ row[d])  # type: ignore[call-arg]
            for d in range(inside, depth):
                target[d] = CENSUS_BITS


def hamming_cost_volume(
    codes_ref: np.ndarray,
    codes_other: np.ndarray,
    depth: int,
    step: int,
    layout: str = 'dhw',
    out: np.ndarray | None = None,
) -> np.ndarray:
    """Per-pixel Hamming costs between reference codes and shifted partner codes.

    Args:
        codes_ref: (H, W) uint32 census codes of the reference view.
        codes_other: (H, W) uint32 census codes of the other view.
        depth: D, number of disparities.
        step: −1 when the partner of x is x − d (left reference), +1 when it is x + d (right).
        layout: ``'dhw'`` for a (D, H, W) result, ``'hwd'`` for (H, W, D) (what SGM uses).
        out: Optional C-contiguous (H, W, D) uint8 array to fill (``'hwd'`` layout only).

    Returns:
        uint8 Hamming distances in [0, 24]; 24 (:data:`CENSUS_BITS`) where the partner is
        outside the image.

    Raises:
        InputError: Code arrays that are not 2-D, differ in shape or hold other values than
            census codes (integers in [0, 2**24)), ``depth`` < 1, ``step`` not ±1, a bad
            ``layout`` or ``out``.
    """
    if layout not in ('dhw', 'hwd'):
        raise InputError(f"layout must be 'dhw' or 'hwd'; got {layout!r}")
    codes_ref = _check_codes('codes_ref', codes_ref)
    codes_other = _check_codes('codes_other', codes_other)
    # The kernel reads the other row at the reference's width: a narrower one would be read
    # past its end (numba does not check bounds) and give costs of whatever lies there.
    if codes_ref.ndim != 2 or codes_ref.shape != codes_other.shape:
        raise InputError(
            'codes_ref and codes_other must be (H, W) arrays of the same shape; got '
            f'{codes_ref.shape} and {codes_other.shape}'
        )
    check_depth_and_step(depth, step)
    height, width = codes_ref.shape
    shape = (height, width, int(depth))
    if out is not None and not isinstance(out, np.ndarray):
        # out.shape of a list or a tensor was an AttributeError (or a torch.Size)
        raise InputError(
            f'out must be a C-contiguous {shape} uint8 numpy array; got {type(out).__name__}'
        )
    if out is not None and (
        layout != 'hwd' or out.shape != shape or out.dtype != np.uint8
        or not out.flags['C_CONTIGUOUS']
    ):
        raise InputError(
            f'out must be a C-contiguous {shape} uint8 array with layout hwd; got '
            f'{out.shape} {out.dtype} with layout {layout}'
        )
    costs = np.empty(shape, np.uint8) if out is None else out
    _hamming_hwd_kernel(
        np.ascontiguousarray(codes_ref, np.uint32),
        np.ascontiguousarray(codes_other, np.uint32),
        int(step),
        costs,
    )
    if layout == 'hwd':
        return costs
    return np.ascontiguousarray(costs.transpose(2, 0, 1))

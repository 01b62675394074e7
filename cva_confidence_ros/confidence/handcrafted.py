"""Hand-crafted confidence measures computed from cost volumes and disparity maps.

Definitions follow Hu & Mordohai (TPAMI 2012), with the notation of a cost curve ``c(d)`` at a
pixel, its minimum ``c1`` at ``d1`` and its second-smallest value ``c2`` (the *naive* variant,
not restricted to local minima; ``c2 == c1`` when the minimum is attained twice):

* ``score``: matching score, ``-c1``.
* ``pkrn``: naive peak ratio, ``(c2 + eps) / (c1 + eps)``.
* ``mlm``: maximum likelihood measure, softmax of ``-c / (2 sigma^2)`` evaluated at ``d1``.
* ``lrd``: left-right difference, ``(c2 - c1) / (|c1 - min_d c_R(x - d1, d)| + eps)``.
* ``lrc``: left-right consistency, ``-|d_L(x) - d_R(x - round(d_L(x)))|``.

All are vectorised with numpy and process the volume in blocks of rows, so temporary arrays stay
small even for deep volumes. Higher values mean more confident.

Column 0 of a left-reference volume has a single candidate with a partner in the right image
(``d = 0``; the others are the matcher's out-of-image filler): its disparity is no matching
decision, and is wrong wherever the scene is not at infinity. ``score``, ``pkrn``, ``mlm`` and
``lrd`` give it their lowest value: the filler, the worst cost, made it the most distinct
minimum (on the develop split at D = 64, every ground-truth pixel, the rule takes Middlebury v3
Census-SGM from AUC ×10² 3.98 to 3.70 for PKRN and 6.52 to 6.15 for MLM; KITTI has no ground
truth in column 0). ``lrc`` needs no such rule: the right pixel it checks has every candidate.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar

import numba
import numpy as np

from cva_confidence_ros.checks import is_real
from cva_confidence_ros.confidence.base import (
    CONFIDENCE_METHODS,
    ConfidenceInputs,
    ConfidenceMethod,
)
from cva_confidence_ros.errors import ConfigError, InputError

__all__ = [
    'LeftRightConsistency',
    'LeftRightDifference',
    'MatchingScore',
    'MaximumLikelihood',
    'PeakRatioNaive',
    'left_right_difference_map',
    'two_smallest',
]

# Temporaries per block of rows stay below about this many float32 values (~32 MB).
_BLOCK_VALUES = 8 * 1024 * 1024

# Smallest sigma whose 1/(2σ²) is finite in float32 (about 3.8e-20).
_MIN_SIGMA = float(np.sqrt(0.5 / np.finfo(np.float32).max))


def _row_blocks(volume: np.ndarray) -> list[slice]:
    depth, height, width = volume.shape
    rows = max(1, _BLOCK_VALUES // max(1, depth * width))
    return [slice(top, min(top + rows, height)) for top in range(0, height, rows)]


def _map_rows(volume: np.ndarray, fn: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """Apply ``fn`` ((D, h, W) → (h, W)) to blocks of rows and stack the results (H, W)."""
    out = np.empty(volume.shape[1:], dtype=np.float64)
    for rows in _row_blocks(volume):
        out[rows] = fn(volume[:, rows])
    return out


@numba.njit(cache=True, parallel=True, fastmath=False)
def _two_smallest_kernel(
    volume: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    # One pass over the disparities per row, in memory order (d outer, x inner): a strided
    # np.partition along axis 0 was ~20× slower on a 128×480×640 volume. NaN fails every '<'
    # and would be skipped (or, at d = 0, kept as c1) without a word: counted per row instead.
    depth, height, width = volume.shape
    c1 = np.empty((height, width), dtype=np.float32)
    c2 = np.empty((height, width), dtype=np.float32)
    d1 = np.zeros((height, width), dtype=np.int64)
    nans = np.zeros(height, dtype=np.int64)
    for y in numba.prange(height):
        count = 0
        for x in range(width):
            value = volume[0, y, x]
            count += value != value
            c1[y, x] = value
            c2[y, x] = np.inf
        for d in range(1, depth):
            for x in range(width):
                value = volume[d, y, x]
                count += value != value
                if value < c1[y, x]:
                    c2[y, x] = c1[y, x]
                    c1[y, x] = value
                    d1[y, x] = d
                elif value < c2[y, x]:
                    c2[y, x] = value
        nans[y] = count
    return c1, d1, c2, nans


def _no_decision(
    confidence: np.ndarray, lowest: float, inputs: ConfidenceInputs
) -> np.ndarray:
    """``confidence`` (H, W) float32 with the image's column 0 (a single candidate) set to
    ``lowest`` (a crop that starts further right has none)."""
    if inputs.first_column == 0:
        confidence[:, :1] = lowest
    return confidence


def _check_real_array(name: str, value: object) -> None:
    # A list has no .ndim (bare AttributeError); complex would lose its imaginary part and a
    # str array fail inside numpy.
    if not isinstance(value, np.ndarray):
        raise InputError(f'{name} must be a numpy array; got {type(value).__name__}')
    if value.dtype.kind not in 'fiu':
        raise InputError(f'{name} must hold real numbers (float or int); got dtype {value.dtype}')


def two_smallest(volume: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Smallest cost, its disparity and the second-smallest cost of every pixel.

    Args:
        volume: (D, H, W) float32 cost volume, D ≥ 2, no NaN.

    Returns:
        ``(c1, d1, c2)``: (H, W) float32 minimum, (H, W) int64 arg-minimum (the first one on
        ties) and (H, W) float32 second-smallest value (naive: any disparity but ``d1``).

    Raises:
        InputError: Not a numpy array of real numbers, not 3-D, D < 2, or NaN costs.
    """
    _check_real_array('volume', volume)
    if volume.ndim != 3 or volume.shape[0] < 2:
        raise InputError(f'expected a (D, H, W) cost volume with D ≥ 2; got shape {volume.shape}')
    volume = np.ascontiguousarray(volume, dtype=np.float32)
    c1, d1, c2, nans = _two_smallest_kernel(volume)
    count = int(nans.sum())
    if count:
        raise InputError(f'volume must not contain NaN costs; got {count} NaN entries')
    return c1, d1, c2


def _check_positive(name: str, value: float) -> None:
    # bool is an int to Python but never a meaningful eps or sigma; a str or None would reach
    # np.isfinite and come back as a bare TypeError.
    if not is_real(value):
        raise ConfigError(f'{name} must be a real number; got {type(value).__name__} {value!r}')
    # np.isfinite takes no Fraction and no int beyond float64 (a bare TypeError): read as float,
    # where such an int is too large to be finite.
    try:
        number = float(value)
    except OverflowError:
        number = float('inf')
    if not (np.isfinite(number) and number > 0):
        raise ConfigError(f'{name} must be a finite number > 0; got {value}')


def _check_eps(value: float) -> None:
    _check_positive('eps', value)
    # eps is added in float32: one that rounds to 0 or inf there makes 0/0 or inf/inf, a NaN
    # confidence, at every perfect match.
    with np.errstate(over='ignore', under='ignore'):
        single = np.float32(value)
    if not (np.isfinite(single) and single > 0):
        raise ConfigError(
            'eps must stay finite and > 0 in float32 (between about '
            f'{np.finfo(np.float32).smallest_subnormal:.1e} and {np.finfo(np.float32).max:.1e}); '
            f'got {value}'
        )


@dataclass(frozen=True)
class MatchingScore(ConfidenceMethod):
    """Matching score measure (MSM): ``-c1``, the negated minimum cost."""

    def __call__(self, inputs: ConfidenceInputs) -> np.ndarray:
        """Return (H, W) float32 in [-1, 0] for costs in [0, 1]; -1 in column 0."""
        score = (-inputs.cost_volume.min(axis=0)).astype(np.float32)
        return _no_decision(score, -1.0, inputs)

    def to_unit_interval(self, confidence: np.ndarray) -> np.ndarray:
        """``1 - c1`` in [0, 1]."""
        return super().to_unit_interval(1.0 + confidence)


@dataclass(frozen=True)
class PeakRatioNaive(ConfidenceMethod):
    """Naive peak ratio (PKRN): ``(c2 + eps) / (c1 + eps)``, ≥ 1.

    Attributes:
        eps: Added to both costs so that a perfect match (``c1 = 0``) stays finite.
    """

    eps: float = 1e-3
    min_depth: ClassVar[int] = 2

    def __post_init__(self) -> None:
        _check_eps(self.eps)

    def __call__(self, inputs: ConfidenceInputs) -> np.ndarray:
        """Return (H, W) float32 in [1, (1 + eps) / eps] for costs in [0, 1]; 1 in column
        0."""
        c1, _, c2 = two_smallest(inputs.cost_volume)
        eps = np.float32(self.eps)
        # ConfidenceInputs lets costs dip 1e-4 below 0 (rounding slack); read as 0, so that an
        # eps below that cannot make c1 + eps zero or negative (an inf or a negative PKRN).
        zero = np.float32(0.0)
        c1, c2 = np.maximum(c1, zero), np.maximum(c2, zero)
        with np.errstate(over='ignore'):  # a tiny eps: +inf at perfect matches, the top
            ratio = ((c2 + eps) / (c1 + eps)).astype(np.float32)
        return _no_decision(ratio, 1.0, inputs)

    def to_unit_interval(self, confidence: np.ndarray) -> np.ndarray:
        """``1 - 1 / PKRN`` in [0, 1): 0 for two equal minima."""
        return super().to_unit_interval(1.0 - 1.0 / np.maximum(confidence, 1.0))


@dataclass(frozen=True)
class MaximumLikelihood(ConfidenceMethod):
    """Maximum likelihood measure (MLM): ``exp(-c1 / 2σ²) / Σ_d exp(-c(d) / 2σ²)``.

    Attributes:
        sigma: Spread of the cost likelihood, for costs normalised to [0, 1]: a cost 0.05
            above the minimum weighs ``exp(-2.5) ≈ 0.08`` of it. Of 0.05, 0.1, 0.2 and 0.3,
            0.1 gave the lowest AUC for census block matching on KITTI 2012 training pairs.
    """

    sigma: float = 0.1

    def __post_init__(self) -> None:
        _check_positive('sigma', self.sigma)
        # The costs are scaled in float32: a sigma so small that 1/(2σ²) overflows would turn
        # every weight into NaN (0 · inf) and the map into NaN.
        if not np.isfinite(self._scale()):
            raise ConfigError(
                f'sigma must be large enough that 1/(2 sigma^2) is finite in float32 '
                f'(sigma ≥ about {_MIN_SIGMA:.1e}); got {self.sigma}'
            )

    def _scale(self) -> np.float32:
        """``-1 / (2σ²)`` in float32; -inf where it overflows (numpy, not Python, arithmetic:
        Python raises for ``1e-200 ** 2`` in the denominator or ``1e200 ** 2``)."""
        with np.errstate(over='ignore', divide='ignore', under='ignore'):
            return np.float32(-1.0 / (2.0 * np.float64(self.sigma) ** 2))

    def __call__(self, inputs: ConfidenceInputs) -> np.ndarray:
        """Return (H, W) float32 in [1/D, 1]; 1/D for a flat cost curve and in column 0."""
        scale = self._scale()

        def block_mlm(block: np.ndarray) -> np.ndarray:
            # Shifting by the minimum keeps every exponent ≤ 0: no overflow, and the sum ≥ 1.
            weights = block - block.min(axis=0)
            with np.errstate(over='ignore'):  # a tiny sigma: -inf, whose exp is the right 0
                weights *= scale
            np.exp(weights, out=weights)
            return 1.0 / weights.sum(axis=0, dtype=np.float64)

        mlm = _map_rows(inputs.cost_volume, block_mlm).astype(np.float32)
        return _no_decision(mlm, 1.0 / inputs.max_disparity, inputs)


def left_right_difference_map(
    volume: np.ndarray, volume_right: np.ndarray, eps: float, first_column: int = 0
) -> np.ndarray:
    """Left-right difference ``(c2 - c1) / (|c1 - min_d c_R(x - d1, d)| + eps)``.

    Args:
        volume: (D, H, W) float32 left-reference costs.
        volume_right: (D, H, W) float32 right-reference costs.
        eps: > 0, keeps the ratio finite when both minima are equal.
        first_column: Image column of the volumes' column 0 (a crop's ``x0``).

    Returns:
        (H, W) float32 ≥ 0 (+inf where an eps below about 1e-38 overflows the ratio). Where
        ``x - d1 < 0`` the right pixel lies outside the image, so the match cannot be checked:
        0, the lowest confidence (as LRC gives its lowest value there); 0 in the image's
        column 0 too (a single candidate: ``c2`` is the filler). Within a crop (``first_column``
        > 0) the right pixel of ``x - d1 < 0`` may exist but is not in ``volume_right``: 0.

    Raises:
        InputError: Either volume not a real array, ``volume_right`` not of the shape of
            ``volume``, or NaN costs.
        ConfigError: ``eps`` not a number > 0 that stays finite and > 0 in float32.
    """
    _check_eps(eps)
    _check_real_array('volume_right', volume_right)
    if np.shape(volume_right) != np.shape(volume):
        raise InputError(
            f'volume_right must have the shape of volume {np.shape(volume)} (D, H, W); '
            f'got {np.shape(volume_right)}'
        )
    c1, d1, c2 = two_smallest(volume)
    right_min = volume_right.min(axis=0)
    # min propagates NaN: one look at the (H, W) minima finds a NaN anywhere in the volume.
    if np.isnan(right_min).any():
        count = int(np.count_nonzero(np.isnan(volume_right)))
        raise InputError(f'volume_right must not contain NaN costs; got {count} NaN entries')
    height, width = c1.shape
    cols = np.arange(width)[None, :] - d1
    # d1 ≥ 0, so only the left edge can be passed; a clipped column there (0) belonged to
    # another pixel and could make an unverifiable match the most confident one.
    inside = cols >= 0
    rows = np.arange(height)[:, None]
    denom = np.abs(c1 - right_min[rows, np.maximum(cols, 0)]) + np.float32(eps)
    if first_column == 0:
        inside[:, :1] = False
    with np.errstate(over='ignore'):  # a tiny eps: +inf, above every finite LRD
        return np.where(inside, (c2 - c1) / denom, np.float32(0.0)).astype(np.float32)


@dataclass(frozen=True)
class LeftRightDifference(ConfidenceMethod):
    """Left-right difference (LRD); needs the right-reference cost volume.

    Attributes:
        eps: Added to the denominator so that equal left and right minima stay finite.
    """

    eps: float = 1e-3
    needs_right = True
    min_depth: ClassVar[int] = 2

    def __post_init__(self) -> None:
        _check_eps(self.eps)

    def __call__(self, inputs: ConfidenceInputs) -> np.ndarray:
        """Return (H, W) float32 ≥ 0."""
        volume_right = self._require_right(inputs)
        return left_right_difference_map(
            inputs.cost_volume, volume_right, self.eps, inputs.first_column
        )

    def to_unit_interval(self, confidence: np.ndarray) -> np.ndarray:
        """``LRD / (1 + LRD)`` in [0, 1]: 1 for +inf (a tiny eps), the most confident."""
        # In float64, rounded once (to float32, in the clip): in float32 both 1 + LRD and the
        # quotient were rounded, which put the larger of two LRDs an ulp apart below the
        # smaller one (an increasing map no more; 18 pixels of the Motorcycle pair at half
        # size, Census-BM, D = 32, 506 with Census-SGM).
        positive = np.maximum(np.asarray(confidence, dtype=np.float64), 0.0)
        # inf / (1 + inf) is NaN, which the clip below would turn into 0, the least confident.
        with np.errstate(invalid='ignore'):
            unit = np.where(np.isposinf(positive), 1.0, positive / (1.0 + positive))
        return super().to_unit_interval(unit)


@dataclass(frozen=True)
class LeftRightConsistency(ConfidenceMethod):
    """Left-right consistency (LRC): ``-|d_L(x) - d_R(x - round(d_L(x)))|``.

    Uses ``inputs.disparity_right``, or the arg-minimum of ``inputs.cost_volume_right`` when
    only the volume is given. Pixels whose right correspondence lies outside the image (within a
    crop, ``first_column`` > 0: outside the arrays) or whose disparity is NaN get ``-D`` (D =
    volume depth), below every checkable value (≥ ``-(D-1)`` for disparities in [0, D - 1];
    given disparities outside that range can differ by more).
    """

    needs_right = True

    def __call__(self, inputs: ConfidenceInputs) -> np.ndarray:
        """Return (H, W) float32 ≤ 0; in [-D, 0] for disparities in [0, D - 1]."""
        disparity_right = inputs.disparity_right
        if disparity_right is None:
            disparity_right = np.argmin(self._require_right(inputs), axis=0).astype(np.float32)
        disparity = inputs.disparity
        height, width = disparity.shape
        worst = np.float32(-inputs.max_disparity)
        finite = np.isfinite(disparity)
        # Columns in float64, cast only once clipped: a disparity beyond int64 (1e20) cast
        # first was an undefined integer (a RuntimeWarning) that only wraparound kept outside.
        cols = np.arange(width, dtype=np.float64)[None, :] - np.rint(
            np.where(finite, disparity, 0.0)
        )
        inside = finite & (cols >= 0) & (cols < width)
        rows = np.broadcast_to(np.arange(height)[:, None], cols.shape)
        matched = disparity_right[rows, np.clip(cols, 0, width - 1).astype(np.intp)]
        diff = -np.abs(disparity - matched)
        return np.where(inside & np.isfinite(diff), diff, worst).astype(np.float32)

    def to_unit_interval(self, confidence: np.ndarray) -> np.ndarray:
        """``1 / (1 + |d_L - d_R|)`` in (0, 1]: 1 for consistent pixels."""
        return super().to_unit_interval(1.0 / (1.0 - np.minimum(confidence, 0.0)))


CONFIDENCE_METHODS.add('score', MatchingScore.from_options)
CONFIDENCE_METHODS.add('pkrn', PeakRatioNaive.from_options)
CONFIDENCE_METHODS.add('mlm', MaximumLikelihood.from_options)
CONFIDENCE_METHODS.add('lrd', LeftRightDifference.from_options)
CONFIDENCE_METHODS.add('lrc', LeftRightConsistency.from_options)

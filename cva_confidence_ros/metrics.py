"""The paper's evaluation protocol: KITTI error labels, ROC curves with interval points, AUC.

CVA-Net (Mehltretter & Heipke, ICCVW 2019, Sec. 4.1) evaluates a confidence map by its ROC
curve: pixels are taken in order of decreasing confidence and the error rate of the taken
pixels is plotted against their share (the density), sampled in 5 % steps. Pixels with equal
confidence are taken together; where such a group spans a sample density, an extra *interval*
point is added whose error rate is the centre between the best case (the group's correct
pixels first) and the worst case (its wrong pixels first).

Curve start: like the paper, the curve starts at its first sample point (density
``ceil(0.05 N) / N``); nothing is extrapolated towards density 0. The optimal curve is zero on
``[0, 1 - ε]``, so this changes nothing for :func:`optimal_auc` as long as
``ε ≤ 1 - ceil(0.05 N) / N`` (0.95 when 20 divides N); above, ``optimal_auc(ε, N)`` leaves out
the area before the curve's start as the AUC does.

All functions are vectorised (one sort, cumulative sums, ``searchsorted``) and handle millions of
pixels.
"""

from __future__ import annotations

from numbers import Real
from typing import Any
import warnings

import numpy as np

from cva_confidence_ros.checks import is_int
from cva_confidence_ros.errors import InputError

__all__ = [
    'ABS_THRESHOLD',
    'DENSITY_STEPS',
    'REL_THRESHOLD',
    'auc_scores',
    'evaluate_confidence',
    'kitti_error',
    'optimal_auc',
    'roc_auc',
    'roc_curve',
]

#: A disparity is correct if it is closer than this to the ground truth (pixels) ...
ABS_THRESHOLD = 3.0
#: ... or closer than this fraction of the ground-truth disparity (KITTI 2015 criterion).
REL_THRESHOLD = 0.05
#: Number of density samples: q = 1/20, 2/20, ..., 20/20.
DENSITY_STEPS = 20

#: dtype kinds of real numbers: float, signed and unsigned int (bool, complex, str excluded).
_REAL_KINDS = 'fiu'


def _real_array(name: str, values: Any) -> np.ndarray:
    """``values`` as an array of a real dtype, without converting it (complex would lose its
    imaginary part, a str array would fail deep inside numpy)."""
    array = np.asarray(values)
    if array.dtype.kind not in _REAL_KINDS:
        raise InputError(
            f'{name} must hold real numbers (float or int); got dtype {array.dtype}'
        )
    return array


def kitti_error(d_est: np.ndarray, d_gt: np.ndarray) -> np.ndarray:
    """Label every disparity as wrong or right with the KITTI criterion.

    A disparity is correct if ``|d_est - d_gt| < 3`` px or ``|d_est - d_gt| < 0.05 * d_gt``.

    Args:
        d_est: (H, W) (any shape) estimated disparity, float; NaN = no estimate.
        d_gt: Same shape, ground-truth disparity; NaN (or ±inf) = unknown.

    Returns:
        Bool array of the same shape, True where the estimate is wrong. A missing (NaN) estimate
        is wrong; pixels without ground truth are False and must be excluded by the caller with
        ``np.isfinite(d_gt)``.

    Raises:
        InputError: A dtype that is not real (float or int), or the shapes differ.
    """
    d_est = _real_array('d_est', d_est).astype(np.float64, copy=False)
    d_gt = _real_array('d_gt', d_gt).astype(np.float64, copy=False)
    if d_est.shape != d_gt.shape:
        raise InputError(
            f'd_est and d_gt must have the same shape; got {d_est.shape} and {d_gt.shape}'
        )
    known = np.isfinite(d_gt)
    with np.errstate(invalid='ignore'):
        diff = np.abs(d_est - d_gt)
        correct = (diff < ABS_THRESHOLD) | (diff < REL_THRESHOLD * d_gt)
    # NaN estimates fail both comparisons above, so they count as wrong.
    return known & ~correct


def _flatten_pair(confidence: np.ndarray, error: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    confidence = np.asarray(confidence)
    if confidence.dtype.kind not in _REAL_KINDS:
        hint = ''
        if confidence.dtype == np.bool_:
            hint = ' (convert a binary confidence with astype(float))'
        raise InputError(
            f'confidence must hold real numbers (float or int){hint}; got dtype {confidence.dtype}'
        )
    error = np.asarray(error)
    if confidence.shape != error.shape:
        raise InputError(
            'confidence and error must have the same shape; '
            f'got {confidence.shape} and {error.shape}'
        )
    if error.dtype != np.bool_:
        raise InputError(f'error must be a bool array (True = wrong); got dtype {error.dtype}')
    if confidence.size == 0:
        raise InputError('confidence and error are empty; expected at least one pixel')
    # Ranked in its own dtype: float64 would tie int64 / uint64 values beyond 2**53 and
    # long-double values closer than float64's resolution, and change the ranking.
    confidence = confidence.reshape(-1)
    if np.isnan(confidence).any():
        raise InputError(
            f'confidence holds {int(np.isnan(confidence).sum())} NaN values; '
            'expected a real number for every evaluated pixel'
        )
    return confidence, error.reshape(-1)


def roc_curve(confidence: np.ndarray, error: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sample the ROC curve (error rate over density) with the paper's interval extension.

    For each target density ``q = k / 20`` (k = 1 … 20) let ``m = ceil(q N)``. The original
    point lies at the end of the equal-confidence group that holds the m-th pixel (in order of
    decreasing confidence): ``(n_k / N, errors among the first n_k / n_k)``. If m lies strictly
    inside that group, the interval point ``(m / N, (best + worst) / 2 / m)`` is added, where
    best / worst are the error counts of the first m pixels when the group's correct / wrong
    pixels come first. Points with equal density are kept once.

    Args:
        confidence: Confidence of the evaluated pixels, any shape, real (no NaN; ±inf allowed);
            higher = more confident.
        error: Bool, same shape; True = the pixel's disparity is wrong.

    Returns:
        ``(density, error_rate)``: float64 1-D arrays of equal length, density strictly
        increasing in (0, 1] and ending at 1, error rate in [0, 1].

    Raises:
        InputError: Shapes differ, ``confidence`` is not real (float or int), ``error`` is not
            bool, the input is empty or holds NaN.
    """
    confidence, error = _flatten_pair(confidence, error)
    n = confidence.size
    # Descending order: ascending, reversed (negating would wrap unsigned and INT_MIN values);
    # the order within a run of equal values does not matter, runs are taken together.
    order = np.argsort(confidence, kind='stable')[::-1]
    sorted_conf = confidence[order]
    cum_err = np.cumsum(error[order], dtype=np.int64)
    # Group ends as pixel counts: the position after the last pixel of every run of equal values.
    ends = np.flatnonzero(sorted_conf[1:] != sorted_conf[:-1]) + 1
    ends = np.append(ends, n).astype(np.int64)

    k = np.arange(1, DENSITY_STEPS + 1, dtype=np.int64)
    targets = (k * n + DENSITY_STEPS - 1) // DENSITY_STEPS  # exact ceil(k / 20 * n)
    group = np.searchsorted(ends, targets, side='left')
    group_end = ends[group]
    group_start = np.where(group > 0, ends[np.maximum(group - 1, 0)], 0)

    errors_before = np.where(group_start > 0, cum_err[np.maximum(group_start - 1, 0)], 0)
    errors_at_end = cum_err[group_end - 1]
    size = group_end - group_start
    wrong = errors_at_end - errors_before
    right = size - wrong
    taken = targets - group_start
    best = errors_before + np.maximum(0, taken - right)
    worst = errors_before + np.minimum(taken, wrong)

    inside = targets < group_end
    counts = np.concatenate([group_end, targets[inside]])
    rates = np.concatenate(
        [errors_at_end / group_end, (best + worst)[inside] / (2.0 * targets[inside])]
    )
    # Equal counts always carry equal rates (the rate is a function of the count), so keeping
    # the first occurrence of each count is exact.
    counts, first = np.unique(counts, return_index=True)
    return counts / n, rates[first].astype(np.float64)


def _trapezoid(x: np.ndarray, y: np.ndarray) -> float:
    if x.size < 2:
        return 0.0
    return float(np.sum(np.diff(x) * (y[1:] + y[:-1]) * 0.5))


def roc_auc(confidence: np.ndarray, error: np.ndarray) -> float:
    """Area under the ROC curve of :func:`roc_curve` (trapezoid rule; lower is better).

    Args:
        confidence: Confidence of the evaluated pixels, any shape, no NaN.
        error: Bool, same shape, True = wrong.

    Returns:
        The area from the first sample density to 1, in [0, 1]. A single pixel gives a one-point
        curve and an area of 0.
    """
    density, rate = roc_curve(confidence, error)
    return _trapezoid(density, rate)


def optimal_auc(error_rate: float, n_pixels: int | None = None) -> float:
    """AUC of a perfect confidence map: ``ε + (1 − ε) ln(1 − ε)`` (paper, Eq. 1).

    Args:
        error_rate: Overall error rate ε of the disparity map, in [0, 1]: a real scalar (Python
            or numpy number, or a 0-d real array); bool is refused, as it is no rate.
        n_pixels: Given, the optimum over the density range that :func:`roc_auc` of that many
            pixels covers, from its first sample ``s = ceil(0.05 N) / N`` on: Eq. (1) while
            ``ε ≤ 1 − s``; above (ε > 0.95, or a few pixels), the area left of ``s``, which no
            confidence map can get, is left out: ``(1 − s) + (1 − ε) ln s`` (ε = 1, N = 100:
            0.95, the AUC of every map). The optimum is the exact area under the optimal
            curve; the AUC, a trapezoid rule over 5 % samples of a concave curve, can fall a
            little below it for a perfect map (ε = 0.1, N = 1000: 0.00513 against 0.00518).

    Returns:
        The optimal AUC in [0, 1] (without ``n_pixels``, 1 for ε = 1, the limit of the
        formula; with it, ``1 − s``).

    Raises:
        InputError: ``error_rate`` is not a real scalar, is outside [0, 1] or is NaN, or
            ``n_pixels`` is not an integer ≥ 1.
    """
    scalar = isinstance(error_rate, (Real, np.integer)) or (
        isinstance(error_rate, np.ndarray)
        and error_rate.ndim == 0
        and error_rate.dtype.kind in _REAL_KINDS
    )
    if not scalar or isinstance(error_rate, (bool, np.bool_)):
        shape = f' of shape {error_rate.shape}' if isinstance(error_rate, np.ndarray) else ''
        raise InputError(
            'error_rate must be a real number in [0, 1]; '
            f'got {type(error_rate).__name__}{shape} {error_rate!r}'
        )
    eps = float(error_rate)
    if not 0.0 <= eps <= 1.0:
        raise InputError(f'error_rate must be in [0, 1]; got {error_rate}')
    if n_pixels is not None:
        if not is_int(n_pixels) or n_pixels < 1:
            raise InputError(f'n_pixels must be an integer ≥ 1; got {n_pixels!r}')
        count = int(n_pixels)
        start = -(-count // DENSITY_STEPS) / count  # ceil(0.05 N) / N, the curve's first point
        if eps > 1.0 - start:
            return (1.0 - start) + (1.0 - eps) * float(np.log(start))
    if eps == 1.0:
        return 1.0
    return eps + (1.0 - eps) * float(np.log1p(-eps))


def auc_scores(confidence: np.ndarray, error: np.ndarray) -> dict[str, float | int]:
    """The paper's scores of a confidence over a set of pixels: what every evaluation here
    (``cva-evaluate``, the replay, training validation) reports.

    Args:
        confidence: Confidence of the evaluated pixels, any shape, no NaN.
        error: Bool, same shape, True = wrong.

    Returns:
        ``auc`` (:func:`roc_auc`), ``auc_opt`` (:func:`optimal_auc` of the error rate over
        these pixels), ``error_rate`` and ``n_pixels``.
    """
    flat_confidence, flat_error = _flatten_pair(confidence, error)
    error_rate = float(flat_error.mean())
    return {
        'auc': roc_auc(flat_confidence, flat_error),
        'auc_opt': optimal_auc(error_rate, int(flat_error.size)),
        'error_rate': error_rate,
        'n_pixels': int(flat_error.size),
    }


def evaluate_confidence(
    confidence: np.ndarray,
    d_est: np.ndarray,
    d_gt: np.ndarray,
    mask: np.ndarray | None = None,
) -> dict[str, float | int]:
    """Evaluate one confidence map against ground truth with the paper's protocol.

    Args:
        confidence: (H, W) confidence, higher = more confident; no NaN where evaluated.
        d_est: (H, W) estimated disparity, NaN = no estimate (counts as wrong).
        d_gt: (H, W) ground-truth disparity, NaN = unknown (excluded); a 0 is judged as
            disparity 0, with a ``RuntimeWarning`` (files that mark unknown pixels with 0 need
            them as NaN).
        mask: Optional (H, W) bool; only True pixels are evaluated (e.g. non-occluded).

    Returns:
        ``auc`` (float), ``auc_opt`` (float), ``error_rate`` (float, share of wrong disparities
        among the evaluated pixels) and ``n_pixels`` (int, pixels evaluated).

    Raises:
        InputError: Shapes differ, or no pixel has ground truth (inside the mask).
    """
    confidence = np.asarray(confidence)
    d_gt = np.asarray(d_gt)
    if confidence.shape != d_gt.shape:
        raise InputError(
            f'confidence and d_gt must have the same shape; got {confidence.shape} and '
            f'{d_gt.shape}'
        )
    error = kitti_error(d_est, d_gt)
    valid = np.isfinite(d_gt)
    if mask is not None:
        mask = np.asarray(mask)
        if mask.shape != d_gt.shape or mask.dtype != np.bool_:
            raise InputError(
                f'mask must be bool of shape {d_gt.shape}; got {mask.dtype} {mask.shape}'
            )
        valid &= mask
    n_pixels = int(valid.sum())
    if n_pixels == 0:
        raise InputError('no pixel has finite ground truth (inside the mask); nothing to evaluate')
    # KITTI's and older Middlebury's files mark "no ground truth" with 0; read as they are,
    # those pixels were judged at disparity 0 (70 % empty: an error rate of 0.74, not 0.17).
    zeros = int(np.count_nonzero(d_gt[valid] == 0))
    if zeros:
        warnings.warn(
            f'd_gt is exactly 0 at {zeros} of the {n_pixels} evaluated pixels '
            f'({100 * zeros / n_pixels:.1f} %), judged as ground-truth disparity 0; if 0 means '
            f'"unknown" (KITTI, Middlebury files), pass np.where(d_gt > 0, d_gt, np.nan)',
            RuntimeWarning, stacklevel=2,
        )
    return auc_scores(confidence[valid], error[valid])

"""Is a confidence of 0.8 right 80 % of the time? Reliability of probabilistic confidences.

The learned methods (CVA-Net and its kin, CCNN, LFN, LGC-Net) are trained with binary
cross-entropy on the KITTI correctness label, so their output is meant as the probability that
the winner-takes-all disparity is correct. Where that holds, a threshold is a probability a
robot can reason with, and the mean of ``1 − confidence`` over the pixels kept estimates their
error rate without any ground truth. This module measures how far it holds:

* :func:`reliability` bins the confidences and compares each bin's mean confidence with the
  share of correct disparities in it (a reliability diagram), giving the expected calibration
  error (ECE: the mean gap, weighted by the pixels in each bin) and the Brier score;
* :class:`ReliabilityTable` keeps sums rather than means, so tables of several scenes add up
  (:meth:`ReliabilityTable.merge`) to the table of all their pixels;
* :func:`expected_error` is the error rate a calibrated confidence predicts for a set of pixels.

The hand-crafted measures' values in [0, 1] (``ConfidenceMethod.to_unit_interval``) keep the
order of the measure but are no probabilities; they are scored by their ranking (AUC) only.
"""

from __future__ import annotations

from collections.abc import Hashable, Iterable, Mapping, MutableMapping
from dataclasses import dataclass
import math
from numbers import Integral, Real
from typing import Any

import numpy as np

from cva_confidence_ros.errors import InputError

__all__ = [
    'DEFAULT_BINS',
    'ReliabilityTable',
    'add_table',
    'expected_error',
    'reliability',
]

#: Equal-width confidence bins of a reliability table.
DEFAULT_BINS = 10


#: How far below its bin's lower edge a bin's mean confidence can lie: half a float16 step
#: below 1 (an edge rounded to float16 for binning a float16 confidence), plus rounding.
_EDGE_SLACK = 2.0**-12 + 1e-9


def _edges(bins: int) -> np.ndarray:
    # k / B exactly rounded: linspace gives 0.30000000000000004 for 3 / 10.
    return np.arange(bins + 1) / bins


def _numeric(name: str, array: np.ndarray) -> np.ndarray:
    if array.dtype.kind not in 'biuf':
        raise InputError(f'{name} must be a numeric array; got dtype {array.dtype}')
    return array


def _confidence_array(confidence: Any) -> np.ndarray:
    values = _numeric('confidence', np.asarray(confidence)).astype(np.float64).ravel()
    if np.isnan(values).any():
        raise InputError(
            f'confidence must not be NaN; got {int(np.isnan(values).sum())} NaN values'
        )
    if values.size and (values.min() < 0.0 or values.max() > 1.0):
        raise InputError(
            'confidence must be a probability in [0, 1]; got values in '
            f'[{values.min():g}, {values.max():g}]'
        )
    return values


@dataclass(frozen=True, eq=False)
class ReliabilityTable:
    """Confidence against correctness in equal-width bins of [0, 1].

    Bin ``i`` holds the confidences in ``[i / B, (i + 1) / B)``, the last bin also 1.0. A
    float32 (float16) confidence is compared with the edges rounded to float32 (float16), as
    the node compares it with ``np.float32(threshold)``: ``np.float32(0.7)``, a little below
    0.7, is in the bin that starts at 0.7, among the pixels a robot keeps at 0.7.

    Attributes:
        counts: (B,) int64 pixels per bin.
        confidence_sums: (B,) float64 sum of the confidences in each bin.
        correct_sums: (B,) float64 number of correct disparities in each bin.
        squared_error_sum: Sum over all pixels of (confidence − correct)², for the Brier score.
    """

    counts: np.ndarray
    confidence_sums: np.ndarray
    correct_sums: np.ndarray
    squared_error_sum: float

    @property
    def bins(self) -> int:
        """Number of bins B."""
        return int(self.counts.size)

    @property
    def edges(self) -> np.ndarray:
        """(B + 1,) float64 bin edges 0, 1/B, …, 1."""
        return _edges(self.bins)

    @property
    def n_pixels(self) -> int:
        """Pixels in the table."""
        return int(self.counts.sum())

    def _per_bin(self, sums: np.ndarray) -> np.ndarray:
        out = np.full(self.bins, np.nan)
        filled = self.counts > 0
        out[filled] = sums[filled] / self.counts[filled]
        return out

    @property
    def mean_confidence(self) -> np.ndarray:
        """(B,) float64 mean confidence per bin; NaN for an empty bin."""
        return self._per_bin(self.confidence_sums)

    @property
    def accuracy(self) -> np.ndarray:
        """(B,) float64 share of correct disparities per bin; NaN for an empty bin."""
        return self._per_bin(self.correct_sums)

    def _whole(self, sums: np.ndarray) -> float:
        if self.n_pixels == 0:
            raise InputError('the reliability table holds no pixels')
        return float(sums.sum() / self.n_pixels)

    @property
    def overall_confidence(self) -> float:
        """Mean confidence over all pixels: the share of correct ones it predicts."""
        return self._whole(self.confidence_sums)

    @property
    def overall_accuracy(self) -> float:
        """Share of correct disparities over all pixels (1 − error rate)."""
        return self._whole(self.correct_sums)

    @property
    def ece(self) -> float:
        """Expected calibration error: Σ_bins (n_b / n) · |mean confidence − accuracy| ∈ [0, 1]."""
        if self.n_pixels == 0:
            raise InputError('the reliability table holds no pixels')
        gap = np.abs(self.confidence_sums - self.correct_sums)  # = n_b · |conf_b − acc_b|
        return float(gap.sum() / self.n_pixels)

    @property
    def max_gap(self) -> float:
        """Largest |mean confidence − accuracy| of a non-empty bin."""
        filled = self.counts > 0
        if not filled.any():
            raise InputError('the reliability table holds no pixels')
        return float(np.max(np.abs(self.mean_confidence - self.accuracy)[filled]))

    @property
    def brier(self) -> float:
        """Brier score: mean (confidence − correct)² ∈ [0, 1]; lower = better."""
        if self.n_pixels == 0:
            raise InputError('the reliability table holds no pixels')
        return float(self.squared_error_sum / self.n_pixels)

    def kept_at(self, threshold: float) -> tuple[float, float | None, float | None]:
        """What a robot keeping the pixels with confidence ≥ ``threshold`` gets.

        Args:
            threshold: A bin edge below 1 (0, 1/B, …, (B − 1)/B), e.g. 0.5 or 0.8 with 10
                bins. 1 is refused: the last bin holds 1.0 with the confidences just below
                it, so the table cannot tell how many pixels reach 1.

        Returns:
            ``(kept share, measured error rate, predicted error rate)`` of those pixels, the
            predicted one being mean(1 − confidence); both None when none is kept.

        Raises:
            InputError: ``threshold`` is not a bin edge below 1, or the table holds no pixels.
        """
        try:
            position = float(threshold) * self.bins
        except (TypeError, ValueError):
            position = math.nan
        first = round(position) if math.isfinite(position) else -1  # round(nan) raises
        if not 0 <= first <= self.bins or abs(position - first) > 1e-6:
            raise InputError(
                f'threshold must be a bin edge (a multiple of 1/{self.bins} in [0, 1]); '
                f'got {threshold!r}'
            )
        if first == self.bins:
            raise InputError(
                f'threshold 1 cannot be answered: the last of the {self.bins} bins holds '
                f'[{(self.bins - 1) / self.bins:g}, 1], not the pixels at 1 alone; use a '
                f'threshold ≤ {(self.bins - 1) / self.bins:g}'
            )
        if self.n_pixels == 0:
            raise InputError('the reliability table holds no pixels')
        count = int(self.counts[first:].sum())
        if count == 0:
            return 0.0, None, None
        measured = 1.0 - float(self.correct_sums[first:].sum()) / count
        predicted = 1.0 - float(self.confidence_sums[first:].sum()) / count
        return count / self.n_pixels, measured, predicted

    def merge(self, other: ReliabilityTable) -> ReliabilityTable:
        """The table of the pixels of both tables (same number of bins).

        Raises:
            InputError: The bin counts differ.
        """
        if other.bins != self.bins:
            raise InputError(
                f'cannot merge reliability tables of {self.bins} and {other.bins} bins'
            )
        return ReliabilityTable(
            counts=self.counts + other.counts,
            confidence_sums=self.confidence_sums + other.confidence_sums,
            correct_sums=self.correct_sums + other.correct_sums,
            squared_error_sum=self.squared_error_sum + other.squared_error_sum,
        )

    @classmethod
    def combine(cls, tables: Iterable[ReliabilityTable]) -> ReliabilityTable:
        """Merge several tables into one (pixel-weighted, unlike a mean of per-scene ECEs).

        Raises:
            InputError: No tables, or their bin counts differ.
        """
        tables = list(tables)
        if not tables:
            raise InputError('no reliability tables to combine')
        result = tables[0]
        for table in tables[1:]:
            result = result.merge(table)
        return result

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready summary and bins (empty bins have ``null`` means)."""

        def listed(values: np.ndarray) -> list[float | None]:
            return [None if np.isnan(v) else float(v) for v in values]

        return {
            'n_pixels': self.n_pixels,
            'ece': self.ece,
            'max_gap': self.max_gap,
            'brier': self.brier,
            'mean_confidence': self.overall_confidence,
            'accuracy': self.overall_accuracy,
            'bins': {
                'edges': [float(v) for v in self.edges],
                'counts': [int(v) for v in self.counts],
                'mean_confidence': listed(self.mean_confidence),
                'accuracy': listed(self.accuracy),
            },
        }

    @classmethod
    def from_dict(cls, item: Mapping[str, Any]) -> ReliabilityTable:
        """Rebuild a table from :meth:`as_dict` (the sums from counts × means).

        Raises:
            InputError: Missing keys, bins of different lengths, or a value that
                :meth:`as_dict` cannot have written: a count that is not a whole number ≥ 0,
                a mean or Brier score that is not a number in [0, 1], a non-empty bin
                without a mean, a mean confidence outside its bin.
        """
        try:
            bins = item['bins']
            lists = [bins[key] for key in ('counts', 'mean_confidence', 'accuracy')]
            brier = item['brier']
        except (KeyError, TypeError) as exc:
            raise InputError(f'not a reliability table: {exc!r}') from None
        if not all(isinstance(values, list) for values in lists):
            raise InputError(
                'not a reliability table: bins counts, mean_confidence and accuracy must be '
                f'lists; got {", ".join(type(values).__name__ for values in lists)}'
            )
        counts, conf, acc = lists
        if not counts or not len(counts) == len(conf) == len(acc):
            raise InputError(
                'reliability bins must be non-empty lists of one length; got '
                f'{len(counts)}, {len(conf)}, {len(acc)}'
            )
        for i, count in enumerate(counts):
            if isinstance(count, bool) or not isinstance(count, Integral) or count < 0:
                raise InputError(
                    f'not a reliability table: bins counts[{i}] must be a whole number ≥ 0; '
                    f'got {count!r}'
                )
            for key, values in (('mean_confidence', conf), ('accuracy', acc)):
                if (values[i] is None and count == 0) or _unit(values[i]):
                    continue
                raise InputError(
                    f'not a reliability table: bins {key}[{i}] of {count} pixels must be a '
                    f'number in [0, 1]; got {values[i]!r}'
                )
            # The mean of confidences in [i / B, (i + 1) / B) lies in that bin (up to rounding;
            # below it by up to half a float16 step, the edge rounded as a float16 / float32
            # confidence is binned); one outside is no table of these bins (a shifted or
            # hand-edited list).
            low, high = i / len(counts), (i + 1) / len(counts)
            if count and not low - _EDGE_SLACK <= float(conf[i]) <= high + 1e-9:
                raise InputError(
                    f'not a reliability table: bins mean_confidence[{i}] must lie in its bin '
                    f'[{low:g}, {high:g}]; got {conf[i]!r}'
                )
        if not _unit(brier):
            raise InputError(
                f'not a reliability table: brier must be a number in [0, 1]; got {brier!r}'
            )
        n = np.asarray(counts, dtype=np.int64)
        filled = n > 0

        def sums(means: list[Any]) -> np.ndarray:
            return np.where(filled, n * np.asarray([v or 0.0 for v in means], np.float64), 0.0)

        return cls(
            counts=n,
            confidence_sums=sums(conf),
            correct_sums=sums(acc),
            squared_error_sum=float(brier) * int(n.sum()),
        )


def _unit(value: Any) -> bool:
    """Whether ``value`` is a real number (not a bool) in [0, 1]."""
    if isinstance(value, bool) or not isinstance(value, Real):
        return False
    try:
        return 0.0 <= float(value) <= 1.0
    except OverflowError:  # an integer of 309 digits or more
        return False


def add_table(
    tables: MutableMapping[Any, ReliabilityTable], key: Hashable, table: ReliabilityTable
) -> None:
    """Merge ``table`` into ``tables[key]`` (or store it there if the key is new)."""
    held = tables.get(key)
    tables[key] = table if held is None else held.merge(table)


def reliability(confidence: Any, correct: Any, bins: int = DEFAULT_BINS) -> ReliabilityTable:
    """Reliability table of probabilistic confidences against correctness labels.

    Args:
        confidence: (N,) or any-shaped float probabilities in [0, 1] (NaN refused).
        correct: Same size, bool, True = the disparity is correct (``~metrics.kitti_error``);
            the same shape where both have two or more dimensions. Pass only pixels with
            ground truth: ``kitti_error`` marks those without it False (not wrong), so
            ``~kitti_error`` over a whole sparse map counts them as correct.
        bins: Number of equal-width bins, ≥ 1.

    Returns:
        The :class:`ReliabilityTable` (may hold no pixels, when ``confidence`` is empty).

    Raises:
        InputError: Sizes or shapes differ, NaN, values outside [0, 1], a confidence that is
            not numeric, or ``bins`` < 1.
    """
    if isinstance(bins, bool) or not isinstance(bins, (int, np.integer)) or bins < 1:
        raise InputError(f'bins must be an integer ≥ 1; got {bins!r}')
    array = np.asarray(confidence)
    values = _confidence_array(array)
    labels = np.asarray(correct)
    if labels.dtype != bool:
        raise InputError(f'correct must be a bool array; got dtype {labels.dtype}')
    shape = np.shape(confidence)
    if len(shape) > 1 and labels.ndim > 1 and shape != labels.shape:
        # Equal sizes are not enough: an (H, W) against a (W, H) array pairs the wrong pixels.
        raise InputError(
            f'confidence and correct must have the same shape; got {shape} and {labels.shape}'
        )
    labels = labels.ravel()
    if labels.size != values.size:
        raise InputError(
            f'confidence and correct must have the same size; got {values.size} and {labels.size}'
        )
    # Not int(c · B): 15/22 · 22 = 14.999999999999998 would put an edge into the bin below it.
    edges = _edges(bins)
    if array.dtype.kind == 'f' and array.dtype.itemsize < 8:
        # The edges in the confidence's own precision: np.float32(0.7) (0.69999999) is the
        # node's threshold 0.7 (np.float32(threshold)), so it belongs to the bin from 0.7 on.
        edges = edges.astype(array.dtype).astype(np.float64)
    index = np.minimum(np.searchsorted(edges, values, side='right') - 1, bins - 1)
    hits = labels.astype(np.float64)
    return ReliabilityTable(
        counts=np.bincount(index, minlength=bins).astype(np.int64),
        confidence_sums=np.bincount(index, weights=values, minlength=bins),
        correct_sums=np.bincount(index, weights=hits, minlength=bins),
        squared_error_sum=float(np.sum((values - hits) ** 2)),
    )


def expected_error(confidence: Any, mask: Any = None) -> float | None:
    """Error rate that calibrated confidences predict for a set of pixels: mean(1 − c).

    For a calibrated method this is, without ground truth, an estimate of the share of wrong
    disparities among the pixels (e.g. those a robot keeps above its threshold).

    Args:
        confidence: Probabilities in [0, 1], any shape; NaN (no confidence) is left out.
        mask: Optional bool array of the same shape: only these pixels (numbers: non-zero
            selects).

    Returns:
        The predicted error rate in [0, 1]; None if no pixel is left.

    Raises:
        InputError: Values outside [0, 1], no numbers, or a mask of another shape, of no
            bool or number dtype (str, object, complex) or with NaN.
    """
    # Called on every frame by the node: pick the pixels first, convert only those.
    values = _numeric('confidence', np.asarray(confidence))
    if mask is not None:
        mask = np.asarray(mask)
        if mask.dtype.kind not in 'biuf':
            # Cast to bool, every non-empty string ('False' too) or object would select its pixel.
            raise InputError(f'mask must be a bool array; got dtype {mask.dtype}')
        if mask.dtype.kind == 'f' and np.isnan(mask).any():
            # NaN cast to bool is True: the pixel would be counted as selected.
            raise InputError('mask must be a bool array; got NaN in a float mask')
        mask = mask.astype(bool)
        if mask.shape != values.shape:
            raise InputError(
                f'mask must have the shape of confidence {values.shape}; got {mask.shape}'
            )
        values = values[mask]
    values = values.ravel()
    missing = np.isnan(values)
    if missing.any():
        values = values[~missing]
    if values.size == 0:
        return None
    low, high = float(values.min()), float(values.max())
    if low < 0.0 or high > 1.0:
        raise InputError(
            f'confidence must be a probability in [0, 1]; got values in [{low:g}, {high:g}]'
        )
    return float(1.0 - values.mean(dtype=np.float64))

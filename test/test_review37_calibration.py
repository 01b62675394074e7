"""Review 37, calibration as planning and mapping engineers use it.

The first tests pin findings (each failed before its fix); the others check
``calibration.reliability`` against an independent implementation of the ECE and Brier score
(equal-width bins, edges, one pixel, empty bins) and ``ReliabilityTable.merge``.
"""

from __future__ import annotations

import math
from pathlib import Path
import re

import numpy as np
import pytest

from cva_confidence_ros import calibration
from cva_confidence_ros.calibration import ReliabilityTable, expected_error, reliability
from cva_confidence_ros.errors import InputError
from cva_confidence_ros.metrics import kitti_error

README = Path(__file__).resolve().parent.parent / 'README.md'


def _readme() -> str:
    return re.sub(r'\s+', ' ', README.read_text(encoding='utf-8'))


def test_readme_expected_kept_error_under_blur_is_that_of_the_defaults():
    # The README quoted 2.7 → 4.6 % (kept share 0.89 → 0.86) for the Motorcycle pair under a
    # σ 4 blur "with the defaults"; those were taken before the speckle filter (speckle_size
    # 100 by default now), which drops wrong pixels: the defaults give 2.2 → 4.0 %.
    import cv2
    from skimage.data import stereo_motorcycle

    from cva_confidence_ros.pipeline import PipelineConfig, StereoPipeline

    left, right, _ = stereo_motorcycle()
    pipeline = StereoPipeline(PipelineConfig(downsample=2))
    plain = pipeline.process(left, right)
    blurred = pipeline.process(
        cv2.GaussianBlur(left, (0, 0), 4.0), cv2.GaussianBlur(right, (0, 0), 4.0)
    )
    assert plain.expected_kept_error is not None and blurred.expected_kept_error is not None
    assert f'{100 * plain.expected_kept_error:.1f}' == '2.2'
    assert f'{100 * blurred.expected_kept_error:.1f}' == '4.0'
    assert (f'{plain.kept_fraction:.2f}', f'{blurred.kept_fraction:.2f}') == ('0.87', '0.84')
    text = _readme()
    assert 'with the defaults (speckle filter on) 2.2 → 4.0 % at σ 4' in text
    assert "with the node's defaults it rises from 2.2 % to 4.0 % under a σ 4 blur" in text
    assert 'the kept share only 0.87 → 0.84' in text
    assert 'it rises from 2.7 % to 4.6 %' not in text


def test_reliability_docstring_warns_that_kitti_error_marks_no_ground_truth_as_right():
    # ~kitti_error, which the docstring names for ``correct``, is True where there is no
    # ground truth: over a sparse map those pixels pass for correct ones.
    disparity = np.array([10.0, 10.0, 10.0, 10.0])
    truth = np.array([10.0, 30.0, np.nan, np.nan])
    confidence = np.array([0.9, 0.9, 0.1, 0.1])
    whole = reliability(confidence, ~kitti_error(disparity, truth))
    known = np.isfinite(truth)
    right = reliability(confidence[known], ~kitti_error(disparity[known], truth[known]))
    assert whole.overall_accuracy == 0.75  # 3 of 4 "correct": two have no ground truth
    assert right.overall_accuracy == 0.5
    doc = ' '.join((calibration.reliability.__doc__ or '').split())
    assert 'Pass only pixels with ground truth' in doc


# Independent implementation: bin of c is the largest k with c ≥ k / B (edges in the
# confidence's float type, as the node compares), at most B − 1.


def _bin(c: float, bins: int, dtype: type) -> int:
    k = 0
    for j in range(1, bins):
        if c >= float(dtype(j / bins)):
            k = j
    return k


def _ece_brier(conf: np.ndarray, correct: np.ndarray, bins: int) -> tuple[float, float, list]:
    dtype = conf.dtype.type if conf.dtype.itemsize < 8 else np.float64
    groups: dict[int, list[tuple[float, float]]] = {}
    for c, y in zip(conf.tolist(), correct.tolist(), strict=True):
        groups.setdefault(_bin(c, bins, dtype), []).append((c, float(y)))
    n = conf.size
    ece = sum(
        len(g) / n * abs(sum(c for c, _ in g) / len(g) - sum(y for _, y in g) / len(g))
        for g in groups.values()
    )
    brier = sum((c - float(y)) ** 2 for c, y in zip(conf.tolist(), correct.tolist(),
                                                     strict=True)) / n
    counts = [len(groups.get(b, [])) for b in range(bins)]
    return ece, brier, counts


@pytest.mark.parametrize('dtype', [np.float64, np.float32, np.float16])
@pytest.mark.parametrize('bins', [1, 3, 7, 10, 22])
def test_ece_brier_match_an_independent_implementation(dtype, bins):
    rng = np.random.default_rng(bins)
    edges = np.arange(bins + 1) / bins
    conf = np.concatenate([rng.random(200), edges, [0.0, 1.0, 0.0, 1.0]]).astype(dtype)
    correct = rng.random(conf.size) < conf.astype(np.float64)
    table = reliability(conf, correct, bins)
    ece, brier, counts = _ece_brier(conf, correct, bins)
    assert table.counts.tolist() == counts
    assert math.isclose(table.ece, ece, rel_tol=1e-12, abs_tol=1e-15)
    assert math.isclose(table.brier, brier, rel_tol=1e-12, abs_tol=1e-15)


def test_edges_zero_one_one_pixel_and_empty_bins():
    table = reliability([0.0, 0.1, 0.5, 0.9, 1.0], [False, False, True, True, True])
    assert table.counts.tolist() == [1, 1, 0, 0, 0, 1, 0, 0, 0, 2]
    assert np.isnan(table.mean_confidence[2]) and np.isnan(table.accuracy[2])
    assert table.as_dict()['bins']['mean_confidence'][2] is None
    one = reliability([0.3], [True])
    assert math.isclose(one.ece, 0.7) and math.isclose(one.brier, 0.49)
    assert one.kept_at(0.3) == (1.0, 0.0, pytest.approx(0.7))
    with pytest.raises(InputError, match='NaN'):
        reliability([0.5, np.nan], [True, True])
    empty = reliability(np.zeros(0), np.zeros(0, bool))
    assert empty.n_pixels == 0
    with pytest.raises(InputError, match='no pixels'):
        _ = empty.ece
    assert expected_error(np.zeros(0)) is None
    assert expected_error(np.array([np.nan, 0.25])) == 0.75  # NaN left out, as documented
    assert expected_error(np.ones((2, 2)), np.zeros((2, 2), bool)) is None


def test_merge_of_scenes_is_the_table_of_all_pixels():
    rng = np.random.default_rng(7)
    scenes = [(rng.random(n).astype(np.float32), rng.random(n) < 0.8) for n in (1, 50, 3000)]
    merged = ReliabilityTable.combine(reliability(c, y) for c, y in scenes)
    whole = reliability(np.concatenate([c for c, _ in scenes]),
                        np.concatenate([y for _, y in scenes]))
    assert merged.counts.tolist() == whole.counts.tolist()
    np.testing.assert_allclose(merged.confidence_sums, whole.confidence_sums, rtol=1e-12)
    np.testing.assert_array_equal(merged.correct_sums, whole.correct_sums)
    assert math.isclose(merged.ece, whole.ece, rel_tol=1e-9)
    assert math.isclose(merged.brier, whole.brier, rel_tol=1e-12)
    with pytest.raises(InputError, match='10 and 5 bins'):
        merged.merge(reliability([0.5], [True], bins=5))

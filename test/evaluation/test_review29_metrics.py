"""Review 29: the ROC / AUC protocol (paper Sec. 4.1) checked against an independent brute force,
plus the defects found on the way (rankings lost to a float64 cast, unchecked input of
``score_confidence``)."""

from __future__ import annotations

from fractions import Fraction
import math

import numpy as np
import pytest

from cva_confidence_ros.errors import InputError
from cva_confidence_ros.evaluation.scene import score_confidence
from cva_confidence_ros.evaluation.table1 import TableRow, _cells, format_table1
from cva_confidence_ros.metrics import optimal_auc, roc_auc, roc_curve


def brute_curve(
    confidence: np.ndarray, error: np.ndarray, steps: int = 20
) -> tuple[list[Fraction], list[Fraction]]:
    """The paper's curve, written from its text with plain Python and exact fractions.

    Pixels in order of decreasing confidence; for every target density k / steps the m-th
    pixel (m = ceil(k N / steps)) lies in a group of equal confidence: the original point is
    at that group's end, and where m lies inside the group an interval point at m gets the
    centre of the best (its correct pixels first) and worst (its wrong pixels first) error.
    """
    pairs = list(zip(confidence.ravel().tolist(), error.ravel().tolist(), strict=True))
    n = len(pairs)
    points: dict[int, Fraction] = {}
    start = errors_before = 0
    for value in sorted({c for c, _ in pairs}, reverse=True):
        group = [e for c, e in pairs if c == value]
        wrong = sum(group)
        right = len(group) - wrong
        end = start + len(group)
        for k in range(1, steps + 1):
            m = math.ceil(Fraction(k * n, steps))
            if start < m <= end:
                points[end] = Fraction(errors_before + wrong, end)
                if m < end:
                    taken = m - start
                    best = errors_before + max(0, taken - right)
                    worst = errors_before + min(taken, wrong)
                    points[m] = Fraction(best + worst, 2 * m)
        start, errors_before = end, errors_before + wrong
    counts = sorted(points)
    return [Fraction(c, n) for c in counts], [points[c] for c in counts]


def brute_auc(confidence: np.ndarray, error: np.ndarray, steps: int = 20) -> Fraction:
    x, y = brute_curve(confidence, error, steps)
    return sum(
        ((x[i + 1] - x[i]) * (y[i] + y[i + 1]) / 2 for i in range(len(x) - 1)), Fraction(0)
    )


def _cases() -> list[tuple[np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(29)
    cases = []
    for trial in range(240):
        n = int(rng.integers(1, 60))
        kind = trial % 6
        if kind == 0:
            confidence = rng.random(n)
        elif kind == 1:  # many ties
            confidence = rng.integers(0, 4, n).astype(np.float32)
        elif kind == 2:  # one tie over everything
            confidence = np.full(n, 0.3)
        elif kind == 3:  # ±inf, signed zeros, outside [0, 1]
            confidence = rng.choice([-np.inf, np.inf, 0.0, -0.0, 5.0, -2.0], n)
        elif kind == 4:  # integer confidence
            confidence = rng.integers(-3, 3, n)
        else:  # huge magnitudes
            confidence = rng.normal(size=n) * 1e300
        error = rng.random(n) < rng.random()
        if trial % 7 == 0:
            error[:] = False  # all correct
        if trial % 11 == 0:
            error[:] = True  # all wrong
        cases.append((confidence, error))
    return cases


def test_protocol_agrees_with_an_independent_brute_force() -> None:
    checked_ties = 0
    for confidence, error in _cases():
        density, rate = roc_curve(confidence, error)
        x, y = brute_curve(confidence, error)
        np.testing.assert_array_equal(density, [float(v) for v in x])
        np.testing.assert_allclose(rate, [float(v) for v in y], rtol=0, atol=1e-15)
        assert roc_auc(confidence, error) == pytest.approx(
            float(brute_auc(confidence, error)), abs=1e-14
        )
        checked_ties += np.unique(confidence).size < confidence.size
    assert checked_ties > 100
    # A single pixel: a one-point curve of area 0, wrong or right.
    for wrong in (False, True):
        one = (np.array([0.7]), np.array([wrong]))
        assert roc_auc(*one) == 0.0 == float(brute_auc(*one))


def test_constant_confidence_is_the_papers_interval_centre_not_eps() -> None:
    # The paper takes the centre between best and worst case inside a tie: one tie over all
    # N = 20 pixels (ε = 0.2) gives 1/2 at densities ≤ ε, not ε; only the last point is ε.
    error = np.zeros(20, dtype=bool)
    error[:4] = True
    confidence = np.full(20, 0.5)
    density, rate = roc_curve(confidence, error)
    assert rate[0] == 0.5 and rate[-1] == pytest.approx(0.2)
    assert roc_auc(confidence, error) == pytest.approx(float(brute_auc(confidence, error)))
    assert roc_auc(confidence, error) > 0.2
    # ε = 0.5: the centre is ε everywhere, the curve's area that from 1/20 on.
    error = np.arange(20) % 2 == 0
    assert roc_auc(confidence, error) == pytest.approx(0.5 * 0.95)


def test_perfect_ranking_at_fine_steps_reaches_equation_1() -> None:
    n = 400
    error = np.zeros(n, dtype=bool)
    error[:100] = True  # ε = 0.25
    confidence = np.where(error, 0.0, 1.0) + np.linspace(0.0, 0.1, n)
    fine = float(brute_auc(confidence, error, steps=n))
    assert fine == pytest.approx(optimal_auc(0.25, n), abs=2e-4)
    # At the paper's 5 % steps the trapezoid rule on the concave optimal curve stays a little
    # below Eq. (1), as optimal_auc's docstring now says.
    assert optimal_auc(0.25, n) - 2e-3 < roc_auc(confidence, error) < optimal_auc(0.25, n)


@pytest.mark.parametrize(
    ('low', 'high'),
    [
        (np.int64(2**53), np.int64(2**53 + 1)),
        (np.uint64(2**64 - 2), np.uint64(2**64 - 1)),
        (np.longdouble(1.0), np.longdouble(1.0) + np.finfo(np.longdouble).eps),
    ],
    ids=['int64', 'uint64', 'longdouble'],
)
def test_confidences_beyond_float64_keep_their_ranking(low: object, high: object) -> None:
    # Was: ranked after a cast to float64, which made the two values one tie (AUC 0.475 for
    # a perfect ranking).
    error = np.arange(20) % 2 == 0
    confidence = np.where(error, low, high)
    assert confidence[0] != confidence[1]
    perfect = roc_auc(np.where(error, 0.0, 1.0), error)
    assert roc_auc(confidence, error) == pytest.approx(perfect)
    assert score_confidence(confidence, error).auc == pytest.approx(perfect)


def test_integer_confidence_at_the_ends_of_its_range() -> None:
    # Negating would wrap INT_MIN / unsigned values; the ranking must survive.
    error = np.array([True, False, True, False])
    for confidence in (
        np.array([np.iinfo(np.int8).min, 5, np.iinfo(np.int8).min, np.iinfo(np.int8).max],
                 dtype=np.int8),
        np.array([0, 7, 1, 255], dtype=np.uint8),
    ):
        assert roc_auc(confidence, error) == pytest.approx(
            float(brute_auc(confidence.astype(np.int64), error))
        )
        assert roc_auc(confidence, error) == pytest.approx(
            roc_auc(np.array([0.0, 1.0, 0.0, 1.0]), error)
        )


@pytest.mark.parametrize(
    ('confidence', 'error', 'message'),
    [
        (np.array([1 + 1j, 2 + 0j]), np.array([True, False]), 'real numbers'),
        (np.array([True, False]), np.array([True, False]), 'real numbers'),
        (np.array(['a', 'b']), np.array([True, False]), 'real numbers'),
        (np.array(['0.2', '0.9']), np.array([True, False]), 'real numbers'),
        (np.array([0.1, 0.9]), np.array([0.2, 0.0]), 'error must be a bool array'),
        (np.zeros((2, 3)), np.zeros((3, 2), dtype=bool), 'same shape'),
    ],
    ids=['complex', 'bool', 'str', 'numeric-str', 'float-error', 'transposed'],
)
def test_score_confidence_refuses_what_the_metrics_refuse(
    confidence: np.ndarray, error: np.ndarray, message: str
) -> None:
    # Was: cast to float64 / bool first: a complex map lost its imaginary part (a warning), a
    # bool or numeric-str one was scored, 'a' raised a bare ValueError, float error labels
    # became True, and a transposed error paired the wrong pixels.
    with pytest.raises(InputError, match=message):
        score_confidence(confidence, error)


def test_table1_cells_are_means_of_per_scene_aucs() -> None:
    # The paper's Table 1 gives the average AUC over the images: a mean of per-scene AUCs,
    # not one AUC over the pooled pixels.
    rng = np.random.default_rng(5)
    records, pooled_conf, pooled_err, aucs, opts = [], [], [], [], []
    for scene, (n, eps) in enumerate(((50, 0.1), (400, 0.6))):
        error = rng.random(n) < eps
        confidence = rng.random(n)
        score = score_confidence(confidence, error)
        aucs.append(score.auc)
        opts.append(score.auc_opt)
        pooled_conf.append(confidence)
        pooled_err.append(error)
        records.append({'row': 'R', 'scene': str(scene), 'matcher': 'census_bm',
                        'method': 'pkrn', 'auc': score.auc, 'auc_opt': score.auc_opt})
    cell = _cells(records)[('R', 'census_bm')]
    assert cell['pkrn'] == pytest.approx(100 * np.mean(aucs))
    assert cell['opt'] == pytest.approx(100 * np.mean(opts))
    pooled = roc_auc(np.concatenate(pooled_conf), np.concatenate(pooled_err))
    assert abs(cell['pkrn'] - 100 * pooled) > 1.0
    table = format_table1(records, [TableRow('R', 'kitti2015')], ['census_bm'],
                          [('pkrn', 'PKRN')])
    assert f'{100 * np.mean(aucs):.2f}' in table

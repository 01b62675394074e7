"""Tests of the evaluation protocol against hand-computed ROC curves and AUCs."""

from __future__ import annotations

from fractions import Fraction
import math

import numpy as np
import pytest

from cva_confidence_ros.errors import InputError
from cva_confidence_ros.metrics import (
    auc_scores,
    evaluate_confidence,
    kitti_error,
    optimal_auc,
    roc_auc,
    roc_curve,
)


def trapezoid(points: list[tuple[Fraction, Fraction]]) -> float:
    area = sum(
        (x1 - x0) * (y0 + y1) / 2 for (x0, y0), (x1, y1) in zip(points, points[1:], strict=False)
    )
    return float(area)


def test_kitti_error_hand_values() -> None:
    d_gt = np.array([10.0, 100.0, 50.0, np.nan, 2.0, 0.0, 80.0, 80.0])
    d_est = np.array([12.9, 104.9, 53.0, 5.0, np.nan, 3.0, 75.9, 76.1])
    # 2.9 < 3 right; 4.9 < 0.05 * 100 right; 3.0 is neither < 3 nor < 2.5 wrong; no GT False;
    # NaN estimate wrong; 3.0 at d_gt = 0 wrong; 4.1 ≥ 4.0 wrong; 3.9 < 4.0 right.
    expected = np.array([False, False, True, False, True, True, True, False])
    np.testing.assert_array_equal(kitti_error(d_est, d_gt), expected)


def test_kitti_error_relative_threshold_applies_above_60px() -> None:
    assert not kitti_error(np.array([103.5]), np.array([100.0]))[0]
    assert kitti_error(np.array([53.5]), np.array([50.0]))[0]


def test_kitti_error_shape_mismatch() -> None:
    with pytest.raises(InputError, match='same shape'):
        kitti_error(np.zeros((2, 2)), np.zeros((2, 3)))


# Ten pixels, already in order of decreasing confidence; groups of equal confidence:
# {0}, {1, 2, 3}, {4, 5}, {6}, {7}, {8, 9}. N = 10, so m = ceil(k / 2) for k = 1 … 20.
CONF = np.array([0.9, 0.8, 0.8, 0.8, 0.5, 0.5, 0.3, 0.2, 0.1, 0.1])
ERR = np.array([False, True, False, False, True, False, False, True, True, False])
F = Fraction
EXPECTED_CURVE = [
    (F(1, 10), F(0)),  # group end, 0 wrong of 1
    (F(2, 10), F(0 + 1, 2) / 2),  # inside {1,2,3} (1 wrong, 2 right): best 0, worst 1
    (F(3, 10), F(0 + 1, 2) / 3),  # best 0 (two right first), worst 1
    (F(4, 10), F(1, 4)),  # group end
    (F(5, 10), F(1 + 2, 2) / 5),  # inside {4,5}: before 1 wrong; best 1, worst 2
    (F(6, 10), F(2, 6)),
    (F(7, 10), F(2, 7)),
    (F(8, 10), F(3, 8)),
    (F(9, 10), F(3 + 4, 2) / 9),  # inside {8,9}: before 3; best 3, worst 4
    (F(10, 10), F(4, 10)),
]


def test_roc_curve_hand_computed_with_ties() -> None:
    density, rate = roc_curve(CONF, ERR)
    np.testing.assert_allclose(density, [float(x) for x, _ in EXPECTED_CURVE])
    np.testing.assert_allclose(rate, [float(y) for _, y in EXPECTED_CURVE])


def test_roc_auc_hand_computed_with_ties() -> None:
    assert roc_auc(CONF, ERR) == pytest.approx(trapezoid(EXPECTED_CURVE), abs=1e-12)
    assert roc_auc(CONF, ERR) == pytest.approx(0.25496031746, abs=1e-10)


def test_roc_is_independent_of_pixel_order_and_shape() -> None:
    perm = np.random.default_rng(3).permutation(CONF.size)
    d1, r1 = roc_curve(CONF[perm].reshape(2, 5), ERR[perm].reshape(2, 5))
    d0, r0 = roc_curve(CONF, ERR)
    np.testing.assert_array_equal(d0, d1)
    np.testing.assert_allclose(r0, r1)


def test_original_points_only_at_group_ends() -> None:
    # 40 pixels, two groups of 20: q = 0.5 ends the first group, every other q < 1 lies inside.
    conf = np.repeat([1.0, 0.0], 20)
    err = np.zeros(40, dtype=bool)
    err[[0, 1, 20, 21, 22, 23]] = True  # 2 wrong in the first group, 4 in the second
    density, rate = roc_curve(conf, err)
    assert density.size == 20
    np.testing.assert_allclose(density, np.arange(1, 21) / 20)
    # k = 1 (m = 2): best 0, worst 2 → 1 / 2; k = 10 (m = 20): group end, 2 / 20.
    assert rate[0] == pytest.approx(0.5)
    assert rate[9] == pytest.approx(0.1)
    # k = 11 (m = 22): 2 before, second group 4 wrong / 16 right, 2 taken → best 2, worst 4.
    assert rate[10] == pytest.approx(3 / 22)
    assert rate[-1] == pytest.approx(6 / 40)


def constant_rate(m: int, n_wrong: int, n_right: int) -> Fraction:
    """Midpoint error rate of the first m pixels of one group of equal confidence."""
    return Fraction(max(0, m - n_right) + min(m, n_wrong), 2 * m)


def test_constant_confidence_gives_midpoint_curve() -> None:
    # N = 20, 4 wrong (ε = 0.2): m = k. Rate 1/2 for m ≤ 4, 2/m for 4 < m ≤ 16,
    # (m − 12) / 2m for m > 16, and ε at m = 20.
    err = np.zeros(20, dtype=bool)
    err[[3, 7, 11, 19]] = True
    density, rate = roc_curve(np.full(20, 0.7), err)
    points = [(Fraction(m, 20), constant_rate(m, 4, 16)) for m in range(1, 21)]
    assert points[1][1] == Fraction(1, 2)
    assert points[9][1] == Fraction(2, 10)
    assert points[17][1] == Fraction(6, 36)
    assert points[-1][1] == Fraction(1, 5)
    np.testing.assert_allclose(rate, [float(y) for _, y in points])
    np.testing.assert_allclose(density, np.arange(1, 21) / 20)
    assert roc_auc(np.full(20, 0.7), err) == pytest.approx(trapezoid(points), abs=1e-12)


def test_constant_confidence_large_n_matches_closed_form() -> None:
    n, n_wrong = 10_000, 3_000
    err = np.zeros(n, dtype=bool)
    err[np.random.default_rng(0).choice(n, n_wrong, replace=False)] = True
    points = [
        (Fraction(m, n), constant_rate(m, n_wrong, n - n_wrong))
        for m in (k * n // 20 for k in range(1, 21))
    ]
    assert roc_auc(np.zeros(n), err) == pytest.approx(trapezoid(points), abs=1e-12)


@pytest.mark.parametrize('eps', [0.05, 0.3, 0.6])
def test_perfect_ranking_reaches_optimal_auc(eps: float) -> None:
    n = 2_000
    n_wrong = round(eps * n)
    rng = np.random.default_rng(1)
    err = np.zeros(n, dtype=bool)
    err[rng.choice(n, n_wrong, replace=False)] = True
    distinct = np.where(err, rng.uniform(0.0, 0.5, n), rng.uniform(0.5, 1.0, n))
    two_level = np.where(err, 0.0, 1.0)
    # Sampled optimal curve: max(0, m − (N − ε N)) / m at m = k N / 20.
    points = [
        (Fraction(m, n), Fraction(max(0, m - (n - n_wrong)), m))
        for m in (k * n // 20 for k in range(1, 21))
    ]
    for conf in (distinct, two_level):
        auc = roc_auc(conf, err)
        assert auc == pytest.approx(trapezoid(points), abs=1e-12)
        # The 5 % grid costs at most a little against the continuous optimum.
        assert abs(auc - optimal_auc(eps)) < 0.01


def test_inverted_ranking_is_worse_than_random_and_optimal() -> None:
    rng = np.random.default_rng(2)
    err = rng.random(5_000) < 0.25
    perfect = roc_auc(np.where(err, 0.0, 1.0), err)
    random = roc_auc(rng.random(5_000), err)
    inverted = roc_auc(np.where(err, 1.0, 0.0), err)
    assert perfect < random < inverted
    assert random == pytest.approx(err.mean(), abs=0.03)


def test_optimal_auc_formula() -> None:
    assert optimal_auc(0.0) == 0.0
    assert optimal_auc(1.0) == 1.0
    assert optimal_auc(0.5) == pytest.approx(0.5 + 0.5 * math.log(0.5))
    assert optimal_auc(0.2) == pytest.approx(0.2 + 0.8 * math.log(0.8))
    with pytest.raises(InputError, match=r'\[0, 1\]'):
        optimal_auc(1.5)


def test_optimal_auc_over_the_curves_range() -> None:
    # ε ≤ 1 − ceil(0.05 N) / N: the paper's Eq. (1) whatever N.
    assert optimal_auc(0.3, 1000) == optimal_auc(0.3)
    assert optimal_auc(0.95, 100) == optimal_auc(0.95)
    # Above: the area before the curve's first point (0.05 for N = 100) is left out.
    assert optimal_auc(1.0, 100) == pytest.approx(0.95)
    assert optimal_auc(0.98, 100) == pytest.approx(0.95 + 0.02 * math.log(0.05))
    assert optimal_auc(1.0, 1) == 0.0  # one point: no area
    # evaluate_confidence, the replay and cva-evaluate agree: with every pixel wrong, a map
    # reaches its optimum (Eq. (1) said 1 against an AUC of 0.95).
    d_gt = np.full((10, 10), 5.0)
    d_est = d_gt + 10.0
    scores = evaluate_confidence(np.random.default_rng(0).random((10, 10)), d_est, d_gt)
    assert scores['auc'] == pytest.approx(0.95) and scores['auc_opt'] == pytest.approx(0.95)
    for bad in (0, -3, 2.5, True):
        with pytest.raises(InputError, match='n_pixels must be an integer ≥ 1'):
            optimal_auc(0.5, bad)


def test_single_pixel_curve() -> None:
    density, rate = roc_curve(np.array([0.3]), np.array([True]))
    np.testing.assert_array_equal(density, [1.0])
    np.testing.assert_array_equal(rate, [1.0])
    assert roc_auc(np.array([0.3]), np.array([True])) == 0.0


@pytest.mark.parametrize(
    ('confidence', 'error', 'message'),
    [
        (np.zeros(3), np.zeros(4, dtype=bool), 'same shape'),
        (np.zeros(3), np.zeros(3), 'bool'),
        (np.zeros(0), np.zeros(0, dtype=bool), 'empty'),
        (np.array([0.1, np.nan]), np.zeros(2, dtype=bool), 'NaN'),
    ],
)
def test_roc_curve_rejects_bad_input(
    confidence: np.ndarray, error: np.ndarray, message: str
) -> None:
    with pytest.raises(InputError, match=message):
        roc_curve(confidence, error)


def test_evaluate_confidence_excludes_unknown_and_masked_pixels() -> None:
    d_gt = np.array([[10.0, 10.0, np.nan], [20.0, 20.0, 30.0]])
    d_est = np.array([[10.0, 15.0, 0.0], [20.0, np.nan, 30.0]])
    conf = np.array([[0.9, 0.1, 0.5], [0.8, 0.2, 0.7]])
    result = evaluate_confidence(conf, d_est, d_gt)
    assert result['n_pixels'] == 5
    assert result['error_rate'] == pytest.approx(2 / 5)
    assert result['auc_opt'] == pytest.approx(optimal_auc(0.4))
    # Wrong pixels have the lowest confidence: the curve equals the sampled optimum.
    assert result['auc'] == pytest.approx(roc_auc(conf[np.isfinite(d_gt)], np.array(
        [False, True, False, True, False])))
    mask = np.array([[True, False, True], [True, True, False]])
    masked = evaluate_confidence(conf, d_est, d_gt, mask=mask)
    assert masked['n_pixels'] == 3
    assert masked['error_rate'] == pytest.approx(1 / 3)


def test_every_evaluation_scores_alike() -> None:
    """cva-evaluate / the replay (score_confidence), evaluate_confidence and training validation
    all go through auc_scores: the same four numbers for the same pixels."""
    from cva_confidence_ros.evaluation.scene import score_confidence

    rng = np.random.default_rng(3)
    # eps near 1 on few pixels: optimal_auc's curve-range case must reach every caller.
    for n, eps in ((500, 0.3), (30, 0.97)):
        error = rng.random(n) < eps
        confidence = np.round(rng.random(n), 1)  # ties
        scores = auc_scores(confidence.reshape(-1, 10), error.reshape(-1, 10))
        assert scores == {
            'auc': roc_auc(confidence, error),
            'auc_opt': optimal_auc(float(error.mean()), n),
            'error_rate': float(error.mean()),
            'n_pixels': n,
        }
        scored = score_confidence(confidence, error)
        assert (scored.auc, scored.auc_opt, scored.error_rate, scored.n_pixels) == tuple(
            scores.values()
        )
        d_gt = np.full(n, 50.0)
        assert evaluate_confidence(confidence, np.where(error, 0.0, 50.0), d_gt) == scores
    with pytest.raises(InputError, match='error must be a bool array'):
        auc_scores(np.zeros(3), np.zeros(3))


def test_evaluate_confidence_without_ground_truth_fails() -> None:
    with pytest.raises(InputError, match='ground truth'):
        evaluate_confidence(np.zeros((2, 2)), np.zeros((2, 2)), np.full((2, 2), np.nan))


@pytest.mark.parametrize(
    ('confidence', 'dtype'),
    [
        (np.array(['0.1', '0.2']), '<U3'),
        (np.array([0.1 + 1j, 0.2]), 'complex128'),
        (np.array([True, False]), 'bool'),
        (np.array([0.1, None]), 'object'),
    ],
)
def test_roc_curve_needs_real_confidence(confidence: np.ndarray, dtype: str) -> None:
    error = np.array([True, False])
    with pytest.raises(InputError, match=f'confidence must hold real numbers.*{dtype}'):
        roc_curve(confidence, error)
    with pytest.raises(InputError, match='confidence must hold real numbers'):
        roc_auc(confidence, error)
    assert roc_auc(np.array([2, 1], np.int32), error) == roc_auc(np.array([0.2, 0.1]), error)


@pytest.mark.parametrize('name', ['d_est', 'd_gt'])
@pytest.mark.parametrize('bad', [np.array(['1', '2']), np.array([1 + 1j, 2]), np.ones(2, bool)])
def test_kitti_error_needs_real_disparities(name: str, bad: np.ndarray) -> None:
    arrays = {'d_est': np.array([1.0, 2.0]), 'd_gt': np.array([1.0, 2.0])}
    arrays[name] = bad
    with pytest.raises(InputError, match=f'{name} must hold real numbers.*{bad.dtype}'):
        kitti_error(**arrays)
    with pytest.raises(InputError, match=f'{name} must hold real numbers'):
        evaluate_confidence(np.array([0.1, 0.2]), **arrays)
    assert kitti_error(np.array([1, 9], np.uint8), np.array([1, 2])).tolist() == [False, True]


@pytest.mark.parametrize(
    'error_rate', ['x', None, np.array([0.1, 0.2]), True, np.bool_(False), np.array(True), 0.5j]
)
def test_optimal_auc_needs_a_real_scalar(error_rate: object) -> None:
    with pytest.raises(InputError, match='error_rate must be a real number in'):
        optimal_auc(error_rate)  # type: ignore[arg-type]


@pytest.mark.parametrize('error_rate', [np.float32(0.5), np.array(0.5), Fraction(1, 2)])
def test_optimal_auc_accepts_real_scalars(error_rate: object) -> None:
    assert optimal_auc(error_rate) == pytest.approx(0.5 + 0.5 * math.log(0.5))  # type: ignore[arg-type]
    assert optimal_auc(1) == 1.0 and optimal_auc(np.int64(0)) == 0.0

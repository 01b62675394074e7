"""Tests of the per-scene evaluation pieces on tiny hand-made arrays."""

from __future__ import annotations

import numpy as np
import pytest

from cva_confidence_ros.datasets import StereoSample
from cva_confidence_ros.errors import InputError
from cva_confidence_ros.evaluation import (
    evaluate_scene,
    overlay_threshold,
    score_confidence,
    select_pixels,
)
from cva_confidence_ros.metrics import optimal_auc


def test_select_pixels_all_and_subset() -> None:
    known = np.zeros((4, 5), dtype=bool)
    known[1, 1] = known[2, 3] = known[3, 0] = True
    ys, xs = select_pixels(known)
    assert ys.tolist() == [1, 2, 3] and xs.tolist() == [1, 3, 0]
    assert select_pixels(known, max_pixels=10)[0].size == 3
    ys, xs = select_pixels(known, max_pixels=2, seed=7)
    assert ys.size == 2 and known[ys, xs].all() and np.all(np.diff(ys * 5 + xs) > 0)
    again = select_pixels(known, max_pixels=2, seed=7)
    assert again[0].tolist() == ys.tolist() and again[1].tolist() == xs.tolist()
    with pytest.raises(InputError, match='max_pixels'):
        select_pixels(known, max_pixels=0)


def test_score_of_a_perfect_ranking_by_hand() -> None:
    # 20 pixels, the 4 wrong ones least confident: ROC samples k/20 carry 0 up to 16/20,
    # then 1/17, 2/18, 3/19, 4/20.
    confidence = np.arange(20, 0, -1, dtype=np.float32)
    error = np.zeros(20, dtype=bool)
    error[16:] = True
    score = score_confidence(confidence, error)
    rates = [0.0, 1 / 17, 2 / 18, 3 / 19, 4 / 20]
    expected = sum(0.05 * (a + b) / 2 for a, b in zip(rates[:-1], rates[1:], strict=True))
    assert score.auc == pytest.approx(expected)
    assert score.error_rate == pytest.approx(0.2)
    assert score.auc_opt == pytest.approx(optimal_auc(0.2))
    assert score.n_pixels == 20
    assert score.density[-1] == 1.0 and score.roc_error[-1] == pytest.approx(0.2)


def test_score_rejects_nan_and_empty() -> None:
    with pytest.raises(InputError, match='NaN'):
        score_confidence(np.array([0.5, np.nan]), np.array([False, True]))
    with pytest.raises(InputError, match='no pixels'):
        score_confidence(np.zeros(0), np.zeros(0, dtype=bool))


def test_overlay_threshold() -> None:
    assert overlay_threshold(np.array([0.0, 0.3, 1.0]), 0.4) == 0.5
    values = np.arange(1.0, 11.0)  # 1 … 10, not in [0, 1]: the ε-quantile
    assert overlay_threshold(values, 0.2) == pytest.approx(np.quantile(values, 0.2))


class _PatchOnly:
    """A stand-in learned method that only supports patch mode, recording its calls."""

    needs_right = False

    def __init__(self) -> None:
        self.calls: list[int] = []

    def __call__(self, inputs):  # pragma: no cover - must not be reached
        raise AssertionError('dense call in a pixel-subset run')

    def confidence_at(self, inputs, ys, xs):
        self.calls.append(len(ys))
        return np.where(np.abs(inputs.disparity[ys, xs] - 4.0) < 1.0, 0.9, 0.1)


def _shifted_sample(width: int = 48, height: int = 24, shift: int = 4) -> StereoSample:
    rng = np.random.default_rng(0)
    right = rng.integers(0, 256, (height, width + shift), dtype=np.uint8)
    left = np.ascontiguousarray(right[:, :width])
    right = np.ascontiguousarray(right[:, shift:])
    gt = np.full((height, width), float(shift), dtype=np.float32)
    gt[:, :shift] = np.nan  # no right pixel there
    return StereoSample('synthetic', 'shift4', left, right, gt)


def test_evaluate_scene_subset_uses_patch_mode_and_plots(tmp_path) -> None:
    from cva_confidence_ros.confidence import CONFIDENCE_METHODS

    patch = _PatchOnly()
    methods = {'learned': patch, 'score': CONFIDENCE_METHODS.get('score')()}
    records = evaluate_scene(
        _shifted_sample(), 'census_bm', methods, max_disparity=8, max_pixels=50, seed=1,
        plot_dir=tmp_path / 'plots',
    )
    assert patch.calls == [50]
    assert [r.method for r in records] == ['learned', 'score']
    assert all(r.n_pixels == 50 and r.scene == 'shift4' for r in records)
    # Random texture with a constant shift: the matcher gets (nearly) everything right.
    assert records[0].error_rate < 0.2
    assert sorted(p.name for p in (tmp_path / 'plots').iterdir()) == sorted([
        'disparity.png', 'roc.png', 'confidence_learned.png', 'confidence_score.png',
        'correct_learned.png', 'correct_score.png',
    ])


def test_evaluate_scene_rejects_wrong_map_shape() -> None:
    def bad(inputs):
        return np.zeros((2, 2), dtype=np.float32)

    with pytest.raises(InputError, match="'bad'"):
        evaluate_scene(_shifted_sample(), 'census_bm', {'bad': bad}, max_disparity=8)


def test_cva_net_patch_mode_equals_dense_mode(tmp_path) -> None:
    torch = pytest.importorskip('torch')
    from cva_confidence_ros.confidence import CONFIDENCE_METHODS
    from cva_confidence_ros.model import CVANet, save_weights

    torch.manual_seed(1)
    weights = save_weights(CVANet(16), tmp_path / 'w.pt', {'matcher': 'census_bm'})
    method = CONFIDENCE_METHODS.get('cva_net')(
        matcher='census_bm', max_disparity=16, weights=weights
    )
    sample = _shifted_sample()
    dense = evaluate_scene(sample, 'census_bm', {'cva_net': method}, max_disparity=16)
    # A subset at least as large as the known pixels is all of them, scored in patch mode.
    patch = evaluate_scene(
        sample, 'census_bm', {'cva_net': method}, max_disparity=16, max_pixels=10**6
    )
    assert patch[0].n_pixels == dense[0].n_pixels == 24 * 44
    assert patch[0].auc == pytest.approx(dense[0].auc, abs=1e-6)


def test_progress_bar_follows_the_network_and_is_removed(tmp_path, capsys) -> None:
    import torch

    from cva_confidence_ros.confidence import CONFIDENCE_METHODS
    from cva_confidence_ros.model import CVANet, save_weights

    torch.manual_seed(1)
    weights = save_weights(CVANet(16), tmp_path / 'w.pt', {'matcher': 'census_bm'})
    method = CONFIDENCE_METHODS.get('cva_net')(
        matcher='census_bm', max_disparity=16, weights=weights, tile_budget_mb=1.0
    )
    quiet = evaluate_scene(_shifted_sample(), 'census_bm', {'cva_net': method}, max_disparity=16)
    assert capsys.readouterr().err == ''
    shown = evaluate_scene(
        _shifted_sample(), 'census_bm', {'cva_net': method}, max_disparity=16, progress=True
    )
    err = capsys.readouterr().err
    assert 'census_bm cva_net' in err and 'px' in err
    assert shown[0].auc == quiet[0].auc and method.evaluator.progress is None


def test_auc_opt_never_exceeds_what_the_curve_can_reach() -> None:
    # Every pixel wrong: every ranking gives the curve 1 from its first density 1/20 on, an
    # area of 0.95; Eq. (1) says 1, which no confidence map could reach.
    score = score_confidence(np.linspace(0.0, 1.0, 100), np.ones(100, dtype=bool))
    assert score.auc == pytest.approx(0.95)
    assert score.auc_opt == pytest.approx(0.95) and score.auc >= score.auc_opt - 1e-12
    # ε = 0.98 > 0.95: the optimal curve 1 − 0.02 / p from 0.05 to 1.
    error = np.zeros(100, dtype=bool)
    error[2:] = True
    confidence = np.arange(100, 0, -1, dtype=np.float64)  # the 2 correct ones first
    score = score_confidence(confidence, error)
    assert score.auc_opt == pytest.approx(0.95 + 0.02 * np.log(0.05))
    # The perfect ranking meets it up to the trapezoid rule on its 5 % samples (Eq. (1),
    # 0.9018, was 0.013 above).
    assert score.auc == pytest.approx(score.auc_opt, abs=2e-3)
    assert optimal_auc(0.98) - score.auc > 0.01
    # One pixel, wrong: a one-point curve of area 0, and nothing better than 0 to reach.
    one = score_confidence(np.array([0.3]), np.array([True]))
    assert (one.auc, one.auc_opt, one.error_rate) == (0.0, 0.0, 1.0)
    # ε ≤ 0.95: the paper's Eq. (1) as before.
    error = np.zeros(100, dtype=bool)
    error[:30] = True
    assert score_confidence(np.ones(100), error).auc_opt == optimal_auc(0.3)


def test_a_float64_confidence_keeps_its_order() -> None:
    # Values 1e-9 apart are one float32 value; the ranking below is perfect in float64.
    confidence = np.array([1.0 - 1e-9, 1.0 - 2e-9] * 50)
    error = np.array([False, True] * 50)
    score = score_confidence(confidence, error)
    perfect = score_confidence(np.where(error, 0.0, 1.0), error)
    assert score.auc == pytest.approx(perfect.auc) and score.auc < 0.2
    # float32 input is scored exactly as before.
    as32 = confidence.astype(np.float32)
    assert score_confidence(as32, error).auc == pytest.approx(0.475)


def test_a_negative_seed_is_an_input_error() -> None:
    with pytest.raises(InputError, match='seed must be ≥ 0; got -1'):
        select_pixels(np.ones((3, 4), dtype=bool), max_pixels=2, seed=-1)

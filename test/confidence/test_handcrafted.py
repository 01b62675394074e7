"""Hand-crafted confidence measures on tiny hand-computed cost volumes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cva_confidence_ros.confidence import (
    CONFIDENCE_METHODS,
    ConfidenceInputs,
    compute_confidence,
    handcrafted,
)
from cva_confidence_ros.errors import ConfigError, InputError

# D = 4, H = 2, W = 3; curves per pixel (y, x). Column 0 as a matcher leaves it: one candidate
# (d = 0) with a partner, the filler 1.0 for the others; every measure but LRC gives it its
# lowest value (no matching decision there), so the hand values are of columns 1 and 2.
CURVES = {
    (0, 1): [0.5, 0.1, 0.3, 0.9],  # c1 = 0.1 at d = 1, c2 = 0.3
    (0, 2): [0.2, 0.2, 0.6, 1.0],  # two equal minima: c2 = c1 = 0.2
    (1, 1): [0.0, 0.4, 0.4, 0.8],  # perfect match: c1 = 0, c2 = 0.4
    (1, 2): [1.0, 0.7, 0.05, 0.6],  # c1 = 0.05 at d = 2, c2 = 0.6
}
COLUMN_0 = [0.05, 1.0, 1.0, 1.0]  # the most distinct minimum of all, with the filler


def small_volume() -> np.ndarray:
    volume = np.empty((4, 2, 3), dtype=np.float32)
    volume[:, :, 0] = np.asarray(COLUMN_0)[:, None]
    for (y, x), curve in CURVES.items():
        volume[:, y, x] = curve
    return volume


def inputs_for(volume: np.ndarray, **kwargs: np.ndarray | None) -> ConfidenceInputs:
    disparity = np.argmin(volume, axis=0).astype(np.float32)
    image = np.zeros(volume.shape[1:], dtype=np.uint8)
    return ConfidenceInputs(cost_volume=volume, disparity=disparity, image=image, **kwargs)


def test_registered_names() -> None:
    assert {'pkrn', 'mlm', 'lrd', 'lrc', 'score'} <= set(CONFIDENCE_METHODS.names())


def test_score_is_negated_minimum() -> None:
    result = compute_confidence('score', inputs_for(small_volume()))
    assert result.dtype == np.float32 and result.shape == (2, 3)
    np.testing.assert_allclose(result, [[-1.0, -0.1, -0.2], [-1.0, 0.0, -0.05]], rtol=1e-6)


def test_pkrn_naive_ratio() -> None:
    eps = 1e-3
    result = compute_confidence('pkrn', inputs_for(small_volume()), eps=eps)
    expected = [
        [1.0, (0.3 + eps) / (0.1 + eps), 1.0],
        [1.0, (0.4 + eps) / eps, (0.6 + eps) / (0.05 + eps)],
    ]
    assert result.dtype == np.float32
    np.testing.assert_allclose(result, expected, rtol=1e-5)


def test_mlm_softmax_at_minimum() -> None:
    sigma = math.sqrt(0.05)  # 2 sigma^2 = 0.1: exponents are -10 × (c - c1)
    result = compute_confidence('mlm', inputs_for(small_volume()), sigma=sigma)
    e = math.exp
    expected = [
        [0.25, 1 / (e(-4) + 1 + e(-2) + e(-8)), 1 / (2 + e(-4) + e(-8))],
        [0.25, 1 / (1 + 2 * e(-4) + e(-8)), 1 / (e(-9.5) + e(-6.5) + 1 + e(-5.5))],
    ]
    np.testing.assert_allclose(result, expected, rtol=1e-5)
    flat = compute_confidence('mlm', inputs_for(np.full((4, 1, 2), 0.5, np.float32)))
    assert flat[0, 1] == pytest.approx(0.25)


# H = 1, W = 4, D = 3. Left curves per column (column 0 as a matcher leaves it) and right
# curves per column.
LEFT = [[0.2, 1.0, 1.0], [0.5, 0.6, 0.05], [0.6, 0.3, 0.2], [0.9, 0.3, 0.4]]
RIGHT = [[0.3, 0.15, 0.25], [0.5, 0.6, 0.7], [0.5, 0.8, 1.0], [0.45, 1.0, 1.0]]


def row_volume(curves: list[list[float]]) -> np.ndarray:
    return np.asarray(curves, dtype=np.float32).T[:, None, :].copy()


def test_lrd_hand_values() -> None:
    eps = 1e-3
    inputs = inputs_for(row_volume(LEFT), cost_volume_right=row_volume(RIGHT))
    result = compute_confidence('lrd', inputs, eps=eps)
    # right minima per column: 0.15, 0.5, 0.5, 0.45; right column = x - d1.
    expected = [
        0.0,  # column 0: a single candidate, no decision (with the filler as c2 it was 16)
        0.0,  # d1 = 2 → column -1: outside the right image, lowest confidence
        (0.3 - 0.2) / (abs(0.2 - 0.15) + eps),  # d1 = 2 → column 0
        (0.4 - 0.3) / (abs(0.3 - 0.5) + eps),  # d1 = 1 → column 2
    ]
    np.testing.assert_allclose(result[0], expected, rtol=1e-5)


def test_lrc_hand_values() -> None:
    volume = np.zeros((3, 2, 4), dtype=np.float32)
    d_left = np.array([[0.0, 2.0, 2.0, 1.4], [np.nan, 0.0, 0.6, 0.0]], dtype=np.float32)
    d_right = np.array([[2.0, 0.0, 1.0, 5.0], [0.0, 0.0, 0.5, np.nan]], dtype=np.float32)
    inputs = ConfidenceInputs(
        cost_volume=volume,
        disparity=d_left,
        image=np.zeros((2, 4, 3), np.uint8),
        disparity_right=d_right,
    )
    result = compute_confidence('lrc', inputs)
    expected = [
        [-2.0, -3.0, 0.0, -0.4],  # x - d: 0, -1 (outside: -D), 0, round(1.4) = 1 → column 2
        [-3.0, 0.0, -0.6, -3.0],  # NaN left; column 1; round(0.6) = 1 → column 1; NaN right
    ]
    np.testing.assert_allclose(result, expected, rtol=1e-6)


def test_lrc_derives_right_disparity_from_right_volume() -> None:
    right = row_volume(RIGHT)  # arg-minima per column: 1, 0, 0, 0
    d_left = np.array([[0.0, 1.0, 2.0, 3.0]], dtype=np.float32)
    inputs = ConfidenceInputs(
        cost_volume=row_volume(LEFT),
        disparity=d_left,
        image=np.zeros((1, 4), np.uint8),
        cost_volume_right=right,
    )
    np.testing.assert_allclose(compute_confidence('lrc', inputs), [[-1.0, 0.0, -1.0, -2.0]])


@pytest.mark.parametrize('name', ['lrd', 'lrc'])
def test_right_view_methods_require_right_input(name: str) -> None:
    method = CONFIDENCE_METHODS.get(name)()
    assert method.needs_right
    with pytest.raises(InputError, match='right'):
        method(inputs_for(small_volume()))


@pytest.mark.parametrize('name', ['pkrn', 'mlm', 'score'])
def test_left_only_methods(name: str) -> None:
    assert not CONFIDENCE_METHODS.get(name)().needs_right


@pytest.mark.parametrize('name', ['pkrn', 'mlm', 'lrd', 'lrc', 'score'])
def test_factories_accept_and_ignore_generic_options(name: str) -> None:
    generic = {
        'matcher': 'census_bm',
        'max_disparity': 64,
        'weights': None,
        'device': 'cpu',
        'tile_budget_mb': 512.0,
    }
    method = CONFIDENCE_METHODS.get(name)(**generic)
    assert callable(method)
    with pytest.raises(ConfigError, match='unknown options'):
        CONFIDENCE_METHODS.get(name)(bogus=1)


@pytest.mark.parametrize(('name', 'options'), [('mlm', {'sigma': 0.0}), ('pkrn', {'eps': -1})])
def test_invalid_option_values(name: str, options: dict[str, float]) -> None:
    with pytest.raises(ConfigError, match='> 0'):
        CONFIDENCE_METHODS.get(name)(**options)


@pytest.mark.parametrize('name', ['pkrn', 'lrd'])
@pytest.mark.parametrize('eps', [1e-300, 1e300])
def test_eps_that_leaves_float32_is_refused(name: str, eps: float) -> None:
    # eps is added in float32: 1e-300 became 0 and 1e300 inf, and a perfect match (c1 = c2
    # = 0 here) came out as 0/0 or inf/inf = NaN instead of an error.
    with pytest.raises(ConfigError, match='eps must stay finite and > 0 in float32'):
        CONFIDENCE_METHODS.get(name)(eps=eps)
    # The smallest float32 eps still gives numbers, not NaN.
    volume = np.zeros((3, 2, 2), np.float32)
    inputs = inputs_for(volume, cost_volume_right=volume)
    assert not np.isnan(compute_confidence(name, inputs, eps=1e-44)).any()


def test_pkrn_needs_two_disparities() -> None:
    with pytest.raises(InputError, match='D ≥ 2'):
        compute_confidence('pkrn', inputs_for(np.zeros((1, 2, 2), np.float32)))


def test_row_blocks_give_the_same_result(monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(0)
    volume = rng.random((8, 7, 5), dtype=np.float32)
    right = rng.random((8, 7, 5), dtype=np.float32)
    inputs = inputs_for(volume, cost_volume_right=right)
    whole = {name: compute_confidence(name, inputs) for name in ('pkrn', 'mlm', 'lrd')}
    monkeypatch.setattr(handcrafted, '_BLOCK_VALUES', 8 * 5 * 2)  # two rows per block
    for name, expected in whole.items():
        np.testing.assert_array_equal(compute_confidence(name, inputs), expected)


def test_inputs_validation() -> None:
    volume = np.zeros((4, 2, 3), np.float32)
    image = np.zeros((2, 3), np.uint8)
    with pytest.raises(InputError, match=r'\(D, H, W\)'):
        ConfidenceInputs(np.zeros((2, 3), np.float32), np.zeros((2, 3)), image)
    with pytest.raises(InputError, match='disparity must have shape'):
        ConfidenceInputs(volume, np.zeros((3, 2)), image)
    with pytest.raises(InputError, match='image'):
        ConfidenceInputs(volume, np.zeros((2, 3)), np.zeros((2, 3, 4), np.uint8))
    with pytest.raises(InputError, match='cost_volume_right'):
        ConfidenceInputs(volume, np.zeros((2, 3)), image, cost_volume_right=volume[:2])
    converted = ConfidenceInputs(volume.astype(np.float64), np.zeros((2, 3), np.int32), image)
    assert converted.cost_volume.dtype == np.float32
    assert converted.disparity.dtype == np.float32
    assert converted.shape == (2, 3) and converted.max_disparity == 4

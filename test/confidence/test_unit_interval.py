"""Each confidence method maps its values into [0, 1] by a fixed increasing function."""

from __future__ import annotations

import numpy as np
import pytest

from cva_confidence_ros.confidence import CONFIDENCE_METHODS, ConfidenceInputs

HANDCRAFTED = ['pkrn', 'mlm', 'lrd', 'lrc', 'score']


def _inputs(seed: int = 0) -> ConfidenceInputs:
    rng = np.random.default_rng(seed)
    volume = rng.random((8, 6, 10), dtype=np.float32)
    right = rng.random((8, 6, 10), dtype=np.float32)
    return ConfidenceInputs(
        cost_volume=volume,
        disparity=volume.argmin(axis=0).astype(np.float32),
        image=np.zeros((6, 10), np.uint8),
        cost_volume_right=right,
        disparity_right=right.argmin(axis=0).astype(np.float32),
    )


@pytest.mark.parametrize('name', HANDCRAFTED)
def test_unit_interval_is_bounded_and_keeps_order(name: str) -> None:
    method = CONFIDENCE_METHODS.get(name)()
    raw = method(_inputs())
    unit = method.to_unit_interval(raw)
    assert unit.dtype == np.float32 and unit.shape == raw.shape
    assert unit.min() >= 0.0 and unit.max() <= 1.0
    order = np.argsort(raw.ravel(), kind='stable')
    assert np.all(np.diff(unit.ravel()[order]) >= 0)


def test_unit_interval_hand_values() -> None:
    pkrn = CONFIDENCE_METHODS.get('pkrn')()
    np.testing.assert_allclose(pkrn.to_unit_interval(np.array([1.0, 2.0, 4.0])), [0, 0.5, 0.75])
    score = CONFIDENCE_METHODS.get('score')()
    np.testing.assert_allclose(score.to_unit_interval(np.array([-1.0, -0.25, 0.0])), [0, 0.75, 1])
    lrc = CONFIDENCE_METHODS.get('lrc')()
    np.testing.assert_allclose(lrc.to_unit_interval(np.array([0.0, -1.0, -3.0])), [1, 0.5, 0.25])
    lrd = CONFIDENCE_METHODS.get('lrd')()
    np.testing.assert_allclose(lrd.to_unit_interval(np.array([0.0, 1.0, np.nan])), [0, 0.5, 0])

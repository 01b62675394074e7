"""The registered ``cva_net`` confidence method."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cva_confidence_ros.confidence import CONFIDENCE_METHODS, ConfidenceInputs, compute_confidence
from cva_confidence_ros.errors import InputError, ModelError
from cva_confidence_ros.model import CVANet, predict_confidence, save_weights

DEPTH = 16


@pytest.fixture(scope='module')
def weights(tmp_path_factory) -> tuple[CVANet, str]:
    torch.manual_seed(0)
    net = CVANet(DEPTH)
    path = tmp_path_factory.mktemp('w') / 'cvanet_census_bm_d16.pt'
    save_weights(net, path, {'matcher': 'census_bm'})
    return net, str(path)


def _inputs(depth: int = DEPTH, matcher: str = 'census_bm') -> ConfidenceInputs:
    rng = np.random.default_rng(0)
    volume = rng.random((depth, 14, 15), dtype=np.float32)
    return ConfidenceInputs(
        cost_volume=volume,
        disparity=volume.argmin(axis=0).astype(np.float32),
        image=np.zeros((14, 15), np.uint8),
        matcher=matcher,
    )


def test_registered_and_equal_to_predict_confidence(weights):
    net, path = weights
    assert 'cva_net' in CONFIDENCE_METHODS
    method = CONFIDENCE_METHODS.get('cva_net')(
        matcher='census_bm', max_disparity=DEPTH, weights=path, device='cpu', tile_budget_mb=64.0
    )
    assert method.needs_right is False
    inputs = _inputs()
    confidence = method(inputs)
    assert confidence.shape == (14, 15) and confidence.dtype == np.float32
    np.testing.assert_allclose(confidence, predict_confidence(net, inputs.cost_volume), atol=1e-5)
    ys, xs = np.array([0, 13, 6]), np.array([0, 14, 3])
    np.testing.assert_allclose(method.confidence_at(inputs, ys, xs), confidence[ys, xs], atol=1e-5)
    shortcut = compute_confidence(
        'cva_net', inputs, matcher='census_bm', max_disparity=DEPTH, weights=path
    )
    np.testing.assert_allclose(shortcut, confidence, atol=1e-6)


def test_depth_and_matcher_checks(weights):
    _, path = weights
    method = CONFIDENCE_METHODS.get('cva_net')(
        matcher='census_bm', max_disparity=DEPTH, weights=path
    )
    with pytest.raises(InputError, match='depth D = 16; got depth 20'):
        method(_inputs(depth=20))
    with pytest.raises(InputError, match='depth D = 16; got depth 20'):
        method.confidence_at(_inputs(depth=20), np.array([0]), np.array([0]))
    with pytest.raises(InputError, match="matcher 'census_bm'; got a cost volume of 'mccnn_fast'"):
        method(_inputs(matcher='mccnn_fast'))
    with pytest.raises(ModelError, match='asked for D = 32'):
        CONFIDENCE_METHODS.get('cva_net')(matcher='census_bm', max_disparity=32, weights=path)
    with pytest.raises(ModelError, match="asked for matcher 'census_sgm'"):
        CONFIDENCE_METHODS.get('cva_net')(matcher='census_sgm', max_disparity=DEPTH, weights=path)


def test_missing_shipped_weights_say_how_to_train():
    with pytest.raises(ModelError, match='cva-train'):
        CONFIDENCE_METHODS.get('cva_net')(matcher='no_such_matcher', max_disparity=DEPTH)

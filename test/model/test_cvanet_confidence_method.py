"""The registered ``cva_net`` confidence method."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from cva_confidence_ros.confidence import CONFIDENCE_METHODS, ConfidenceInputs, compute_confidence
from cva_confidence_ros.confidence.cva_net import CVANetConfidence
from cva_confidence_ros.errors import ConfigError, InputError, ModelError
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
    with pytest.raises(ConfigError, match='max_disparity must be an integer ≥ 1; got 16.5'):
        CONFIDENCE_METHODS.get('cva_net')(matcher='census_bm', max_disparity=16.5, weights=path)


@pytest.mark.parametrize('stride', [1, 2])
def test_pixels_outside_the_image_are_refused(weights, stride):
    # With a stride the map is computed whole and indexed: -1 must not read the last pixel.
    method = CONFIDENCE_METHODS.get('cva_net')(
        matcher='census_bm', max_disparity=DEPTH, weights=weights[1], cva_stride=stride
    )
    for ys, xs in [([-1], [0]), ([14], [0]), ([0], [15])]:
        with pytest.raises(InputError, match=r'pixel indices must lie in \[0, 14\) × \[0, 15\)'):
            method.confidence_at(_inputs(), np.array(ys), np.array(xs))
    with pytest.raises(InputError, match='integer pixel indices'):
        method.confidence_at(_inputs(), np.array([0.5]), np.array([1.0]))


def test_missing_shipped_weights_say_how_to_train():
    with pytest.raises(ModelError, match='cva-train'):
        CONFIDENCE_METHODS.get('cva_net')(matcher='no_such_matcher', max_disparity=DEPTH)


def test_sparse_options_through_the_pipeline_config(weights):
    from cva_confidence_ros.errors import ConfigError
    from cva_confidence_ros.pipeline import PipelineConfig, StereoPipeline

    _, path = weights
    inputs = _inputs()
    exact = compute_confidence('cva_net', inputs, max_disparity=DEPTH, weights=path)
    config = PipelineConfig(
        max_disparity=DEPTH,
        confidence_method='cva_net',
        model_path=path,
        device='cpu',
        cva_stride=4,
        cva_cascade='pkrn',
        cva_cascade_fraction=0.5,
    )
    pipeline = StereoPipeline(config)
    method = pipeline._method
    assert method.sparse.stride == 4 and method.sparse.cascade == 'pkrn'
    assert method.needs_right is False
    sparse = method(inputs)
    assert sparse.shape == exact.shape and np.all((sparse > 0) & (sparse < 1))
    assert not np.allclose(sparse, exact)  # it is not the exact path ...
    # ... but where the network ran, its value is kept.
    evaluated = method.evaluator.path_counts
    assert sum(evaluated.values()) >= 1
    ys, xs = np.array([1, 5]), np.array([1, 9])
    np.testing.assert_allclose(method.confidence_at(inputs, ys, xs), sparse[ys, xs], atol=1e-6)
    lrd = StereoPipeline(config.replace(cva_cascade='lrd'))._method
    assert lrd.needs_right is True
    left = np.random.default_rng(1).integers(0, 255, (20, 40), dtype=np.uint8)
    result = StereoPipeline(config.replace(cva_cascade='lrd')).process(left, np.roll(left, -3, 1))
    assert result.confidence.shape == (20, 40)
    for name, value in (
        ('cva_stride', 3),
        ('cva_cascade', 'score'),
        ('cva_cascade_fraction', 0.0),
        ('cva_precision', 'int8'),
    ):
        with pytest.raises(ConfigError, match=name):
            config.replace(**{name: value})
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match='fp16'):
            StereoPipeline(config.replace(cva_precision='fp16'))


def test_a_folder_as_weights_says_how_to_get_the_shipped_ones(tmp_path) -> None:
    # Path('') is Path('.'): a folder, where None or '' would have meant the shipped weights.
    with pytest.raises(ModelError, match=r"weights '\.' is a folder .*None or '' selects"):
        CVANetConfidence(max_disparity=64, weights=Path(''))
    with pytest.raises(ModelError, match='is a folder'):
        CVANetConfidence(max_disparity=64, weights=tmp_path)

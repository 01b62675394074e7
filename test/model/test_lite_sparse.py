"""CVA-Net-Lite behind the sparse paths: exact stride 1, grid values, own sizes and counts."""

from __future__ import annotations

from light_net_test_utils import peaked_volume, with_data_bn
import numpy as np
import pytest
import torch

from cva_confidence_ros.confidence import CONFIDENCE_METHODS, ConfidenceInputs
from cva_confidence_ros.confidence.cva_net_lite import CVANetLiteConfidence
from cva_confidence_ros.matching import wta_disparity
from cva_confidence_ros.model import (
    CVANetLite,
    SparseConfig,
    SparseEvaluator,
    dense_macs,
    predict_confidence,
    save_weights,
    tile_shape,
)
from cva_confidence_ros.model.inference import activations_per_pixel
from cva_confidence_ros.model.lite import condensed_depth, lite_activations_per_pixel
from cva_confidence_ros.model.sparse import grid_offset

DEPTH, HEIGHT, WIDTH = 24, 20, 28


pytestmark = pytest.mark.usefixtures('one_torch_thread')


def _volume(seed: int = 0) -> np.ndarray:
    return peaked_volume(seed, DEPTH, HEIGHT, WIDTH)


def _inputs(seed: int = 0) -> ConfidenceInputs:
    volume = _volume(seed)
    image = np.random.default_rng(seed).integers(0, 255, (HEIGHT, WIDTH, 3), dtype=np.uint8)
    return ConfidenceInputs(volume, wta_disparity(volume), image, matcher='census_bm')


@pytest.fixture(scope='module')
def net() -> CVANetLite:
    """A Lite network whose BN statistics come from data, so that folding is not trivial."""
    torch.manual_seed(0)
    return with_data_bn(CVANetLite(DEPTH), (_volume(seed + 10) for seed in range(3)))


@pytest.fixture(scope='module')
def weights(net, tmp_path_factory) -> str:
    folder = tmp_path_factory.mktemp('lite')
    path = folder / f'cvanet_lite_census_bm_d{DEPTH}.pt'
    return str(save_weights(net, path, {'matcher': 'census_bm'}))


@pytest.mark.parametrize('path', ['auto', 'tile', 'fused', 'extracts'])
def test_every_way_equals_exact(net, path):
    volume = _volume()
    exact = predict_confidence(net, volume)
    evaluator = SparseEvaluator(net, tile_budget_mb=0.2, path=path)  # several tiles
    rows, columns = tile_shape(HEIGHT, WIDTH, DEPTH, 0.2, activations_per_pixel(net, DEPTH))
    assert rows * columns < HEIGHT * WIDTH
    np.testing.assert_allclose(evaluator(volume), exact, atol=1e-4, rtol=0)


def test_stride_1_method_equals_exact(net, weights):
    inputs = _inputs()
    exact = predict_confidence(net, inputs.cost_volume)
    method = CONFIDENCE_METHODS.get('cva_net_lite')(
        matcher='census_bm', max_disparity=DEPTH, weights=weights, cva_stride=1
    )
    assert isinstance(method, CVANetLiteConfidence) and method.sparse.exact
    np.testing.assert_allclose(method(inputs), exact, atol=1e-4, rtol=0)


@pytest.mark.parametrize(
    'config',
    [
        SparseConfig(stride=2),
        SparseConfig(stride=4),
        SparseConfig(stride=8),
        SparseConfig(stride=4, cascade='pkrn', cascade_fraction=0.25),
        SparseConfig(stride=8, cascade='pkrn', cascade_fraction=0.5),
    ],
)
def test_sparse_configs_keep_lite_values(net, weights, config):
    inputs = _inputs(1)
    exact = predict_confidence(net, inputs.cost_volume)
    method = CONFIDENCE_METHODS.get('cva_net_lite')(
        matcher='census_bm',
        max_disparity=DEPTH,
        weights=weights,
        cva_stride=config.stride,
        cva_cascade=config.cascade,
        cva_cascade_fraction=config.cascade_fraction,
    )
    cheap = None if config.cascade == 'none' else CONFIDENCE_METHODS.get(config.cascade)()(inputs)
    result = method.evaluator.confidence(
        inputs.cost_volume, inputs.image, inputs.disparity, config, cheap
    )
    assert np.all((result.confidence > 0) & (result.confidence < 1))
    evaluated = result.evaluated
    assert 0 < evaluated.sum() < evaluated.size
    np.testing.assert_allclose(result.confidence[evaluated], exact[evaluated], atol=1e-4, rtol=0)
    if config.cascade == 'none':
        offset = grid_offset(config.stride)
        grid = np.zeros((HEIGHT, WIDTH), bool)
        grid[offset :: config.stride, offset :: config.stride] = True
        np.testing.assert_array_equal(evaluated, grid)
    np.testing.assert_allclose(method(inputs), result.confidence, atol=1e-6)


def test_stride_4_through_the_pipeline_config(net, weights):
    from cva_confidence_ros.pipeline import PipelineConfig, StereoPipeline

    config = PipelineConfig(
        matcher='census_bm',
        max_disparity=DEPTH,
        confidence_method='cva_net_lite',
        model_path=weights,
        device='cpu',
        cva_stride=4,
    )
    pipeline = StereoPipeline(config)
    method = pipeline._method
    assert isinstance(method, CVANetLiteConfidence)
    assert method.sparse.stride == 4 and method.sparse.cascade == 'none'
    left = np.random.default_rng(2).integers(0, 255, (HEIGHT, 48), dtype=np.uint8)
    result = pipeline.process(left, np.roll(left, -3, 1))
    assert result.confidence.shape == (HEIGHT, 48)
    # stride 4 ran the network on a sixteenth of the pixels, the dense-fusion way
    assert method.evaluator.path_counts['fused'] + method.evaluator.path_counts['extracts'] >= 1
    inputs = _inputs(3)
    exact = predict_confidence(net, inputs.cost_volume)
    sparse = method(inputs)
    grid = np.zeros((HEIGHT, WIDTH), bool)
    grid[grid_offset(4) :: 4, grid_offset(4) :: 4] = True
    np.testing.assert_allclose(sparse[grid], exact[grid], atol=1e-4, rtol=0)
    assert not np.allclose(sparse[~grid], exact[~grid], atol=1e-4)


def test_tiles_and_path_choice_use_the_networks_own_sizes(net):
    evaluator = SparseEvaluator(net)
    folded = evaluator.net
    values = lite_activations_per_pixel(DEPTH)
    assert values == max(DEPTH, 16 * condensed_depth(DEPTH))
    assert activations_per_pixel(folded, DEPTH) == activations_per_pixel(net, DEPTH) == values
    # Lite's activations are 32·D / values times smaller than CVA-Net's: larger tiles.
    lite_tile = tile_shape(400, 400, DEPTH, 8.0, values)
    cva_tile = tile_shape(400, 400, DEPTH, 8.0)
    assert lite_tile[0] * lite_tile[1] > 2 * cva_tile[0] * cva_tile[1]
    # The operation counts are Lite's own (counted on the folded network: the banded depth
    # matrices count their zeros), near its analytic multiply-adds, far below CVA-Net's.
    flops = evaluator._flops('tile', 16, 16)
    analytic = 2 * dense_macs('cvanet_lite', DEPTH, 16, 16)
    assert 0.8 * analytic <= flops <= 1.5 * analytic
    assert flops < 2 * dense_macs('cvanet', DEPTH, 16, 16) / 5
    volume = _volume()
    evaluator(volume)
    assert evaluator.path_counts['tile'] == 1
    single = np.zeros((HEIGHT, WIDTH), bool)
    single[5, 5] = True
    evaluator(volume, single)
    assert evaluator.path_counts['extracts'] == 1
    quarter = np.zeros_like(single)
    quarter[::2, ::2] = True
    evaluator(volume, quarter)
    assert evaluator.path_counts['fused'] == 1

"""CVA-Net-Fast: CVA-Net's contract (shapes, checks, folding, tiles, pixels, sparse paths,
weights) and its WTA-aligned inputs (compiled kernel = torch ops)."""

from __future__ import annotations

from light_net_test_utils import (
    check_confidence_method,
    check_registered_saved_and_loaded,
    gradient_step_losses,
    peaked_volume,
    with_data_bn,
)
import numpy as np
import pytest
import torch

from cva_confidence_ros.confidence import CONFIDENCE_METHODS, ConfidenceInputs
from cva_confidence_ros.errors import ConfigError, InputError, ModelError
from cva_confidence_ros.model import (
    PATCH_SIZE,
    CVANetFast,
    FoldedCVANetFast,
    SparseEvaluator,
    default_weights_path,
    predict_confidence,
    predict_confidence_at,
    tile_shape,
)
from cva_confidence_ros.model.fast import FAST_ALIGN, FAST_INPUTS, aligned_curve
from cva_confidence_ros.model.inference import activations_per_pixel

DEPTH, HEIGHT, WIDTH = 24, 18, 21


pytestmark = pytest.mark.usefixtures('one_torch_thread')


def _volume(seed: int = 0, depth: int = DEPTH) -> np.ndarray:
    return peaked_volume(seed, depth, HEIGHT, WIDTH)


@pytest.fixture(scope='module')
def net() -> CVANetFast:
    """A network whose BN statistics come from data, so that folding is not trivial."""
    torch.manual_seed(0)
    volumes = (np.pad(_volume(seed + 10), ((0, 0), (6, 6), (6, 6))) for seed in range(3))
    return with_data_bn(CVANetFast(DEPTH), volumes)


def test_aligned_curve_reads_the_costs_around_the_wta_minimum():
    costs = torch.full((1, 12, 1, 3), 0.9)
    costs[0, 5, 0, 0] = 0.1  # minimum inside: the 9 costs around it
    costs[0, 4, 0, 0] = 0.3
    costs[0, 1, 0, 1] = 0.2  # near the low end: d − 4 … d − 2 are outside → 1.0
    costs[0, :, 0, 2] = 0.5  # a flat curve: ties go to d = 0
    for grad in (False, True):  # compiled kernel, torch ops
        source = costs.clone().requires_grad_(grad)
        with torch.set_grad_enabled(grad):
            out = aligned_curve(source).detach()
        assert out.shape == (1, FAST_INPUTS, 1, 3)
        expected = torch.full((9,), 0.9)
        expected[FAST_ALIGN], expected[FAST_ALIGN - 1] = 0.1, 0.3
        assert torch.equal(out[0, :9, 0, 0], expected)
        assert out[0, 9, 0, 0] == pytest.approx(5 / 12)
        assert torch.equal(out[0, :3, 0, 1], torch.ones(3))
        assert out[0, FAST_ALIGN, 0, 1] == pytest.approx(0.2)
        assert out[0, 9, 0, 1] == pytest.approx(1 / 12)
        assert out[0, 9, 0, 2] == 0
        assert torch.equal(out[0, FAST_ALIGN:9, 0, 2], torch.full((5,), 0.5))


def test_compiled_kernel_equals_torch_ops():
    rng = np.random.default_rng(4)
    costs = torch.from_numpy(rng.random((2, 40, 15, 17), dtype=np.float32))
    costs[:, :, :4, :4] = 0.0  # ties, as in the zero-padded border
    compiled = aligned_curve(costs)
    reference = aligned_curve(costs.clone().requires_grad_(True)).detach()
    assert torch.equal(compiled, reference)


@pytest.mark.parametrize('batch', [1, 3])
def test_shapes_of_extracts_and_images(net, batch):
    extracts = torch.rand(batch, 1, DEPTH, PATCH_SIZE, PATCH_SIZE)
    assert net(extracts).shape == (batch, 1, 1)
    image = torch.rand(batch, 1, DEPTH, HEIGHT + 12, WIDTH + 12)
    confidence = net(image)
    assert confidence.shape == (batch, HEIGHT, WIDTH)
    assert torch.all((confidence >= 0) & (confidence <= 1)) and confidence.std() > 1e-3
    assert torch.allclose(torch.sigmoid(net.forward_logits(image)), confidence)


def test_receptive_field_is_13x13(net):
    """An output changes only with inputs inside its own 13×13 window."""
    volume = torch.rand(1, 1, DEPTH, 30, 30)
    base = net(volume)[0]
    changed = volume.clone()
    changed[..., 20, 20] = torch.flip(changed[..., 20, 20], dims=[-1])  # moves the minimum
    diff = (net(changed)[0] - base).abs() > 0
    rows, cols = np.nonzero(diff.numpy())
    assert rows.min() >= 14 - 6 and rows.max() <= 14 + 6
    assert cols.min() >= 14 - 6 and cols.max() <= 14 + 6
    assert diff[14, 14]


def test_bad_inputs_and_settings(net):
    with pytest.raises(InputError, match='depth D = 24'):
        net(torch.rand(1, 1, DEPTH + 1, 13, 13))
    with pytest.raises(InputError, match='shape'):
        net(torch.rand(1, DEPTH, 13, 13))
    with pytest.raises(InputError, match='at least 13'):
        net(torch.rand(1, 1, DEPTH, 12, 13))
    with pytest.raises(ConfigError, match='>= 9'):
        CVANetFast(8)
    with pytest.raises(ConfigError, match='dropout'):
        CVANetFast(DEPTH, dropout=1.0)


def test_folded_equals_eval_and_is_inference_only(net):
    folded = net.fold_batchnorm()
    assert isinstance(folded, FoldedCVANetFast) and folded.is_folded
    assert folded.max_disparity == DEPTH
    assert not any(p.requires_grad for p in folded.parameters())
    volume = torch.from_numpy(np.pad(_volume(), ((0, 0), (6, 6), (6, 6))))[None, None]
    with torch.no_grad():
        expected = net.forward_logits(volume)
    got = folded.forward_logits(volume)
    assert torch.allclose(got, expected, atol=1e-4, rtol=1e-5)
    assert torch.allclose(folded(volume), torch.sigmoid(expected), atol=1e-5)
    # The split the sparse evaluation uses gives the same logits.
    fused = folded.fusion_features(volume)
    assert fused.shape == (1, 32, 1, HEIGHT, WIDTH)
    curves = fused.permute(0, 3, 4, 1, 2).reshape(HEIGHT * WIDTH, 32, 1)
    assert torch.allclose(folded.head_logits(curves).reshape(HEIGHT, WIDTH), got[0], atol=1e-5)
    assert net.training is False


def test_tiled_whole_and_pixel_inference_agree(net):
    volume = _volume(3)
    whole = predict_confidence(net, volume, tile_budget_mb=1000.0)
    tiled = predict_confidence(net, volume, tile_budget_mb=0.02)  # many small tiles
    rows, columns = tile_shape(HEIGHT, WIDTH, DEPTH, 0.02, activations_per_pixel(net, DEPTH))
    assert rows * columns < HEIGHT * WIDTH
    unfolded = predict_confidence(net, volume, fold_bn=False)
    np.testing.assert_allclose(tiled, whole, atol=1e-5)
    np.testing.assert_allclose(unfolded, whole, atol=1e-5)
    ys, xs = np.array([0, 5, HEIGHT - 1, 9]), np.array([0, 7, WIDTH - 1, WIDTH - 1])
    at = predict_confidence_at(net, volume, ys, xs, batch_size=3)
    np.testing.assert_allclose(at, whole[ys, xs], atol=1e-5)
    assert whole.std() > 1e-3  # a flat map would make the comparisons vacuous


@pytest.mark.parametrize('path', ['auto', 'tile', 'fused', 'extracts'])
def test_every_sparse_way_equals_exact(net, path):
    volume = _volume(1)
    exact = predict_confidence(net, volume)
    evaluator = SparseEvaluator(net, tile_budget_mb=0.05, path=path)
    np.testing.assert_allclose(evaluator(volume), exact, atol=1e-4, rtol=0)


def test_gradient_step_lowers_the_loss():
    torch.manual_seed(1)
    losses = gradient_step_losses(CVANetFast(DEPTH, dropout=0.0).train(), _volume, HEIGHT, WIDTH)
    assert losses[-1] < losses[0]


def test_registered_saved_and_loaded(net, tmp_path):
    check_registered_saved_and_loaded(net, 'cvanet_fast', DEPTH, tmp_path, _volume(5))


def test_confidence_method(net, tmp_path):
    check_confidence_method(
        net, 'cvanet_fast', 'cva_net_fast', DEPTH, tmp_path, lambda depth: _volume(7, depth)
    )


def test_missing_shipped_weights_say_how_to_train():
    with pytest.raises(ModelError, match='cva-train --arch cvanet_fast'):
        default_weights_path('census_bm', 40, 'cvanet_fast')


@pytest.mark.parametrize(
    ('matcher', 'depth'),
    [(m, d) for d in (64, 128, 256) for m in ('census_bm', 'census_sgm', 'mccnn_fast')],
)
def test_shipped_weights_load_and_run(matcher, depth):
    """The weights in models/: found by default, for their matcher and D, with a card; a clean
    minimum is trusted more than a flat curve."""
    path = default_weights_path(matcher, depth, 'cvanet_fast')
    assert path.name == f'cvanet_fast_{matcher}_d{depth}.pt'
    assert path.with_suffix('.md').is_file() and path.with_suffix('.yaml').is_file()
    method = CONFIDENCE_METHODS.get('cva_net_fast')(matcher=matcher, max_disparity=depth)
    assert method.meta['arch'] == 'cvanet_fast' and method.meta['samples_seen'] > 0
    rng = np.random.default_rng(0)
    truth = np.full((24, 40), 20)
    d = np.arange(depth)[:, None, None]
    volume = np.clip(np.abs(d - truth) / 8.0, 0, 1).astype(np.float32)
    volume[:, :, 20:] = 0.5 + rng.random((depth, 24, 20), dtype=np.float32) * 0.02  # flat, noisy
    inputs = ConfidenceInputs(
        cost_volume=volume,
        disparity=volume.argmin(axis=0).astype(np.float32),
        image=np.zeros((24, 40), np.uint8),
        matcher=matcher,
    )
    confidence = method(inputs)
    assert confidence.shape == (24, 40) and np.all((confidence >= 0) & (confidence <= 1))
    assert confidence[6:18, 2:12].mean() > confidence[6:18, 28:38].mean()

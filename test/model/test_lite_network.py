"""CVA-Net-Lite: CVA-Net's contract (shapes, checks, folding, tiles, pixels, weights)."""

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
    CVANetLite,
    FoldedCVANetLite,
    default_weights_path,
    predict_confidence,
    predict_confidence_at,
)
from cva_confidence_ros.model.lite import condensed_depth

DEPTH, HEIGHT, WIDTH = 24, 18, 21


pytestmark = pytest.mark.usefixtures('one_torch_thread')


def _volume(seed: int = 0, depth: int = DEPTH) -> np.ndarray:
    return peaked_volume(seed, depth, HEIGHT, WIDTH)


@pytest.fixture(scope='module')
def net() -> CVANetLite:
    """A network whose BN statistics come from data, so that folding is not trivial."""
    torch.manual_seed(0)
    return with_data_bn(CVANetLite(DEPTH), (_volume(seed + 10) for seed in range(3)))


@pytest.mark.parametrize('batch', [1, 3])
def test_shapes_of_extracts_and_images(net, batch):
    extracts = torch.rand(batch, 1, DEPTH, PATCH_SIZE, PATCH_SIZE)
    assert net(extracts).shape == (batch, 1, 1)
    image = torch.rand(batch, 1, DEPTH, HEIGHT + 12, WIDTH + 12)
    confidence = net(image)
    assert confidence.shape == (batch, HEIGHT, WIDTH)
    assert torch.all((confidence > 0) & (confidence < 1))
    logits = net.forward_logits(image)
    assert torch.allclose(torch.sigmoid(logits), confidence)


def test_receptive_field_is_13x13(net):
    """An output changes only with inputs inside its own 13×13 window."""
    volume = torch.rand(1, 1, DEPTH, 30, 30)
    base = net(volume)[0]
    changed = volume.clone()
    changed[..., 20, 20] = 1.0 - changed[..., 20, 20]  # input (20, 20) = output (14, 14) + 6
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
    with pytest.raises(ConfigError, match='>= 8'):
        CVANetLite(7)
    with pytest.raises(ConfigError, match='dropout'):
        CVANetLite(DEPTH, dropout=1.0)


def test_condensed_depth():
    assert [condensed_depth(d) for d in (8, 11, 12, 64, 128)] == [1, 1, 2, 15, 31]


def test_folded_equals_eval_and_is_inference_only(net):
    folded = net.fold_batchnorm()
    assert isinstance(folded, FoldedCVANetLite) and folded.is_folded
    assert folded.max_disparity == DEPTH
    assert not any(p.requires_grad for p in folded.parameters())
    volume = torch.from_numpy(np.pad(_volume(), ((0, 0), (6, 6), (6, 6))))[None, None]
    with torch.no_grad():
        expected = net.forward_logits(volume)
    got = folded.forward_logits(volume)
    assert torch.allclose(got, expected, atol=1e-4, rtol=1e-5)
    assert torch.allclose(folded(volume), torch.sigmoid(expected), atol=1e-5)
    assert net.training is False


def test_tiled_whole_and_pixel_inference_agree(net):
    volume = _volume(3)
    whole = predict_confidence(net, volume, tile_budget_mb=1000.0)
    tiled = predict_confidence(net, volume, tile_budget_mb=0.05)  # many small tiles
    unfolded = predict_confidence(net, volume, fold_bn=False)
    np.testing.assert_allclose(tiled, whole, atol=1e-5)
    np.testing.assert_allclose(unfolded, whole, atol=1e-5)
    ys, xs = np.array([0, 5, HEIGHT - 1, 9]), np.array([0, 7, WIDTH - 1, WIDTH - 1])
    at = predict_confidence_at(net, volume, ys, xs, batch_size=3)
    np.testing.assert_allclose(at, whole[ys, xs], atol=1e-5)
    assert whole.std() > 1e-3  # a flat map would make the comparisons vacuous


def test_gradient_step_lowers_the_loss():
    torch.manual_seed(1)
    losses = gradient_step_losses(CVANetLite(DEPTH, dropout=0.0).train(), _volume, HEIGHT, WIDTH)
    assert losses[-1] < losses[0]


def test_registered_saved_and_loaded(net, tmp_path):
    check_registered_saved_and_loaded(net, 'cvanet_lite', DEPTH, tmp_path, _volume(5))


def test_confidence_method(net, tmp_path):
    factory = check_confidence_method(
        net, 'cvanet_lite', 'cva_net_lite', DEPTH, tmp_path, lambda depth: _volume(7, depth)
    )
    path = tmp_path / 'cvanet_lite_census_bm_d24.pt'
    with pytest.raises(ModelError, match="matcher 'census_bm'"):
        factory(matcher='census_sgm', max_disparity=DEPTH, weights=str(path))


def test_missing_shipped_weights_say_how_to_train():
    with pytest.raises(ModelError, match='cva-train --arch cvanet_lite'):
        default_weights_path('census_bm', 40, 'cvanet_lite')
    with pytest.raises(ModelError, match='cvanet_lite_census_bm_d40.pt'):
        CONFIDENCE_METHODS.get('cva_net_lite')(matcher='census_bm', max_disparity=40)


@pytest.mark.parametrize('matcher', ['census_bm', 'census_sgm', 'mccnn_fast'])
def test_shipped_weights_load_and_run(matcher):
    """The weights in models/: found by default, for their matcher and D = 64, with a card."""
    path = default_weights_path(matcher, 64, 'cvanet_lite')
    assert path.name == f'cvanet_lite_{matcher}_d64.pt'
    assert path.with_suffix('.md').is_file() and path.with_suffix('.yaml').is_file()
    method = CONFIDENCE_METHODS.get('cva_net_lite')(matcher=matcher, max_disparity=64)
    assert method.meta['arch'] == 'cvanet_lite' and method.meta['samples_seen'] > 0
    rng = np.random.default_rng(0)
    truth = rng.integers(0, 64, size=(16, 20))
    volume = np.clip(np.abs(np.arange(64)[:, None, None] - truth) / 8.0, 0, 1).astype(np.float32)
    volume += rng.random(volume.shape, dtype=np.float32) * 0.05
    inputs = ConfidenceInputs(
        cost_volume=np.clip(volume, 0, 1),
        disparity=truth.astype(np.float32),
        image=np.zeros((16, 20), np.uint8),
        matcher=matcher,
    )
    confidence = method(inputs)
    assert confidence.shape == (16, 20) and np.all((confidence > 0) & (confidence < 1))

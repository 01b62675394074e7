"""Whole-image, tiled, per-pixel and BN-folded inference agree."""

from __future__ import annotations

from light_net_test_utils import with_data_bn
import numpy as np
import pytest
import torch

from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.model import (
    CVANet,
    fold_batchnorm,
    predict_confidence,
    predict_confidence_at,
    tile_shape,
)

DEPTH, HEIGHT, WIDTH = 16, 20, 24


pytestmark = pytest.mark.usefixtures('one_torch_thread')


def _volume(seed: int = 0) -> np.ndarray:
    """A cost volume with structure: a minimum at a per-pixel disparity, plus noise."""
    rng = np.random.default_rng(seed)
    truth = rng.integers(0, DEPTH, size=(HEIGHT, WIDTH))
    d = np.arange(DEPTH)[:, None, None]
    volume = np.minimum(1.0, np.abs(d - truth[None]) / 4.0) + rng.normal(
        0, 0.1, (DEPTH, HEIGHT, WIDTH)
    )
    return np.clip(volume, 0.0, 1.0).astype(np.float32)


@pytest.fixture(scope='module')
def net() -> CVANet:
    """A network whose BN statistics come from data, so that eval outputs are not flat."""
    torch.manual_seed(0)
    return with_data_bn(CVANet(DEPTH), [_volume(seed + 10) for seed in range(3)])


def test_output_varies(net):
    confidence = predict_confidence(net, _volume())
    assert confidence.shape == (HEIGHT, WIDTH) and confidence.dtype == np.float32
    assert np.all((confidence > 0) & (confidence < 1))
    assert confidence.std() > 1e-2


def test_tiled_equals_whole_equals_patch(net):
    volume = _volume()
    whole = predict_confidence(net, volume, tile_budget_mb=1e3, fold_bn=False)
    assert tile_shape(HEIGHT, WIDTH, DEPTH, 1e3) == (HEIGHT, WIDTH)
    budget = 2.0
    rows, columns = tile_shape(HEIGHT, WIDTH, DEPTH, budget)
    assert rows < HEIGHT and columns < WIDTH  # several tiles in both directions
    tiled = predict_confidence(net, volume, tile_budget_mb=budget, fold_bn=False)
    ys, xs = np.mgrid[:HEIGHT, :WIDTH]
    patch = predict_confidence_at(
        net, volume, ys.ravel(), xs.ravel(), batch_size=97, fold_bn=False
    )
    np.testing.assert_allclose(tiled, whole, atol=1e-5, rtol=0)
    np.testing.assert_allclose(patch.reshape(HEIGHT, WIDTH), whole, atol=1e-5, rtol=0)
    # The network module itself on the zero-padded volume gives the same.
    padded = np.pad(volume, ((0, 0), (6, 6), (6, 6)))
    with torch.no_grad():
        direct = net(torch.from_numpy(padded)[None, None])[0].numpy()
    np.testing.assert_allclose(direct, whole, atol=1e-5, rtol=0)


def test_folded_batchnorm_matches(net):
    volume = _volume(1)
    plain = predict_confidence(net, volume, fold_bn=False)
    folded = predict_confidence(net, volume, fold_bn=True, tile_budget_mb=2.0)
    np.testing.assert_allclose(folded, plain, atol=1e-5, rtol=0)
    assert not any(
        isinstance(m, torch.nn.modules.batchnorm._BatchNorm) for m in fold_batchnorm(net).modules()
    )
    ys, xs = np.array([0, 19, 7]), np.array([0, 23, 11])
    np.testing.assert_allclose(
        predict_confidence_at(net, volume, ys, xs), plain[ys, xs], atol=1e-5
    )


def test_train_mode_is_restored(net):
    net.train()
    try:
        predict_confidence(net, _volume(), fold_bn=False)
        assert net.training
    finally:
        net.eval()


def test_bad_inputs(net):
    volume = _volume()
    with pytest.raises(InputError, match='depth D = 16'):
        predict_confidence(net, volume[:15])
    with pytest.raises(InputError, match=r'\(D, H, W\)'):
        predict_confidence(net, volume[0])
    with pytest.raises(InputError, match=r'\[0, 1\]'):
        predict_confidence(net, volume * 3)
    with pytest.raises(InputError, match='NaN'):
        predict_confidence(net, np.full_like(volume, np.nan))
    with pytest.raises(InputError, match='lie in'):
        predict_confidence_at(net, volume, np.array([HEIGHT]), np.array([0]))
    with pytest.raises(InputError, match='integer'):
        predict_confidence_at(net, volume, np.array([1.5]), np.array([0.0]))
    with pytest.raises(ConfigError, match='tile_budget_mb'):
        predict_confidence(net, volume, tile_budget_mb=0)
    with pytest.raises(ConfigError, match='device'):
        predict_confidence(net, volume, device='tpu')


BAD_BUDGETS = [0, -1.0, float('nan'), float('inf'), '1', None, True]


@pytest.mark.parametrize('budget', BAD_BUDGETS, ids=repr)
def test_tile_budget_must_be_a_finite_positive_number(net, budget):
    with pytest.raises(ConfigError, match='tile_budget_mb must be a finite number > 0'):
        tile_shape(HEIGHT, WIDTH, DEPTH, budget)
    with pytest.raises(ConfigError, match='tile_budget_mb must be a finite number > 0'):
        predict_confidence(net, _volume(), tile_budget_mb=budget)


@pytest.mark.parametrize('batch_size', [0, 1.5, 4.0, float('nan'), '4', None, True], ids=repr)
def test_batch_size_must_be_a_positive_integer(net, batch_size):
    ys, xs = np.array([0, 5]), np.array([1, 7])
    with pytest.raises(ConfigError, match='batch_size must be an integer >= 1'):
        predict_confidence_at(net, _volume(), ys, xs, batch_size=batch_size)


def test_numpy_budget_and_batch_size_are_accepted(net):
    assert tile_shape(HEIGHT, WIDTH, DEPTH, np.float32(0.5)) == tile_shape(
        HEIGHT, WIDTH, DEPTH, 0.5
    )
    ys, xs = np.array([0, 5, 19]), np.array([1, 7, 23])
    np.testing.assert_array_equal(
        predict_confidence_at(net, _volume(), ys, xs, batch_size=np.int64(2)),
        predict_confidence_at(net, _volume(), ys, xs, batch_size=2),
    )


def test_empty_pixel_list(net):
    assert predict_confidence_at(net, _volume(), np.array([], int), np.array([], int)).shape == (
        0,
    )


@pytest.mark.skipif(not torch.cuda.is_available(), reason='no CUDA device')
def test_cuda_matches_cpu(net):
    volume = _volume()
    cpu = predict_confidence(net, volume)
    np.testing.assert_allclose(predict_confidence(net, volume, device='cuda'), cpu, atol=1e-4)

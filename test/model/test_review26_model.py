"""Review 26 of the model modules: regression tests for what it found."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.model import (
    CVANet,
    CVANetFast,
    CVANetLite,
    dense_macs,
    fold_batchnorm,
    macs_per_pixel,
    predict_confidence,
    predict_confidence_at,
)
from cva_confidence_ros.model.fast import aligned_curve
from cva_confidence_ros.model.sparse import SparseEvaluator

DEPTH = 16
ARCHS = [CVANet, CVANetLite, CVANetFast]


def _volume(shape=(DEPTH, 5, 6), seed=0):
    return np.random.default_rng(seed).random(shape).astype(np.float32)


def test_folded_cvanet_checks_its_input_as_the_light_folded_networks_do():
    # Was a RuntimeError from deep inside torch ("shape '[1, 1, 1]' is invalid for input of
    # size 5", "Kernel size can't be greater than actual input size").
    folded = fold_batchnorm(CVANet(DEPTH))
    with pytest.raises(InputError, match='depth D = 16; got depth 20'):
        folded(torch.rand(1, 1, 20, 13, 13))
    with pytest.raises(InputError, match='depth D = 16; got depth 14'):
        folded(torch.rand(1, 1, 14, 13, 13))
    with pytest.raises(InputError, match='at least 13×13'):
        folded(torch.rand(1, 1, DEPTH, 12, 13))
    with pytest.raises(InputError, match='shape'):
        folded(torch.rand(1, DEPTH, 13, 13))


@pytest.mark.parametrize('arch', ARCHS)
def test_integer_cost_volumes_are_refused(arch):
    # CVA-Net-Fast returned confidence 1.0 for a uint8 volume (0..255) without a word; the
    # others failed inside torch.
    net = arch(DEPTH).eval()
    volume = torch.randint(0, 256, (1, 1, DEPTH, 13, 13), dtype=torch.uint8)
    with torch.no_grad():
        for module in (net, net.fold_batchnorm()):
            with pytest.raises(InputError, match='floating-point.*uint8'):
                module(volume)
            with pytest.raises(InputError, match='floating-point.*int64'):
                module(volume.long())


def test_compiled_wta_kernel_takes_nan_as_argmin_does():
    # The compiled kernel skipped a NaN cost away from the minimum (a finite confidence)
    # where the torch version, argmin, takes the first NaN as the minimum (NaN out).
    costs = torch.rand(2, DEPTH, 3, 4, generator=torch.Generator().manual_seed(0))
    costs[0, 10, 0, 0] = float('nan')  # NaN far from the minimum
    costs[0, 3, 0, 0] = 0.0
    costs[0, 0, 1, 1] = float('nan')  # NaN first
    costs[1, 5, 2, 3] = float('nan')  # two NaNs: the first one counts
    costs[1, 12, 2, 3] = float('nan')
    costs[1, 1, 2, 3] = 0.0
    costs[1, :, 0, 2] = float('nan')  # all NaN
    compiled = aligned_curve(costs)
    with torch.enable_grad():
        through_torch = aligned_curve(costs.clone().requires_grad_(True)).detach()
    torch.testing.assert_close(compiled, through_torch, equal_nan=True, rtol=0, atol=0)
    net = CVANetFast(DEPTH).eval()
    volume = torch.rand(1, 1, DEPTH, 13, 13)
    volume[0, 0, 3, 6, 6] = 0.0
    volume[0, 0, 10, 6, 6] = float('nan')
    with torch.no_grad():
        assert torch.isnan(net(volume)).all()
        assert torch.isnan(net.fold_batchnorm()(volume)).all()


def test_mac_counts_refuse_depths_no_network_has():
    # 'cvanet' at D = 12 gave -4 028 368 multiply-adds, D = True a negative count, D = 64.5
    # the count of D = 64; a fractional tile side a fractional count.
    for arch, below in (('cvanet', 12), ('cvanet_lite', 7), ('cvanet_fast', 8)):
        with pytest.raises(ConfigError, match=f'max_disparity must be an integer >= {below + 1}'):
            macs_per_pixel(arch, below)
        assert macs_per_pixel(arch, below + 1) > 0
        assert macs_per_pixel(arch, np.int64(64)) == macs_per_pixel(arch, 64)
    for depth in (64.5, True, -3, '64'):
        with pytest.raises(ConfigError, match='max_disparity must be an integer'):
            macs_per_pixel('cvanet', depth)
    with pytest.raises(ConfigError, match='height and width must be integers'):
        dense_macs('cvanet', 64, 2.5, 3)
    assert dense_macs('cvanet', 64, np.int64(2), 3) == dense_macs('cvanet', 64, 2, 3)


@pytest.mark.parametrize('arch', ARCHS)
@pytest.mark.parametrize('dtype', [torch.float64, torch.bfloat16])
def test_unfolded_inference_runs_a_network_of_another_dtype(arch, dtype):
    # fold_bn=False fed float32 tiles to a float64 / bfloat16 network: "mixed dtype (CPU)".
    torch.manual_seed(0)
    net = arch(DEPTH)
    volume = _volume()
    exact = predict_confidence(net, volume)
    converted = arch(DEPTH)
    converted.load_state_dict(net.state_dict())
    converted.to(dtype).train()
    tolerance = 1e-6 if dtype == torch.float64 else 2e-2
    whole = predict_confidence(converted, volume, fold_bn=False, tile_budget_mb=0.01)
    np.testing.assert_allclose(whole, exact, atol=tolerance)
    ys, xs = np.array([0, 4, 2]), np.array([5, 0, 3])
    at = predict_confidence_at(converted, volume, ys, xs, fold_bn=False)
    np.testing.assert_allclose(at, exact[ys, xs], atol=tolerance)
    assert converted.training
    assert next(converted.parameters()).dtype == dtype
    assert whole.dtype == at.dtype == np.float32


@pytest.mark.parametrize('arch', ARCHS)
def test_a_folded_network_converted_to_float64_runs_every_way(arch):
    # A folded network after .double() failed in predict_confidence and in every way of the
    # sparse evaluator ("Input type (float) and bias type (double) should be the same").
    torch.manual_seed(0)
    net = arch(DEPTH)
    volume = _volume((DEPTH, 7, 5), seed=1)
    exact = predict_confidence(net, volume)
    folded = net.fold_batchnorm().double()
    np.testing.assert_allclose(predict_confidence(folded, volume), exact, atol=1e-6)
    for path in ('tile', 'fused', 'extracts'):
        evaluator = SparseEvaluator(folded, path=path)
        np.testing.assert_allclose(evaluator(volume), exact, atol=1e-6)
        np.testing.assert_allclose(
            evaluator.at(volume, np.array([6, 0]), np.array([4, 2])), exact[[6, 0], [4, 2]],
            atol=1e-6,
        )


def test_cuda_means_the_current_cuda_device(monkeypatch: pytest.MonkeyPatch) -> None:
    # A network on the GPU reports cuda:0, and torch.device('cuda') != torch.device('cuda:0'):
    # predict_confidence(net_on_gpu, ..., device='cuda', fold_bn=False) was refused.
    from cva_confidence_ros.model.inference import same_device

    monkeypatch.setattr(torch.cuda, 'current_device', lambda: 0)
    cuda, cuda0, cuda1 = torch.device('cuda'), torch.device('cuda:0'), torch.device('cuda:1')
    assert cuda != cuda0  # what the old check compared
    assert same_device(cuda0, cuda) and same_device(cuda, cuda0) and same_device(cuda, cuda)
    assert not same_device(cuda1, cuda) and not same_device(cuda0, cuda1)
    cpu = torch.device('cpu')
    assert same_device(cpu, torch.device('cpu')) and not same_device(cpu, cuda0)

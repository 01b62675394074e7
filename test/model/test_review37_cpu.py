"""CVA-Net-Fast's CPU speed-ups give the values of the path they replaced (review 37).

The folded network now takes the aligned curve in channels-last straight from the kernel (rows
in parallel), keeps its weights channels-last, applies its ReLUs in place, and the evaluator
moves a whole frame's tile without index arrays. Each is checked against the old way,
re-implemented here.
"""

from __future__ import annotations

from light_net_test_utils import peaked_volume, with_data_bn
import numba
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from cva_confidence_ros.model import CVANetFast, SparseEvaluator, predict_confidence
from cva_confidence_ros.model.fast import FAST_ALIGN, OUTSIDE_COST, aligned_curve
from cva_confidence_ros.model.inference import pad_cost_volume
from cva_confidence_ros.model.network import confidence_from_logits

DEPTH, HEIGHT, WIDTH = 24, 19, 23


@pytest.fixture(scope='module')
def net() -> CVANetFast:
    torch.manual_seed(3)
    volumes = (np.pad(peaked_volume(s, DEPTH, HEIGHT, WIDTH), ((0, 0), (6, 6), (6, 6)))
               for s in range(3))
    return with_data_bn(CVANetFast(DEPTH), volumes)


def _old_aligned(costs: torch.Tensor) -> torch.Tensor:
    """The aligned curve as torch ops compute it (the reference of the compiled kernel)."""
    wta = costs.argmin(dim=1, keepdim=True)
    padded = F.pad(costs, (0, 0, 0, 0, FAST_ALIGN, FAST_ALIGN), value=OUTSIDE_COST)
    offsets = torch.arange(2 * FAST_ALIGN + 1).reshape(1, -1, 1, 1)
    return torch.cat([padded.gather(1, wta + offsets), wta.to(costs.dtype) / costs.shape[1]], 1)


def _old_folded_logits(folded: torch.nn.Module, volume: torch.Tensor) -> torch.Tensor:
    """The folded forward before review 37: an NCHW curve copied to channels-last, NCHW
    weights, a new tensor for every ReLU."""
    def conv(layer: torch.nn.Conv2d, x: torch.Tensor) -> torch.Tensor:
        return F.conv2d(x, layer.weight.contiguous(), layer.bias)

    x = _old_aligned(volume[:, 0]).contiguous(memory_format=torch.channels_last)
    for layer in (folded.curve, folded.squeeze, *folded.fusion):
        x = F.relu(conv(layer, x))
    return conv(folded.fc2, F.relu(conv(folded.fc1, x)))[:, 0]


def _costs() -> torch.Tensor:
    rng = np.random.default_rng(7)
    costs = torch.from_numpy(rng.random((2, 40, 15, 17), dtype=np.float32))
    costs[:, :, :4, :4] = 0.0  # ties, as in the zero-padded border
    costs[0, 3, 8, 8] = float('nan')  # a NaN wins as in argmin
    costs[1, :, 9, 2] = 0.5  # a flat curve: d = 0
    return costs


@pytest.mark.parametrize('threads', [1, 2])
def test_channels_last_kernel_equals_torch_ops(threads):
    costs = _costs()
    saved = numba.get_num_threads()
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    try:
        last = aligned_curve(costs, torch.channels_last)
        plain = aligned_curve(costs)
    finally:
        numba.set_num_threads(saved)
    reference = _old_aligned(costs)
    assert last.is_contiguous(memory_format=torch.channels_last)
    assert plain.is_contiguous()
    torch.testing.assert_close(last, reference, rtol=0, atol=0, equal_nan=True)
    torch.testing.assert_close(plain, reference, rtol=0, atol=0, equal_nan=True)
    saved_dtype = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    try:  # the kernel's output has the costs' dtype, not the default one
        assert aligned_curve(costs, torch.channels_last).dtype == torch.float32
    finally:
        torch.set_default_dtype(saved_dtype)
    # The torch path (autograd) gives the asked layout too.
    through_torch = aligned_curve(costs.clone().requires_grad_(True), torch.channels_last)
    assert through_torch.is_contiguous(memory_format=torch.channels_last)
    torch.testing.assert_close(through_torch.detach(), reference, rtol=0, atol=0, equal_nan=True)


def test_folded_forward_equals_the_old_forward(net):
    folded = net.fold_batchnorm()
    # Channels-last weights: oneDNN no longer reorders them on every call.
    assert all(
        layer.weight.is_contiguous(memory_format=torch.channels_last)
        for layer in (folded.curve, folded.squeeze, *folded.fusion)
    )
    volume = torch.from_numpy(pad_cost_volume(peaked_volume(5, DEPTH, HEIGHT, WIDTH)))[None, None]
    extracts = volume[..., :13, :13].expand(3, -1, -1, -1, -1).contiguous()
    with torch.inference_mode():
        for tensor in (volume, extracts):
            new = folded(tensor)
            old = confidence_from_logits(_old_folded_logits(folded, tensor))
            assert new.shape == old.shape
            assert float((new - old).abs().max()) <= 1e-5
    with torch.no_grad():  # the unfolded network, the trained reference
        eval_net = net.eval()
        assert float((folded(volume) - eval_net(volume)).abs().max()) <= 1e-5


@pytest.mark.parametrize('budget', [512.0, 0.3])  # one tile; several
@pytest.mark.parametrize('path', ['auto', 'fused', 'extracts'])
def test_whole_frame_block_equals_the_indexed_pixels(net, budget, path):
    volume = peaked_volume(9, DEPTH, HEIGHT, WIDTH)
    evaluator = SparseEvaluator(net, tile_budget_mb=budget, path=path)
    reports: list[tuple[int, int]] = []
    evaluator.progress = lambda done, total: reports.append((done, total))
    every = evaluator(volume)
    counts = dict(evaluator.path_counts)
    assert reports[-1] == (HEIGHT * WIDTH, HEIGHT * WIDTH)
    assert all(a[0] <= b[0] for a, b in zip(reports, reports[1:], strict=False))
    # A mask of all pixels goes the old way: index arrays, gather and scatter.
    indexed = evaluator(volume, np.ones((HEIGHT, WIDTH), bool))
    np.testing.assert_array_equal(every, indexed)
    assert not np.isnan(every).any()
    # Each tile counted once, as with the mask.
    assert sum(counts.values()) * 2 == sum(evaluator.path_counts.values())
    whole = predict_confidence(net, volume)
    assert float(np.abs(every - whole).max()) <= 1e-5

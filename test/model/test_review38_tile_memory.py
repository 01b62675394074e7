"""Review 38: the confidence stage keeps to ``tile_budget_mb``.

A whole zero-padded copy of the cost volume (4 bytes a voxel) was made before tiling, and
CVA-Net-Lite's small tiles ran PyTorch's vol2col 3D convolution, whose work buffer was 27 times
the activations the budget counts. Memory is checked structurally here: the largest numpy
allocation of a call (tracemalloc) and the peak of the tensors PyTorch allocated (its profiler).
"""

from __future__ import annotations

from collections.abc import Callable
import tracemalloc

import numpy as np
import pytest
import torch
from torch.profiler import ProfilerActivity, profile

from cva_confidence_ros.model import (
    SparseEvaluator,
    pad_cost_volume,
    predict_confidence,
    predict_confidence_at,
)
from cva_confidence_ros.model.fast import CVANetFast
from cva_confidence_ros.model.inference import PAD
from cva_confidence_ros.model.lite import CVANetLite

DEPTH, HEIGHT, WIDTH = 16, 120, 160
#: Tiles of 24×24 output pixels for CVA-Net-Fast at D = 16: far below the volume.
BUDGET_MB = 1.0


def _volume(
    dtype: type = np.float32, depth: int = DEPTH, height: int = HEIGHT, width: int = WIDTH
) -> np.ndarray:
    return np.random.default_rng(3).random((depth, height, width)).astype(dtype)


def _numpy_peak(call: Callable[[], object]) -> int:
    """Peak bytes of Python and numpy allocations during ``call`` (tracemalloc)."""
    started = not tracemalloc.is_tracing()  # pytest may trace already
    if started:
        tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        before = tracemalloc.get_traced_memory()[0]
        call()
        return tracemalloc.get_traced_memory()[1] - before
    finally:
        if started:
            tracemalloc.stop()


def _torch_peak(call: Callable[[], object]) -> int:
    """Peak bytes of CPU tensors (work buffers included) alive during ``call``."""
    with profile(activities=[ProfilerActivity.CPU], profile_memory=True) as prof:
        call()
    events = [e for e in prof.profiler.kineto_results.events() if e.name() == '[memory]']
    live = peak = 0
    for event in sorted(events, key=lambda e: e.start_ns()):
        live += event.nbytes()
        peak = max(peak, live)
    return peak


@pytest.fixture(scope='module')
def fast_net() -> CVANetFast:
    torch.manual_seed(0)
    return CVANetFast(DEPTH).eval()


def _calls(net: torch.nn.Module, volume: np.ndarray) -> dict[str, Callable[[], object]]:
    budget = BUDGET_MB
    evaluator = SparseEvaluator(net, tile_budget_mb=budget)
    ys, xs = np.nonzero(np.ones((HEIGHT, WIDTH), dtype=bool))

    sparse = np.zeros((HEIGHT, WIDTH), dtype=bool)
    sparse[::8, ::8] = True

    def way(path: str) -> Callable[[], object]:
        fixed = SparseEvaluator(net, tile_budget_mb=budget, path=path)
        return lambda: fixed(volume, sparse)

    return {
        'predict_confidence': lambda: predict_confidence(net, volume, tile_budget_mb=budget),
        'evaluator': lambda: evaluator(volume),
        'evaluator tile': way('tile'),
        'evaluator fused': way('fused'),
        'evaluator extracts': way('extracts'),
        'evaluator.at': lambda: evaluator.at(volume, ys[::97], xs[::97]),
        'predict_confidence_at': lambda: predict_confidence_at(
            net, volume, ys[::97], xs[::97], batch_size=8
        ),
    }


@pytest.mark.parametrize('dtype', [np.float32, np.float64])
@pytest.mark.parametrize(
    'name',
    [
        'predict_confidence',
        'evaluator',
        'evaluator tile',
        'evaluator fused',
        'evaluator extracts',
        'evaluator.at',
        'predict_confidence_at',
    ],
)
def test_no_copy_of_the_whole_volume(fast_net: CVANetFast, name: str, dtype: type) -> None:
    # Every route padded the whole volume first (pad_cost_volume: 4 bytes a voxel, 1.4× the
    # float32 volume here), and a float64 volume was copied to float32 before that.
    volume = _volume(dtype)
    call = _calls(fast_net, volume)[name]
    call()  # warm: numba, torch and the operation counts
    float32_bytes = volume.size * 4
    assert _numpy_peak(call) < 0.5 * float32_bytes
    assert _torch_peak(call) < 1.5 * BUDGET_MB * 1e6  # the tiles, not the volume (1.2 MB)


def test_lite_small_tiles_keep_to_the_budget() -> None:
    # A tile of fewer than 74 rows went through PyTorch's vol2col Conv3d (batch 1, 3-wide kernel,
    # N·C·D·H ≤ 20480), whose work buffer holds 16·27 values per output voxel: 27× the
    # activations counted, +130 MB beyond a 16 MB budget at 320×240, D = 64 (and 5× slower).
    torch.manual_seed(0)
    net = CVANetLite(64).eval()
    volume = _volume(depth=64, height=40, width=56)
    budget = 3.0  # MB: tiles of about 20×20 output pixels
    whole = predict_confidence(net, volume, tile_budget_mb=512.0)
    tiled = predict_confidence(net, volume, tile_budget_mb=budget)
    peak = _torch_peak(lambda: predict_confidence(net, volume, tile_budget_mb=budget))
    assert peak < 1.5 * budget * 1e6
    # oneDNN's convolution gives the values of the whole image and of single extracts
    ys, xs = np.array([0, 5, 30, 39]), np.array([0, 55, 40, 6])
    at = predict_confidence_at(net, volume, ys, xs)
    np.testing.assert_allclose(tiled, whole, atol=1e-5)
    np.testing.assert_allclose(at, whole[ys, xs], atol=1e-5)


def test_padded_tiles_and_extracts_equal_the_padded_volume() -> None:
    from cva_confidence_ros.model.inference import _extract_batch, _padded_tile

    volume = np.random.default_rng(1).random((3, 9, 15)).astype(np.float32)
    padded = pad_cost_volume(volume)
    read_only = volume.copy()
    read_only.flags.writeable = False  # torch cannot wrap it (nor a byte-swapped volume)
    for y0, y1, x0, x1 in [(0, 9, 0, 15), (0, 2, 0, 3), (2, 5, 4, 15), (8, 9, 14, 15)]:
        expected_tile = padded[:, y0 : y1 + 2 * PAD, x0 : x1 + 2 * PAD]
        for given in (volume, volume.astype('>f8'), read_only):
            tile = _padded_tile(given, y0, y1, x0, x1)
            assert tile.is_contiguous() and tile.dtype == torch.float32
            np.testing.assert_array_equal(tile.numpy(), expected_tile)
    ys, xs = (axis.ravel() for axis in np.indices(volume.shape[1:]))
    expected = np.stack([padded[:, y : y + 13, x : x + 13] for y, x in zip(ys, xs, strict=True)])
    for given in (volume, volume.astype(np.float64)):
        np.testing.assert_array_equal(_extract_batch(given, ys, xs), expected[:, None])
    assert _extract_batch(volume, ys[:0], xs[:0]).shape == (0, 1, 3, 13, 13)

"""Regressions of review 37 (matchers against brute-force references): the MC-CNN correlation
refuses features it would read past the end of, and takes every float tensor the torch path
takes.

The brute-force comparisons themselves (census codes, Census-BM, 8-path SGM against
Hirschmüller's recursion, (1 − cos) / 2, WTA ties, sub-pixel fits, left–right check, speckles)
agreed exactly and are kept here as tests too, on tiny images.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cva_confidence_ros.errors import InputError
from cva_confidence_ros.matching import (
    compute_cost_volume,
    mccnn_fast,
    refine_subpixel,
    wta_disparity,
)
from cva_confidence_ros.matching.sgm import sgm_aggregate

_DIRECTIONS = [(0, 1), (0, -1), (1, 0), (-1, 0), (1, 1), (1, -1), (-1, 1), (-1, -1)]


def _census_bits(gray: np.ndarray) -> np.ndarray:
    """(H, W, 24) bits of the 5×5 census, replicate padding, 1 = neighbour darker."""
    height, width = gray.shape
    bits = np.zeros((height, width, 24), bool)
    for y in range(height):
        for x in range(width):
            k = 0
            for dy in range(-2, 3):
                for dx in range(-2, 3):
                    if dy or dx:
                        yy, xx = min(max(y + dy, 0), height - 1), min(max(x + dx, 0), width - 1)
                        bits[y, x, k] = gray[yy, xx] < gray[y, x]
                        k += 1
    return bits


def _hamming(left: np.ndarray, right: np.ndarray, depth: int, view: str) -> np.ndarray:
    ref, other = _census_bits(left), _census_bits(right)
    if view == 'right':
        ref, other = other, ref
    height, width = left.shape
    costs = np.full((depth, height, width), 24, np.int64)
    for d in range(depth):
        for y in range(height):
            for x in range(width):
                partner = x - d if view == 'left' else x + d
                if 0 <= partner < width:
                    costs[d, y, x] = np.count_nonzero(ref[y, x] != other[y, partner])
    return costs


def _outside(depth: int, width: int, view: str) -> np.ndarray:
    xs, ds = np.arange(width)[None, None, :], np.arange(depth)[:, None, None]
    return (xs - ds < 0) if view == 'left' else (xs + ds >= width)


def _sgm(costs: np.ndarray, p1: int, p2: int) -> np.ndarray:
    """Σ_r L_r of Hirschmüller's recursion, pixel by pixel."""
    depth, height, width = costs.shape
    total = np.zeros(costs.shape, np.int64)
    for dy, dx in _DIRECTIONS:
        path = np.zeros(costs.shape, np.int64)
        rows = range(height) if dy >= 0 else range(height - 1, -1, -1)
        columns = list(range(width)) if dx >= 0 else list(range(width - 1, -1, -1))
        for y in rows:
            for x in columns:
                if not (0 <= y - dy < height and 0 <= x - dx < width):
                    path[:, y, x] = costs[:, y, x]
                    continue
                prev = path[:, y - dy, x - dx]
                low = int(prev.min())
                for d in range(depth):
                    options = [prev[d], low + p2]
                    options += [prev[d - 1] + p1] if d > 0 else []
                    options += [prev[d + 1] + p1] if d < depth - 1 else []
                    path[d, y, x] = costs[d, y, x] + min(options) - low
        total += path
    return total


@pytest.fixture(scope='module')
def pair() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(37)
    left = rng.integers(0, 256, (7, 13), dtype=np.uint8)
    return left, np.roll(left, -2, axis=1)


@pytest.mark.parametrize('view', ['left', 'right'])
@pytest.mark.parametrize('window', [1, 3, 15])
def test_census_bm_equals_a_brute_force_reference(
    pair: tuple[np.ndarray, np.ndarray], view: str, window: int
) -> None:
    left, right = pair
    depth, (height, width), radius = 6, left.shape, window // 2
    costs = _hamming(left, right, depth, view)
    expected = np.zeros(costs.shape)
    for y in range(height):
        for x in range(width):
            rows = np.clip(np.arange(y - radius, y + radius + 1), 0, height - 1)
            cols = np.clip(np.arange(x - radius, x + radius + 1), 0, width - 1)
            expected[:, y, x] = costs[:, rows][:, :, cols].sum((1, 2)) / (24 * window**2)
    expected[_outside(depth, width, view).repeat(height, 1)] = 1.0
    volume = compute_cost_volume(left, right, 'census_bm', depth, view, window=window)
    np.testing.assert_allclose(volume, expected, atol=1e-6)


@pytest.mark.parametrize('view', ['left', 'right'])
@pytest.mark.parametrize(('p1', 'p2'), [(4, 32), (0, 0), (3, 8167)])
def test_census_sgm_equals_hirschmuellers_recursion(
    pair: tuple[np.ndarray, np.ndarray], view: str, p1: int, p2: int
) -> None:
    left, right = pair
    depth, width = 5, left.shape[1]
    expected = _sgm(_hamming(left, right, depth, view), p1, p2) / (8 * (24 + p2))
    expected[_outside(depth, width, view).repeat(left.shape[0], 1)] = 1.0
    volume = compute_cost_volume(left, right, 'census_sgm', depth, view, p1=p1, p2=p2)
    np.testing.assert_allclose(volume, expected, atol=1e-6)


def test_sgm_aggregate_equals_the_recursion_on_8_bit_costs() -> None:
    costs = np.random.default_rng(1).integers(0, 256, (17, 3, 5))
    np.testing.assert_array_equal(sgm_aggregate(costs, 7, 7936), _sgm(costs, 7, 7936))


def test_wta_of_a_constant_pair_is_zero_and_finite() -> None:
    flat = np.full((4, 12), 90, np.uint8)
    for matcher in ('census_bm', 'census_sgm'):
        volume = compute_cost_volume(flat, flat, matcher, 6)
        assert np.isfinite(volume).all()
        np.testing.assert_array_equal(wta_disparity(volume), 0.0)


@pytest.mark.parametrize('view', ['left', 'right'])
@pytest.mark.parametrize(('method', 'shape'), [('parabola', 2), ('equiangular', 1)])
def test_subpixel_is_exact_on_its_own_curve(view: str, method: str, shape: int) -> None:
    truth = np.random.default_rng(2).uniform(1.6, 6.4, (2, 14))
    ds = np.arange(9)[:, None, None]
    volume = np.abs(ds - truth) ** shape
    volume[_outside(9, 14, view).repeat(2, 1)] = 1e9
    refined = refine_subpixel(volume, wta_disparity(volume), method, view)
    xs, d = np.arange(14)[None], np.rint(truth)
    inside = (xs - d - 1 >= 0) if view == 'left' else (xs + d + 1 < 14)
    assert inside.sum() > 5
    np.testing.assert_allclose(refined[inside], truth[inside], atol=1e-5)


def _features(seed: int, shape: tuple[int, int, int] = (8, 3, 10)) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return torch.nn.functional.normalize(torch.randn(shape, generator=generator), dim=0)


@pytest.mark.parametrize('step', [-1, 1])
def test_cosine_costs_equal_a_brute_force_reference(step: int) -> None:
    ref, other = _features(1), _features(2)
    volume = mccnn_fast.cosine_cost_volume(ref, other, 12, step)
    expected = np.ones(volume.shape)
    for d in range(12):
        for y in range(3):
            for x in range(10):
                if 0 <= x + step * d < 10:
                    cosine = float(ref[:, y, x] @ other[:, y, x + step * d])
                    expected[d, y, x] = (1.0 - cosine) / 2.0
    np.testing.assert_allclose(volume, expected, atol=1e-6)


@pytest.mark.parametrize('function', ['cosine_cost_volume', 'cosine_cost_volume_torch'])
@pytest.mark.parametrize(
    ('other', 'depth', 'step', 'message'),
    [
        ((8, 3, 4), 3, -1, 'same'),  # narrower: the kernel read columns past its end
        ((4, 3, 10), 3, -1, 'same'),  # fewer channels: read past each feature vector
        ((8, 3, 10), 3, 3, 'step'),  # partner x + 3·d past the row
        ((8, 3, 10), 0, -1, 'depth'),
    ],
)
def test_cosine_costs_refuse_features_they_would_read_past(
    function: str, other: tuple[int, int, int], depth: int, step: int, message: str
) -> None:
    with pytest.raises(InputError, match=message):
        getattr(mccnn_fast, function)(_features(1), _features(2, other), depth, step)


@pytest.mark.parametrize('kind', ['ndarray', 'int'])
def test_cosine_costs_refuse_what_is_not_a_float_tensor(kind: str) -> None:
    features = _features(1)
    bad = features.numpy() if kind == 'ndarray' else (features * 10).int()
    with pytest.raises(InputError, match='features_ref'):
        mccnn_fast.cosine_cost_volume(bad, bad, 3, -1)  # type: ignore[arg-type]


@pytest.mark.parametrize('kind', ['float16', 'bfloat16', 'requires_grad'])
def test_cpu_cosine_costs_take_what_the_torch_path_takes(kind: str) -> None:
    features = [_features(1), _features(2)]
    if kind == 'requires_grad':
        features = [f.clone().requires_grad_() for f in features]
    else:
        features = [f.to(getattr(torch, kind)) for f in features]
    by_numba = mccnn_fast.cosine_cost_volume(features[0], features[1], 4, -1)
    by_torch = mccnn_fast.cosine_cost_volume_torch(features[0], features[1], 4, -1)
    # the torch path multiplies in the tensors' own precision
    np.testing.assert_allclose(by_numba, by_torch, atol=1e-2 if kind != 'requires_grad' else 1e-6)


@pytest.mark.parametrize(('channels', 'hint'), [(4, r'image\[\.\.\., :3\]'),
                                                (1, r'image\[\.\.\., 0\]')])
def test_an_rgba_or_one_channel_image_is_refused_with_what_to_give(
    channels: int, hint: str
) -> None:
    from cva_confidence_ros.errors import InputError
    from cva_confidence_ros.matching.base import check_image_pair

    image = np.zeros((8, 16, channels), np.uint8)
    with pytest.raises(InputError, match=hint):
        check_image_pair(image, image)

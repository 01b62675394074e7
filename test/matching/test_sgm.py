"""Semi-Global Matching: one path step by hand, all 8 paths against the textbook recursion."""

from __future__ import annotations

import numpy as np
import pytest

from cva_confidence_ros.errors import InputError
from cva_confidence_ros.matching.census import census_transform, hamming_cost_volume
from cva_confidence_ros.matching.sgm import census_sgm_volume, sgm_aggregate

DIRECTIONS = [(0, 1), (0, -1), (1, 0), (-1, 0), (1, 1), (1, -1), (-1, 1), (-1, -1)]


def textbook_sgm(costs: np.ndarray, p1: int, p2: int) -> np.ndarray:
    """Hirschmüller's recursion, one direction at a time, pixel by pixel (slow, obvious)."""
    depth, height, width = costs.shape
    costs = costs.astype(np.int64)
    total = np.zeros_like(costs)
    for dy, dx in DIRECTIONS:
        paths = np.zeros_like(costs)
        rows = range(height) if dy >= 0 else range(height - 1, -1, -1)
        columns = list(range(width)) if dx >= 0 else list(range(width - 1, -1, -1))
        for y in rows:
            for x in columns:
                py, px = y - dy, x - dx
                if not (0 <= py < height and 0 <= px < width):
                    paths[:, y, x] = costs[:, y, x]
                    continue
                prev = paths[:, py, px]
                low = prev.min()
                for d in range(depth):
                    options = [prev[d], low + p2]
                    if d > 0:
                        options.append(prev[d - 1] + p1)
                    if d < depth - 1:
                        options.append(prev[d + 1] + p1)
                    paths[d, y, x] = costs[d, y, x] + min(options) - low
        total += paths
    return total


def test_one_path_step_by_hand() -> None:
    # One row of two pixels, D = 3: the 6 vertical and diagonal paths start at every pixel
    # (L = C); only the two horizontal paths take a step.
    costs = np.array([[[0, 7]], [[5, 3]], [[9, 8]]], np.uint8)  # (D=3, H=1, W=2)
    total = sgm_aggregate(costs, p1=2, p2=10)
    # Left to right at x = 1, from L(x=0) = (0, 5, 9), min 0:
    #   d=0: 7 + min(0, 5 + 2, 0 + 10) − 0 = 7
    #   d=1: 3 + min(5, 0 + 2, 10) − 0 = 5
    #   d=2: 8 + min(9, 5 + 2, 10) − 0 = 15
    # Right to left at x = 0, from L(x=1) = (7, 3, 8), min 3:
    #   d=0: 0 + min(7, 3 + 2, 13) − 3 = 2
    #   d=1: 5 + min(3, 7 + 2, 13) − 3 = 5
    #   d=2: 9 + min(8, 3 + 2, 13) − 3 = 11
    # S(x=0) = 7·C(x=0) + (2, 5, 11); S(x=1) = 7·C(x=1) + (7, 5, 15).
    np.testing.assert_array_equal(total[:, 0, 0], [2, 40, 74])
    np.testing.assert_array_equal(total[:, 0, 1], [56, 26, 71])
    assert total.dtype == np.int32 and total.shape == (3, 1, 2)


def test_one_vertical_step_by_hand() -> None:
    # The same numbers in a column: now the vertical paths take the step.
    costs = np.array([[[0], [7]], [[5], [3]], [[9], [8]]], np.uint8)  # (D=3, H=2, W=1)
    total = sgm_aggregate(costs, p1=2, p2=10)
    np.testing.assert_array_equal(total[:, 0, 0], [2, 40, 74])
    np.testing.assert_array_equal(total[:, 1, 0], [56, 26, 71])


@pytest.mark.parametrize('shape', [(5, 7, 9), (1, 1, 1), (3, 1, 6), (4, 6, 1), (12, 9, 11)])
def test_all_eight_paths_match_the_textbook_recursion(shape: tuple[int, int, int]) -> None:
    costs = np.random.default_rng(sum(shape)).integers(0, 25, shape).astype(np.uint8)
    np.testing.assert_array_equal(sgm_aggregate(costs, 3, 20), textbook_sgm(costs, 3, 20))


def test_path_costs_respect_the_bound() -> None:
    costs = np.random.default_rng(1).integers(0, 25, (10, 8, 12)).astype(np.uint8)
    total = sgm_aggregate(costs, 1, 5)
    # every L_r ≤ Cmax + P2, so S ≤ 8·(24 + 5)
    assert total.max() <= 8 * (24 + 5)
    # and L_r ≥ C, so S ≥ 8·C
    assert np.all(total >= 8 * costs.astype(np.int32))


def test_no_smoothness_penalty_sums_eight_copies_of_the_costs() -> None:
    costs = np.random.default_rng(2).integers(0, 25, (6, 5, 7)).astype(np.uint8)
    # With P1 = P2 = 0 the recursion adds C + min(prev) − min(prev) = C on every path.
    np.testing.assert_array_equal(sgm_aggregate(costs, 0, 0), 8 * costs.astype(np.int32))


@pytest.mark.parametrize('step', [-1, 1])
def test_census_sgm_volume_is_the_normalised_textbook_sum(step: int) -> None:
    rng = np.random.default_rng(7 + step)
    codes_a = census_transform(rng.integers(0, 256, (9, 13), dtype=np.uint8))
    codes_b = census_transform(rng.integers(0, 256, (9, 13), dtype=np.uint8))
    p1, p2 = 3, 20
    volume = census_sgm_volume(codes_a, codes_b, 5, step, p1, p2)
    hamming = hamming_cost_volume(codes_a, codes_b, 5, step)
    expected = textbook_sgm(hamming, p1, p2) / (8 * (24 + p2))
    outside = hamming == 24
    np.testing.assert_allclose(volume[~outside], expected[~outside], rtol=1e-6)
    # partner outside the image: 1.0 exactly (only there is Hamming 24 forced)
    columns = np.arange(13)[None, None, :]
    depths = np.arange(5)[:, None, None]
    beyond = np.broadcast_to((columns + step * depths < 0) | (columns + step * depths >= 13),
                             volume.shape)
    assert np.all(volume[beyond] == 1.0)


@pytest.mark.parametrize(
    ('costs', 'p1', 'p2', 'message'),
    [
        (np.zeros((2, 3), np.uint8), 1, 2, 'integer array'),
        (np.zeros((2, 3, 4), np.float32), 1, 2, 'integer array'),
        (np.full((2, 3, 4), 300, np.int32), 1, 2, r'\[0, 255\]'),
        (np.zeros((2, 3, 4), np.uint8), 5, 2, 'p1 ≤ p2'),
        (np.full((2, 3, 4), 255, np.uint8), 1, 8000, 'must be ≤ 65535'),
        # a fractional penalty was truncated to int16 without a word, a str raised TypeError
        (np.zeros((2, 3, 4), np.uint8), 1.9, 3, 'integer penalties'),
        (np.zeros((2, 3, 4), np.uint8), '1', 3, 'integer penalties'),
        (np.zeros((2, 3, 4), np.uint8), 1, None, 'integer penalties'),
    ],
)
def test_sgm_aggregate_rejects_bad_input(
    costs: np.ndarray, p1: int, p2: int, message: str
) -> None:
    with pytest.raises(InputError, match=message):
        sgm_aggregate(costs, p1, p2)

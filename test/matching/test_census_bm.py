"""Census block matching: hand-checked window sums, normalisation, both views."""

from __future__ import annotations

from matching_test_utils import shifted_pair
import numpy as np
import pytest

from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.matching import compute_cost_volume, wta_disparity
from cva_confidence_ros.matching.census import census_transform, hamming_cost_volume
from cva_confidence_ros.matching.census_bm import CensusBMConfig


def test_constant_pair_costs_only_the_cells_without_partner() -> None:
    flat = np.full((6, 8), 90, np.uint8)
    volume = compute_cost_volume(flat, flat, 'census_bm', 3)
    # Every census code is 0, so wherever the whole window has partners the cost is 0.
    for d in range(3):
        assert np.all(volume[d, :, d + 2:] == 0.0)
    # d = 1, x = 1: window columns −1…3 clamp to 0, 0, 1, 2, 3; column 0 has no partner
    # (0 − 1 < 0), so 2 columns × 5 rows × 24 bits = 240 of 600.
    assert volume[1, 3, 1] == pytest.approx(240 / 600)
    # d = 2, x = 2: columns 0…4, of which 0 and 1 have no partner: 240 of 600 again.
    assert volume[2, 3, 2] == pytest.approx(240 / 600)
    # d = 2, x = 3: columns 1…5, only column 1 without partner: 120 of 600.
    assert volume[2, 3, 3] == pytest.approx(120 / 600)
    # x − d < 0: no partner at all.
    assert np.all(volume[1, :, 0] == 1.0) and np.all(volume[2, :, :2] == 1.0)


def test_window_sum_matches_a_direct_sum_of_hamming_costs() -> None:
    left, right = shifted_pair(12, 20, 2, seed=5)
    volume = compute_cost_volume(left, right, 'census_bm', 4)
    hamming = hamming_cost_volume(
        census_transform(left), census_transform(right), 4, -1
    ).astype(np.int64)
    # Interior pixels with all partners inside: a plain 5×5 sum, divided by 600.
    for d, y, x in [(0, 5, 7), (1, 2, 10), (3, 9, 17), (2, 6, 4 + 2)]:
        expected = hamming[d, y - 2:y + 3, x - 2:x + 3].sum() / 600
        assert volume[d, y, x] == pytest.approx(expected, abs=1e-6)


def test_window_parameter_changes_the_bound() -> None:
    left, right = shifted_pair(10, 16, 1, seed=2)
    volume = compute_cost_volume(left, right, 'census_bm', 2, window=1)
    hamming = hamming_cost_volume(census_transform(left), census_transform(right), 2, -1)
    np.testing.assert_allclose(volume, hamming / 24, atol=1e-6)


def test_shifted_texture_gives_the_shift() -> None:
    shift = 3
    left, right = shifted_pair(24, 40, shift, seed=1)
    disparity = wta_disparity(compute_cost_volume(left, right, 'census_bm', 8))
    # Interior: window fully inside and all window partners inside.
    assert np.all(disparity[2:-2, shift + 2:-2] == shift)


def test_right_view_pairs_the_same_pixels_as_the_left_view() -> None:
    left, right = shifted_pair(14, 30, 2, seed=4)
    depth = 6
    vol_left = compute_cost_volume(left, right, 'census_bm', depth)
    vol_right = compute_cost_volume(left, right, 'census_bm', depth, view='right')
    for d in range(depth):
        # right (y, x) with left (y, x + d) is left (y, x + d) with right (y, x): the same
        # window pairs wherever no window cell is clamped at the border.
        np.testing.assert_allclose(
            vol_right[d, :, 2:30 - d - 2], vol_left[d, :, 2 + d:30 - 2], atol=1e-6
        )
        assert np.all(vol_right[d, :, 30 - d:] == 1.0)


@pytest.mark.parametrize('window', [0, 2, 17, 3.0, True, '5'])
def test_bad_window(window: object) -> None:
    with pytest.raises(ConfigError, match='window'):
        CensusBMConfig(window=window)  # type: ignore[arg-type]


@pytest.mark.parametrize(('window', 'shape'), [(3, (9, 14)), (5, (4, 7)), (15, (6, 11))])
def test_border_rule_matches_a_padded_box_sum(window: int, shape: tuple[int, int]) -> None:
    # The documented rule, written with numpy: per-pixel Hamming costs (24 where the partner
    # is outside), the border cells repeated outwards, a plain window sum.
    left, right = shifted_pair(*shape, 1, seed=window)
    depth = 3
    volume = compute_cost_volume(left, right, 'census_bm', depth, window=window)
    hamming = hamming_cost_volume(census_transform(left), census_transform(right), depth, -1)
    radius = window // 2
    for d in range(depth):
        padded = np.pad(hamming[d].astype(np.int64), radius, mode='edge')
        sums = np.zeros(shape, np.int64)
        for dy in range(window):
            for dx in range(window):
                sums += padded[dy:dy + shape[0], dx:dx + shape[1]]
        expected = np.where(np.arange(shape[1]) < d, 1.0, sums / (24 * window * window))
        np.testing.assert_allclose(volume[d], expected, atol=1e-6)

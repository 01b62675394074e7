"""The census_sgm matcher: normalisation by 8·(Cmax + P2), disparities, views, penalties."""

from __future__ import annotations

from matching_test_utils import shifted_pair
import numpy as np
import pytest

from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.matching import compute_cost_volume, left_right_check, wta_disparity
from cva_confidence_ros.matching.census import census_transform, hamming_cost_volume
from cva_confidence_ros.matching.census_sgm import CensusSGMConfig
from cva_confidence_ros.matching.sgm import sgm_aggregate


def test_volume_is_the_path_sum_over_its_bound() -> None:
    left, right = shifted_pair(10, 18, 2, seed=8)
    volume = compute_cost_volume(left, right, 'census_sgm', 5, p1=2, p2=12)
    hamming = hamming_cost_volume(census_transform(left), census_transform(right), 5, -1)
    expected = sgm_aggregate(hamming, 2, 12) / (8 * (24 + 12))
    inside = np.arange(18)[None, None, :] >= np.arange(5)[:, None, None]
    inside = np.broadcast_to(inside, volume.shape)
    np.testing.assert_allclose(volume[inside], expected[inside], rtol=1e-6)
    assert np.all(volume[~inside] == 1.0)


def test_shifted_texture_gives_the_shift() -> None:
    shift = 4
    left, right = shifted_pair(24, 40, shift, seed=2)
    volume = compute_cost_volume(left, right, 'census_sgm', 10)
    assert volume.dtype == np.float32 and volume.flags['C_CONTIGUOUS']
    assert 0.0 <= volume.min() and volume.max() <= 1.0
    disparity = wta_disparity(volume)
    # Away from the 2-pixel census borders, where replicate padding makes left and right codes
    # of the same scene point differ.
    assert np.all(disparity[:, shift + 2:-2] == shift)


def test_right_view_is_consistent_with_the_left_view() -> None:
    shift = 3
    left, right = shifted_pair(20, 36, shift, seed=3)
    vol_left = compute_cost_volume(left, right, 'census_sgm', 8)
    vol_right = compute_cost_volume(left, right, 'census_sgm', 8, view='right')
    for d in range(8):
        assert np.all(vol_right[d, :, 36 - d:] == 1.0)
    disp_right = wta_disparity(vol_right)
    assert np.all(disp_right[:, 2:36 - shift - 2] == shift)
    consistent = left_right_check(wta_disparity(vol_left), disp_right)
    assert consistent[:, shift + 2:-2].all()


def test_penalties_smooth_a_noisy_cost_volume() -> None:
    rng = np.random.default_rng(4)
    # textured left, noisy right: stronger penalties must give a smoother disparity map
    left, right = shifted_pair(30, 40, 3, seed=9)
    noisy = np.clip(right.astype(np.int16) + rng.integers(-40, 41, right.shape), 0, 255)
    noisy = noisy.astype(np.uint8)
    rough = wta_disparity(compute_cost_volume(left, noisy, 'census_sgm', 8, p1=0, p2=0))
    smooth = wta_disparity(compute_cost_volume(left, noisy, 'census_sgm', 8, p1=8, p2=64))

    def jumps(disparity: np.ndarray) -> int:
        return int(np.count_nonzero(np.diff(disparity[:, 6:], axis=1)))

    assert jumps(smooth) < jumps(rough)


@pytest.mark.parametrize(
    'params',
    [{'p1': -1}, {'p1': 10, 'p2': 5}, {'p2': 9000}, {'p1': 1.5}, {'p2': True}, {'p2': '32'}],
)
def test_bad_penalties(params: dict[str, object]) -> None:
    with pytest.raises(ConfigError, match='p1|p2|penalties'):
        CensusSGMConfig(**params)  # type: ignore[arg-type]


def test_penalties_through_the_public_entry() -> None:
    left, right = shifted_pair(8, 12, 1)
    with pytest.raises(ConfigError, match='penalties'):
        compute_cost_volume(left, right, 'census_sgm', 4, p1=40, p2=10)

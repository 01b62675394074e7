"""Winner-takes-all disparity and the left–right consistency check on hand-made arrays."""

from __future__ import annotations

import numpy as np
import pytest

from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.matching import left_right_check, wta_disparity


def test_wta_picks_the_lowest_cost_and_the_smallest_d_on_ties() -> None:
    volume = np.array(
        [
            [[0.5, 0.2, 0.3]],
            [[0.1, 0.2, 0.9]],
            [[0.7, 0.6, 0.3]],
        ],
        np.float32,
    )  # (D=3, H=1, W=3)
    disparity = wta_disparity(volume)
    assert disparity.dtype == np.float32 and disparity.shape == (1, 3)
    # column 1 ties d = 0 and d = 1, column 2 ties d = 0 and d = 2
    np.testing.assert_array_equal(disparity, [[1.0, 0.0, 0.0]])


def test_wta_equals_numpy_argmin_and_accepts_float64() -> None:
    volume = np.random.default_rng(0).random((7, 5, 6))
    np.testing.assert_array_equal(wta_disparity(volume), np.argmin(volume, axis=0))


@pytest.mark.parametrize(
    ('volume', 'message'),
    [
        (np.zeros((3, 4), np.float32), r'\(D, H, W\)'),
        (np.zeros((0, 4, 4), np.float32), r'\(D, H, W\)'),
        (np.zeros((3, 4, 4), np.int32), 'float'),
        ([[[0.0]]], 'numpy array'),
    ],
)
def test_wta_rejects_bad_volumes(volume: object, message: str) -> None:
    with pytest.raises(InputError, match=message):
        wta_disparity(volume)  # type: ignore[arg-type]


def test_wta_rejects_nan_costs() -> None:
    volume = np.zeros((2, 2, 2), np.float32)
    volume[1, 0, 1] = np.nan
    with pytest.raises(InputError, match='1 NaN'):
        wta_disparity(volume)


def test_left_right_check_by_hand() -> None:
    # One row of 5 pixels.
    disp_left = np.array([[0.0, 1.0, 1.0, 3.0, np.nan]], np.float32)
    disp_right = np.array([[0.0, 1.0, 3.0, 0.0, 2.0]], np.float32)
    consistent = left_right_check(disp_left, disp_right)
    # x=0: partner 0, |0 − 0| = 0 → True
    # x=1: partner 0, |1 − 0| = 1 ≤ 1 → True
    # x=2: partner 1, |1 − 1| = 0 → True
    # x=3: partner 0, |3 − 0| = 3 → False
    # x=4: NaN → False
    np.testing.assert_array_equal(consistent, [[True, True, True, False, False]])
    strict = left_right_check(disp_left, disp_right, max_diff=0.5)
    np.testing.assert_array_equal(strict, [[True, False, True, False, False]])


def test_left_right_check_partner_outside_or_unknown() -> None:
    disp_left = np.array([[2.0, 2.0, 2.0]], np.float32)  # partners −2, −1, 0
    disp_right = np.array([[np.nan, 2.0, 2.0]], np.float32)
    np.testing.assert_array_equal(left_right_check(disp_left, disp_right), [[False] * 3])
    # subpixel disparities round to the nearest partner column
    np.testing.assert_array_equal(
        left_right_check(np.array([[0.0, 1.4]]), np.array([[2.0, 0.0]])), [[False, True]]
    )


@pytest.mark.parametrize(
    ('left', 'right', 'message'),
    [
        (np.zeros((2, 3)), np.zeros((2, 4)), 'same shape'),
        (np.zeros(3), np.zeros(3), r'\(H, W\)'),
        (np.zeros((2, 3), bool), np.zeros((2, 3)), 'dtype'),
        ([[0.0]], np.zeros((1, 1)), 'numpy array'),
    ],
)
def test_left_right_check_rejects_bad_maps(left: object, right: object, message: str) -> None:
    with pytest.raises(InputError, match=message):
        left_right_check(left, right)  # type: ignore[arg-type]


@pytest.mark.parametrize('max_diff', [-1.0, float('nan'), float('inf'), 'one'])
def test_left_right_check_rejects_bad_tolerance(max_diff: object) -> None:
    with pytest.raises(ConfigError, match='max_diff'):
        left_right_check(np.zeros((1, 2)), np.zeros((1, 2)), max_diff=max_diff)  # type: ignore

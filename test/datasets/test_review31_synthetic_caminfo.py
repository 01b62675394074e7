"""Review 31: the synthetic pairs' seed range and the REP 104 reading of camera infos."""

from __future__ import annotations

from types import SimpleNamespace
import warnings

import numpy as np
import pytest

from cva_confidence_ros import camera_info
from cva_confidence_ros.datasets.synthetic import synthetic_pair, synthetic_pairs
from cva_confidence_ros.errors import ConfigError, InputError

FX, BASELINE = 100.0, 0.1
P_LEFT = [FX, 0.0, 48.0, 0.0, 0.0, FX, 32.0, 0.0, 0.0, 0.0, 1.0, 0.0]
P_RIGHT = [FX, 0.0, 48.0, -FX * BASELINE, 0.0, FX, 32.0, 0.0, 0.0, 0.0, 1.0, 0.0]


def _info(p, binning=(0, 0), roi=(0, 0, 0, 0), width=96, height=64) -> SimpleNamespace:
    """The fields of a ``sensor_msgs/CameraInfo`` that camera_info reads."""
    x_offset, y_offset, roi_width, roi_height = roi
    return SimpleNamespace(
        p=list(p),
        width=width,
        height=height,
        binning_x=binning[0],
        binning_y=binning[1],
        roi=SimpleNamespace(
            x_offset=x_offset, y_offset=y_offset, width=roi_width, height=roi_height
        ),
    )


def test_synthetic_pairs_numpy_first_seed_does_not_wrap_around() -> None:
    # np.uint8(255) + 1 wrapped to 0: the second pair was seed0 (a RuntimeWarning only).
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        pairs = synthetic_pairs(2, np.uint8(255), 16, 16, 4)
    assert [pair.scene for pair in pairs] == ['seed255', 'seed256']
    np.testing.assert_array_equal(pairs[1].left, synthetic_pair(256, 16, 16, 4).left)


def test_synthetic_pairs_checks_first_seed_and_sizes_even_for_no_pairs() -> None:
    # first_seed=True gave seeds 1 and 2 (synthetic_pair refuses a bool seed), and a count of
    # 0 returned [] whatever the seed and sizes.
    with pytest.raises(ConfigError, match=r'^first_seed must be an integer >= 0; got True$'):
        synthetic_pairs(2, True, 16, 16, 4)
    with pytest.raises(ConfigError, match=r'^first_seed must be an integer >= 0; got -5$'):
        synthetic_pairs(0, -5)
    with pytest.raises(ConfigError, match=r'^first_seed must be an integer >= 0; got nan$'):
        synthetic_pairs(0, float('nan'))
    with pytest.raises(ConfigError, match='at least 16×16 pixels; got 0×0'):
        synthetic_pairs(0, 0, 0, 0, 4)
    with pytest.raises(ConfigError, match='max_disparity must be in'):
        synthetic_pairs(0, 0, 16, 16, 9)
    assert synthetic_pairs(0, 3, 16, 16, 4) == []


@pytest.mark.parametrize('image_size', [(96, 64), (48, 32), None])
def test_image_projection_refuses_a_p_of_the_wrong_size(image_size) -> None:
    # A P of 9 values failed in numpy's reshape (ValueError 'cannot reshape array of size 9').
    info = _info(P_LEFT[:9], binning=(2, 2))
    with pytest.raises(
        InputError,
        match=r'^left camera info p must be a 3×4 projection matrix \(12 values\); '
        r'got 9$',
    ):
        camera_info.image_projection(info, 'left camera info', image_size)


def test_image_projection_refuses_a_binning_that_leaves_no_pixels() -> None:
    # A 3×3 ROI binned by 4 gave images of 0×0, and binning 200 of 96 columns 0×64.
    with pytest.raises(
        InputError, match=r'^left camera info: binning 4×4 leaves no pixels of its 3×3 region'
    ):
        camera_info.image_projection(_info(P_LEFT, (4, 4), (0, 0, 3, 3)), 'left camera info')
    with pytest.raises(InputError, match=r'binning 200×1 leaves no pixels of its 96×64'):
        camera_info.image_projection(_info(P_LEFT, (200, 1)), 'left camera info')
    # One binned pixel is still an image.
    size, _ = camera_info.image_projection(_info(P_LEFT, (4, 4), (0, 0, 4, 4)), 'info')
    assert size == (1, 1)


def test_check_rows_refuses_non_finite_and_wrongly_sized_matrices() -> None:
    # NaN fy or cy passed (NaN compares False with every tolerance), a wrong size failed in
    # numpy's reshape.
    for index in (5, 6):
        bad = list(P_RIGHT)
        bad[index] = float('nan')
        with pytest.raises(InputError, match=r'^projection matrices must be finite'):
            camera_info.check_rows(P_LEFT, bad)
        with pytest.raises(InputError, match=r'^projection matrices must be finite'):
            camera_info.check_rows(bad, P_LEFT)
    with pytest.raises(InputError, match=r'^P_right must be a 3×4 projection matrix .*got 11$'):
        camera_info.check_rows(P_LEFT, P_RIGHT[:11])


def test_check_rows_refuses_a_vertical_baseline() -> None:
    # P_right[1, 3] = Ty = −fy·B_y: the rows of the pair do not correspond (a point at disparity
    # d is d·Ty/Tx rows off in the right image); it was read as a horizontal pair.
    vertical = list(P_RIGHT)
    vertical[7] = -FX * 0.05  # 5 cm vertically for 10 cm horizontally: d / 2 rows off
    with pytest.raises(
        InputError,
        match=r'^left and right projection matrices must share Ty .*got P_left\[1, 3\] = 0 and '
        r'P_right\[1, 3\] = -5$',
    ):
        camera_info.check_rows(P_LEFT, vertical)
    # Text round-off of a horizontal pair, and a pair that shares a nonzero Ty, pass.
    rounded = list(P_RIGHT)
    rounded[7] = 1e-9
    camera_info.check_rows(P_LEFT, rounded)
    shared_left, shared_right = list(P_LEFT), list(P_RIGHT)
    shared_left[7] = shared_right[7] = -3.0
    camera_info.check_rows(shared_left, shared_right)
    # Binning folds Ty with Tx: a binned horizontal pair still passes.
    _, left = camera_info.image_projection(_info(P_LEFT, (2, 2)), 'left camera info')
    _, right = camera_info.image_projection(_info(P_RIGHT, (2, 2)), 'right camera info')
    camera_info.check_rows(left, right)

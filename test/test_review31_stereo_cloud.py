"""Review 31: stereo_cloud names its left image when that is of another size (the error
spoke of a 'colour image', no argument of it)."""

from __future__ import annotations

import numpy as np
import pytest

from cva_confidence_ros.errors import InputError
from cva_confidence_ros.pointcloud import StereoGeometry, stereo_cloud

GEOMETRY = StereoGeometry(fx=50.0, fy=50.0, cx=8.0, cy=6.0, baseline=0.1, cx_right=8.0)


@pytest.mark.parametrize('left_shape', [(12, 15), (11, 16, 3), (12, 16, 3, 1), (16, 12)])
@pytest.mark.parametrize('with_confidence', [False, True])
def test_a_left_image_of_another_size_is_named(left_shape: tuple[int, ...],
                                              with_confidence: bool) -> None:
    disparity = np.full((12, 16), 4.0, np.float32)
    with pytest.raises(InputError, match=r"^the left image must have the disparity map's size "
                                         r'\(12, 16\) \(\+ 3 colours\); got '):
        stereo_cloud(disparity, np.ones_like(disparity), np.zeros(left_shape, np.uint8),
                     GEOMETRY, np.ones((12, 16), bool), with_confidence=with_confidence)


def test_a_left_image_of_the_right_size_makes_the_cloud() -> None:
    disparity = np.full((12, 16), 4.0, np.float32)
    for left in (np.zeros((12, 16), np.uint8), np.zeros((12, 16, 3), np.uint8)):
        cloud = stereo_cloud(disparity, np.ones_like(disparity), left, GEOMETRY,
                             np.ones((12, 16), bool))
        assert cloud.shape == (12, 16) and np.allclose(cloud['z'], 50.0 * 0.1 / 4.0)

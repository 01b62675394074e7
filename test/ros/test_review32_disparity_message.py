"""``disparity_from_message``: a DisparityImage whose min_disparity leaves no pixel valid."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip('rclpy')

from std_msgs.msg import Header  # noqa: E402

from cva_confidence_ros.errors import InputError  # noqa: E402
from cva_confidence_ros.pointcloud import StereoGeometry  # noqa: E402
from cva_confidence_ros.ros.convert import (  # noqa: E402
    disparity_from_message,
    disparity_to_message,
)


@pytest.mark.parametrize('lowest', [float('nan'), float('inf')])
def test_a_min_disparity_that_leaves_every_pixel_unknown_is_refused(lowest: float) -> None:
    disparity = np.array([[1.0, 2.0], [np.nan, 3.0]], np.float32)
    geometry = StereoGeometry(fx=100.0, fy=100.0, cx=1.0, cy=1.0, cx_right=1.0, baseline=0.1)
    msg = disparity_to_message(disparity, Header(), geometry, max_disparity=16)
    np.testing.assert_array_equal(disparity_from_message(msg), disparity)
    msg.min_disparity = lowest  # read as all NaN, a ground truth that scores nothing
    with pytest.raises(InputError, match=f'min_disparity .*got {lowest}'):
        disparity_from_message(msg)

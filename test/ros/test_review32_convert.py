"""Review 32 of ``ros/convert.py``: the shrink factor of the published camera info and the data
of empty clouds (each a regression test of a fault found in the review)."""

from __future__ import annotations

import numpy as np
import pytest
from sensor_msgs.msg import CameraInfo, PointCloud2, PointField
from std_msgs.msg import Header

from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.ros.convert import point_cloud_to_records, scale_camera_info


def _info(width: int = 97, height: int = 65) -> CameraInfo:
    cx, cy = (width - 1) / 2, (height - 1) / 2
    return CameraInfo(
        width=width,
        height=height,
        k=[100.0, 0.0, cx, 0.0, 100.0, cy, 0.0, 0.0, 1.0],
        r=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        p=[100.0, 0.0, cx, -10.0, 0.0, 100.0, cy, 0.0, 0.0, 0.0, 1.0, 0.0],
    )


@pytest.mark.parametrize('factor', [0, -1, 2.5, True, '2'])
def test_scale_camera_info_refuses_a_factor_that_is_no_integer_of_at_least_1(
    factor: object,
) -> None:
    # Was: 0 a ZeroDivisionError, −1 an info of −97×−65 px, 2.5 one of 38.0×26.0 px.
    with pytest.raises(ConfigError, match='factor must be an integer >= 1'):
        scale_camera_info(_info(), factor, Header())  # type: ignore[arg-type]


def test_scale_camera_info_refuses_a_factor_that_leaves_no_pixel() -> None:
    # Was: a 0×0 info, which ROS reads as an uncalibrated camera.
    with pytest.raises(InputError, match='97×65 px leaves no pixel when shrunk by 128'):
        scale_camera_info(_info(), 128, Header())
    # A factor that does not divide the size is still right: crop 97×65 to 96×63, shrink by
    # 3, x → (x + 0.5)/3 − 0.5.
    out = scale_camera_info(_info(), np.int64(3), Header(frame_id='f'))
    assert (out.width, out.height, out.header.frame_id) == (32, 21, 'f')
    np.testing.assert_allclose(out.k, [100 / 3, 0, 48.5 / 3 - 0.5, 0, 100 / 3, 32.5 / 3 - 0.5,
                                       0, 0, 1])
    assert out.p[3] == pytest.approx(-10 / 3)


def _empty_cloud(height: int, width: int, row_step: int, data: bytes) -> PointCloud2:
    fields = [PointField(name='x', offset=0, datatype=PointField.FLOAT32, count=1)]
    return PointCloud2(header=Header(), height=height, width=width, fields=fields,
                       is_bigendian=False, point_step=4, row_step=row_step, data=data)


@pytest.mark.parametrize(('height', 'width', 'row_step'), [(1, 0, 0), (0, 5, 20)])
def test_an_empty_cloud_with_data_is_refused(height: int, width: int, row_step: int) -> None:
    # Was: the 40 bytes dropped unseen and an empty array returned, although a non-empty
    # cloud with more data than its header says is refused.
    with pytest.raises(InputError, match='holds 40 bytes'):
        point_cloud_to_records(_empty_cloud(height, width, row_step, bytes(40)))
    # Without data, or with its rows of padding, it is still read.
    assert point_cloud_to_records(_empty_cloud(height, width, row_step, b'')).shape == (
        height, width)
    padding = bytes(row_step * height)
    assert point_cloud_to_records(_empty_cloud(height, width, row_step, padding)).size == 0
    assert point_cloud_to_records(_empty_cloud(2, 0, 8, bytes(16))).shape == (2, 0)


def test_an_8uc1_image_reads_as_mono8() -> None:
    # The OpenCV spelling some camera drivers give their mono images was refused.
    from sensor_msgs.msg import Image

    from cva_confidence_ros.ros.convert import image_to_array

    pixels = np.arange(12, dtype=np.uint8).reshape(3, 4)
    msg = Image(height=3, width=4, encoding='8UC1', step=4, data=pixels.tobytes())
    np.testing.assert_array_equal(image_to_array(msg), pixels)


def test_a_16uc1_image_reads_as_mono16_in_both_byte_orders() -> None:
    # Review 35: the OpenCV spelling of mono16 (some drivers) was refused on every frame.
    from sensor_msgs.msg import Image

    from cva_confidence_ros.ros.convert import image_to_array

    pixels = np.arange(12, dtype=np.uint16).reshape(3, 4) * 5000
    for order, big in (('<u2', 0), ('>u2', 1)):
        data = pixels.astype(order).tobytes()
        msg = Image(height=3, width=4, encoding='16UC1', is_bigendian=big, step=8, data=data)
        out = image_to_array(msg)
        assert out.dtype == np.uint16
        np.testing.assert_array_equal(out, pixels)

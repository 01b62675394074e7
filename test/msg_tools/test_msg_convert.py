"""rosbags message types ⇄ arrays: hand-checked fields, CDR round trips, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from cva_confidence_ros.errors import InputError
from cva_confidence_ros.pointcloud import StereoGeometry
from cva_confidence_ros.ros.convert import image_to_array
from msg_tools.convert import (
    CAMERA_INFO,
    DISPARITY_IMAGE,
    IMAGE,
    camera_geometry,
    camera_info_msgs,
    disparity_from_msg,
    disparity_to_msg,
    float_image_to_msg,
    image_to_msg,
    jazzy_typestore,
    make_header,
    stamp_to_ns,
)

STAMP = 1_700_000_000_123_456_789


def _cdr_round_trip(msg: object, msgtype: str) -> object:
    store = jazzy_typestore()
    return store.deserialize_cdr(store.serialize_cdr(msg, msgtype), msgtype)


@pytest.mark.parametrize(
    ('array', 'encoding', 'step'),
    [
        (np.arange(12, dtype=np.uint8).reshape(3, 4), 'mono8', 4),
        (np.arange(36, dtype=np.uint8).reshape(3, 4, 3), 'rgb8', 12),
        (np.array([[1, 256, 65535]], dtype=np.uint16), 'mono16', 6),
    ],
)
def test_image_round_trip_through_cdr(array: np.ndarray, encoding: str, step: int) -> None:
    msg = _cdr_round_trip(image_to_msg(array, STAMP, 'cam'), IMAGE)
    assert (msg.encoding, msg.step, msg.is_bigendian) == (encoding, step, 0)
    assert (msg.height, msg.width) == array.shape[:2]
    assert stamp_to_ns(msg.header.stamp) == STAMP
    assert msg.header.frame_id == 'cam'
    # The node's decoder reads what the bag tools write.
    np.testing.assert_array_equal(image_to_array(msg), array)


def test_image_rejects_other_layouts() -> None:
    with pytest.raises(InputError, match=r'\(2, 2, 4\)'):
        image_to_msg(np.zeros((2, 2, 4), np.uint8), 0, 'cam')
    with pytest.raises(InputError, match='float'):
        float_image_to_msg(np.zeros((2, 2), np.int32), 0, 'cam')


def test_header_splits_stamp_and_rejects_negative() -> None:
    header = make_header(STAMP, 'f')
    assert (header.stamp.sec, header.stamp.nanosec) == (1_700_000_000, 123_456_789)
    with pytest.raises(InputError, match='>= 0'):
        make_header(-1, 'f')


def test_disparity_image_holds_d_plus_offset_and_reads_back() -> None:
    geometry = StereoGeometry(fx=80.0, fy=80.0, cx=10.0, cy=5.0, cx_right=12.5, baseline=0.2)
    disparity = np.array([[0.0, 3.0, np.nan], [7.25, 1.0, 2.0]], np.float32)
    msg = _cdr_round_trip(
        disparity_to_msg(disparity, STAMP, 'left', geometry, delta_d=0.0), DISPARITY_IMAGE
    )
    values = np.frombuffer(msg.image.data, '<f4').reshape(2, 3)
    np.testing.assert_array_equal(values, [[2.5, 5.5, np.nan], [9.75, 3.5, 4.5]])
    assert (msg.f, msg.t, msg.min_disparity, msg.max_disparity) == (80.0, pytest.approx(0.2),
                                                                    2.5, 9.75)
    assert (msg.valid_window.width, msg.valid_window.height) == (3, 2)
    np.testing.assert_array_equal(disparity_from_msg(msg, offset=2.5), disparity)
    # Below min_disparity is invalid by the message's definition.
    msg.image.data = np.array([1.0, 5.5, 2.5, 9.75, 3.5, 4.5], '<f4').view(np.uint8)
    read = disparity_from_msg(msg, offset=2.5)
    assert np.isnan(read[0, 0]) and read[0, 2] == 0.0


def test_plain_float_images_are_raw_disparity() -> None:
    msg = float_image_to_msg(np.array([[-1.0, 0.0, np.inf, 4.5]], np.float32), STAMP, 'l')
    np.testing.assert_array_equal(disparity_from_msg(msg, offset=3.0), [[np.nan, 0, np.nan, 4.5]])
    # A big-endian 64FC1 image of the same values.
    msg.encoding, msg.is_bigendian, msg.step = '64FC1', 1, 32
    msg.data = np.array([[-1.0, 0.0, np.inf, 4.5]], '>f8').view(np.uint8).ravel()
    np.testing.assert_array_equal(disparity_from_msg(msg), [[np.nan, 0, np.nan, 4.5]])


@pytest.mark.parametrize(
    ('change', 'message'),
    [({'encoding': 'mono8'}, "unknown image encoding 'mono8'"), ({'step': 2}, 'needs step')],
)
def test_disparity_from_bad_images(change: dict[str, object], message: str) -> None:
    msg = float_image_to_msg(np.zeros((2, 3), np.float32), STAMP, 'l')
    for key, value in change.items():
        setattr(msg, key, value)
    with pytest.raises(InputError, match=message):
        disparity_from_msg(msg, what='/gt')


def test_camera_infos_of_a_rectified_pair() -> None:
    geometry = StereoGeometry(fx=100.0, fy=90.0, cx=31.5, cy=23.5, cx_right=33.0, baseline=0.12)
    left, right = (
        _cdr_round_trip(msg, CAMERA_INFO)
        for msg in camera_info_msgs(geometry, 64, 48, STAMP, ('l', 'r'))
    )
    np.testing.assert_allclose(left.k, [100, 0, 31.5, 0, 90, 23.5, 0, 0, 1])
    np.testing.assert_allclose(left.p, [100, 0, 31.5, 0, 0, 90, 23.5, 0, 0, 0, 1, 0])
    np.testing.assert_allclose(right.p, [100, 0, 33.0, -12.0, 0, 90, 23.5, 0, 0, 0, 1, 0])
    np.testing.assert_allclose(right.r, np.eye(3).ravel())
    assert (right.header.frame_id, right.width, right.height) == ('r', 64, 48)
    read, width, height = camera_geometry(left, right)
    assert (width, height) == (64, 48)
    assert read.disparity_offset == pytest.approx(1.5)
    assert (read.fx, read.fy, read.baseline) == (100.0, 90.0, pytest.approx(0.12))
    right.width = 32
    with pytest.raises(InputError, match='same size'):
        camera_geometry(left, right)

"""Review fixes of the bag I/O and the message conversions: ±inf and negative disparities
written as NaN, delta_d and min_disparity checked, camera info sizes checked, timestamps a
rosbag2 cannot hold and message types the typestore does not know refused as BagError, a
single topic name taken as one topic."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cva_confidence_ros.errors import BagError, InputError
from cva_confidence_ros.pointcloud import StereoGeometry
from msg_tools.bagio import STORAGES, InputBag, OutputBag, deserialize
from msg_tools.convert import (
    IMAGE,
    camera_info_msgs,
    disparity_from_msg,
    disparity_to_msg,
    image_to_msg,
    jazzy_typestore,
)

GEOMETRY = StereoGeometry(fx=80.0, fy=80.0, cx=10.0, cy=5.0, cx_right=11.5, baseline=0.2)


def _image(value: int) -> object:
    return image_to_msg(np.full((2, 3), value, np.uint8), 0, 'cam')


def test_inf_and_negative_disparities_are_written_nan() -> None:
    # Before: +inf was written as inf, a valid value by DisparityImage's definition (not
    # below min_disparity), i.e. a point at depth fT/inf = 0 for every consumer.
    disparity = np.array([[np.inf, 3.0, -np.inf], [-2.0, np.nan, 0.0]], np.float32)
    msg = disparity_to_msg(disparity, 0, 'left', GEOMETRY)
    values = np.frombuffer(bytes(msg.image.data), '<f4').reshape(2, 3)
    np.testing.assert_array_equal(values, [[np.nan, 4.5, np.nan], [np.nan, np.nan, 1.5]])
    assert (msg.min_disparity, msg.max_disparity) == (1.5, 4.5)
    np.testing.assert_array_equal(
        disparity_from_msg(msg, 1.5), [[np.nan, 3.0, np.nan], [np.nan, np.nan, 0.0]]
    )
    # A float64 value beyond float32 is no disparity either (was written as inf).
    big = disparity_to_msg(np.array([[1e40, 2.0]]), 0, 'left', GEOMETRY)
    assert np.isnan(np.frombuffer(bytes(big.image.data), '<f4')[0])


@pytest.mark.parametrize('delta_d', [float('nan'), float('inf'), -0.0625])
def test_a_delta_d_that_is_no_step_is_refused(delta_d: float) -> None:
    # Before: written into the message as it was.
    with pytest.raises(InputError, match=r'delta_d must be a finite number >= 0; got'):
        disparity_to_msg(np.zeros((2, 2), np.float32), 0, 'left', GEOMETRY, delta_d=delta_d)


@pytest.mark.parametrize('lowest', [float('nan'), float('inf')])
def test_a_disparity_image_without_a_finite_min_disparity_is_refused(lowest: float) -> None:
    msg = disparity_to_msg(np.array([[0.0, 2.0, 5.0]], np.float32), 0, 'left', GEOMETRY)
    msg.min_disparity = lowest
    # Before: every pixel came back NaN, a ground truth that silently scores nothing.
    with pytest.raises(InputError, match=r'/gt: the DisparityImage has min_disparity (nan|inf)'):
        disparity_from_msg(msg, 1.5, '/gt')


@pytest.mark.parametrize(
    ('width', 'height', 'match'),
    [
        (64.7, 48, r'width must be an integer .*; got 64\.7'),
        (0, 48, r'width must be an integer .*; got 0'),
        (64, -1, r'height must be an integer .*; got -1'),
    ],
)
def test_camera_infos_of_a_size_no_image_has_are_refused(
    width: object, height: object, match: str
) -> None:
    # Before: 64.7 was cut to 64 silently, 0 written, and -1 failed at serialisation with a
    # bare struct.error.
    with pytest.raises(InputError, match=match):
        camera_info_msgs(GEOMETRY, width, height, 0, ('l', 'r'))  # type: ignore[arg-type]
    with pytest.raises(InputError, match='two frame ids'):
        camera_info_msgs(GEOMETRY, 64, 48, 0, ('l',))  # type: ignore[arg-type]


@pytest.mark.parametrize('storage', STORAGES)
@pytest.mark.parametrize('stamp', [-1, 2**63, float('nan')])
def test_a_timestamp_a_bag_cannot_hold_is_a_bag_error(
    tmp_path: Path, storage: str, stamp: float
) -> None:
    # Before: a bare OverflowError (mcap) or ValueError (NaN), or a negative timestamp written
    # into a sqlite3 bag without a word.
    path = tmp_path / 'out'
    with OutputBag(path, storage=storage) as bag:
        bag.write('/a', IMAGE, _image(1), 5)
        with pytest.raises(BagError, match=r'timestamp must be 0 … 2\^63 − 1 ns; got'):
            bag.write('/a', IMAGE, _image(2), stamp)  # type: ignore[arg-type]
        bag.write('/a', IMAGE, _image(3), 2**63 - 1)
    with InputBag(path) as bag:
        assert [stamp for _, _, stamp, _ in bag.messages(['/a'])] == [5, 2**63 - 1]


def test_a_message_type_the_typestore_does_not_know_is_a_bag_error(tmp_path: Path) -> None:
    # Before: rosbags' TypesysError on writing, a KeyError on reading.
    with OutputBag(tmp_path / 'out') as bag:
        with pytest.raises(BagError, match=r"'my_msgs/msg/Thing' is not a message type"):
            bag.write('/thing', 'my_msgs/msg/Thing', b'\x00\x01\x00\x00', 1)
        bag.write('/a', IMAGE, _image(1), 1)
    with pytest.raises(BagError, match=r"message 0 on /thing cannot be read: its type "
                                       r"'my_msgs/msg/Thing' is not"):
        deserialize(jazzy_typestore(), b'\x00\x01\x00\x00', 'my_msgs/msg/Thing',
                    'message 0 on /thing')


def test_a_single_topic_name_is_one_topic(tmp_path: Path) -> None:
    path = tmp_path / 'bag'
    with OutputBag(path) as bag:
        bag.write('/a', IMAGE, _image(1), 1)
        bag.write('/a', IMAGE, _image(2), 2)
    with InputBag(path) as bag:
        # Before: '/a' was taken as the topics '/' and 'a': nothing, without an error.
        assert [stamp for _, _, stamp, _ in bag.messages('/a')] == [1, 2]
        # Before: a type was matched as a part of the string ('...Image' in '...ImageX').
        with pytest.raises(BagError, match=r'has type sensor_msgs/msg/Image; expected one of '
                                           r"\['sensor_msgs/msg/ImageX'\]"):
            bag.require('/a', 'sensor_msgs/msg/ImageX', 'left')
        assert bag.require('/a', IMAGE, 'left') == IMAGE

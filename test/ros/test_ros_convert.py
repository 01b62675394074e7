"""Tests of the rclpy message ⇄ numpy conversions (no DDS needed)."""

from __future__ import annotations

import cv2
from node_test_utils import image_msg, info_msgs
import numpy as np
import pytest
from sensor_msgs.msg import CompressedImage, Image, PointCloud2, PointField
from std_msgs.msg import Header

from cva_confidence_ros.errors import InputError
from cva_confidence_ros.pointcloud import (
    CLOUD_CONFIDENCE_DTYPE,
    CLOUD_DTYPE,
    StereoGeometry,
    make_cloud,
)
from cva_confidence_ros.ros.convert import (
    SUPPORTED_ENCODINGS,
    array_to_image,
    camera_info_to_geometry,
    cloud_to_array,
    cloud_to_message,
    depth_image_to_array,
    depth_to_image,
    disparity_from_message,
    disparity_to_message,
    float_image_to_array,
    image_camera_info,
    image_to_array,
    ns_to_stamp,
    pair_to_uint8,
    point_cloud_to_records,
    records_to_point_cloud,
    rgb_to_image,
    scale_camera_info,
    stamp_to_ns,
    stereo_pair_from_messages,
)

RGB = np.array([[[10, 20, 30], [40, 50, 60], [70, 80, 90]]], np.uint8)  # 1×3 pixels


def _raw(data: bytes, height: int, width: int, encoding: str, step: int, big: bool = False):
    return Image(
        height=height, width=width, encoding=encoding, step=step, is_bigendian=big, data=data
    )


def test_stamp_round_trip() -> None:
    stamp = ns_to_stamp(1_700_000_000_123_456_789)
    assert (stamp.sec, stamp.nanosec) == (1_700_000_000, 123_456_789)
    assert stamp_to_ns(stamp) == 1_700_000_000_123_456_789


@pytest.mark.parametrize(
    ('encoding', 'pixels'),
    [
        ('rgb8', RGB),
        ('bgr8', RGB[..., ::-1]),
        ('rgba8', np.concatenate([RGB, np.full((1, 3, 1), 255, np.uint8)], axis=2)),
        ('bgra8', np.concatenate([RGB[..., ::-1], np.zeros((1, 3, 1), np.uint8)], axis=2)),
    ],
)
def test_colour_encodings_give_rgb(encoding: str, pixels: np.ndarray) -> None:
    msg = _raw(pixels.tobytes(), 1, 3, encoding, pixels.shape[2] * 3)
    out = image_to_array(msg)
    assert out.dtype == np.uint8 and out.shape == (1, 3, 3)
    np.testing.assert_array_equal(out, RGB)


def test_mono8_with_row_padding() -> None:
    # 2×3 image, rows padded to 4 bytes; the padding byte (99) must not leak in.
    data = bytes([1, 2, 3, 99, 4, 5, 6, 99])
    out = image_to_array(_raw(data, 2, 3, 'mono8', 4))
    np.testing.assert_array_equal(out, [[1, 2, 3], [4, 5, 6]])
    assert out.flags.writeable and out.flags.c_contiguous


@pytest.mark.parametrize('big', [False, True])
def test_mono16_endianness(big: bool) -> None:
    values = np.array([[1, 256, 4095]], np.uint16)
    data = values.astype('>u2' if big else '<u2').tobytes()
    out = image_to_array(_raw(data, 1, 3, 'mono16', 6, big))
    assert out.dtype == np.uint16
    np.testing.assert_array_equal(out, values)


def test_supported_encodings() -> None:
    assert set(SUPPORTED_ENCODINGS) == {'mono8', 'mono16', 'rgb8', 'bgr8', 'rgba8', 'bgra8',
                                        '8uc1', '16uc1'}


@pytest.mark.parametrize(
    ('msg', 'match'),
    [
        (_raw(b'\x00' * 12, 1, 3, '32FC1', 12), 'encoding'),
        (_raw(b'\x00' * 4, 2, 3, 'mono8', 3), 'data must hold'),
        (_raw(b'\x00' * 7, 2, 3, 'mono8', 3), 'data must hold 2 rows of step 3 .6 bytes.; got 7'),
        (_raw(b'\x00' * 6, 2, 3, 'mono8', 2), 'step'),
        (_raw(b'', 0, 3, 'mono8', 3), 'positive size'),
    ],
)
def test_bad_images(msg: Image, match: str) -> None:
    with pytest.raises(InputError, match=match):
        image_to_array(msg)


def test_pair_to_uint8_scales_16_bit_jointly() -> None:
    left = np.array([[0, 1000]], np.uint16)
    right = np.array([[4000, 2000]], np.uint16)
    out_left, out_right = pair_to_uint8(left, right)
    # 12-bit data: one factor 255/4000 for both.
    np.testing.assert_array_equal(out_left, [[0, 64]])
    np.testing.assert_array_equal(out_right, [[255, 128]])
    eight = np.zeros((1, 2), np.uint8)
    assert pair_to_uint8(eight, eight)[0] is eight
    with pytest.raises(InputError, match='both'):
        pair_to_uint8(eight, left)


def test_float_image_round_trip() -> None:
    array = np.array([[0.0, 0.5], [np.nan, 1.0], [2.0, -1.0]], np.float32)
    header = Header(frame_id='f', stamp=ns_to_stamp(5))
    msg = array_to_image(array, header)
    assert (msg.encoding, msg.height, msg.width, msg.step) == ('32FC1', 3, 2, 8)
    assert msg.header.frame_id == 'f'
    np.testing.assert_array_equal(float_image_to_array(msg), array)
    with pytest.raises(InputError, match='32FC1'):
        float_image_to_array(image_msg(np.zeros((2, 2), np.uint8), 0))


def test_rgb_image_round_trip() -> None:
    rgb = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3)
    msg = rgb_to_image(rgb, Header(frame_id='f', stamp=ns_to_stamp(5)))
    assert (msg.encoding, msg.height, msg.width, msg.step) == ('rgb8', 2, 3, 9)
    np.testing.assert_array_equal(image_to_array(msg), rgb)
    with pytest.raises(InputError, match='rgb8 image must be \\(H, W, 3\\) uint8'):
        rgb_to_image(rgb.astype(np.float32), Header())
    with pytest.raises(InputError, match='rgb8'):
        rgb_to_image(rgb[..., 0], Header())


def test_depth_image_32fc1_metres_with_nan() -> None:
    depth = np.array([[0.5, np.nan, 2.25], [np.inf, -1.0, 70.0]], np.float32)
    msg = depth_to_image(depth, Header(frame_id='left', stamp=ns_to_stamp(7)))
    assert (msg.encoding, msg.height, msg.width, msg.step, msg.is_bigendian) == (
        '32FC1', 2, 3, 12, 0
    )
    assert msg.header.frame_id == 'left' and stamp_to_ns(msg.header.stamp) == 7
    values = np.frombuffer(bytes(msg.data), '<f4').reshape(2, 3)
    # REP 118 float form: metres, NaN wherever there is no depth (±inf and ≤ 0 included).
    np.testing.assert_array_equal(values, [[0.5, np.nan, 2.25], [np.nan, np.nan, 70.0]])
    np.testing.assert_array_equal(depth_image_to_array(msg), values)


def test_depth_image_16uc1_millimetres_with_zero() -> None:
    depth = np.array([[0.5, np.nan, 2.2504], [65.535, 65.5356, 0.0004]], np.float32)
    msg = depth_to_image(depth, Header(), '16UC1')
    assert (msg.encoding, msg.step) == ('16UC1', 6)
    values = np.frombuffer(bytes(msg.data), '<u2').reshape(2, 3)
    # Millimetres rounded; no depth, beyond 65.535 m or below 0.5 mm: 0 (no depth).
    np.testing.assert_array_equal(values, [[500, 0, 2250], [65535, 0, 0]])
    np.testing.assert_allclose(
        depth_image_to_array(msg), [[0.5, np.nan, 2.25], [65.535, np.nan, np.nan]], rtol=1e-6
    )


def test_depth_image_decoding_reads_big_endian_and_row_padding() -> None:
    data = np.array([[1000, 0], [2500, 7]], '>u2')
    padded = np.zeros((2, 6), np.uint8)
    padded[:, :4] = data.view(np.uint8).reshape(2, 4)
    msg = _raw(padded.tobytes(), 2, 2, '16UC1', step=6, big=True)
    np.testing.assert_allclose(depth_image_to_array(msg), [[1.0, np.nan], [2.5, 0.007]])


def test_float_and_depth_images_without_the_last_rows_padding_decode() -> None:
    # As image_to_array: data of step · (H − 1) + row bytes, the last row's padding left out,
    # was refused by the 32FC1 and depth decoders ('needs … 16 bytes; got … 12').
    values = np.array([[1.5], [-2.0]], '<f4')
    data = values[0].tobytes() + b'\xff' * 4 + values[1].tobytes()
    msg = _raw(data, 2, 1, '32FC1', step=8)
    np.testing.assert_array_equal(float_image_to_array(msg), [[1.5], [-2.0]])
    np.testing.assert_array_equal(depth_image_to_array(msg), [[1.5], [np.nan]])
    millimetres = np.array([2500, 7], '>u2').tobytes()
    msg = _raw(millimetres[:2] + b'\x00' * 2 + millimetres[2:], 2, 1, '16UC1', step=4, big=True)
    np.testing.assert_allclose(depth_image_to_array(msg), [[2.5], [0.007]])
    # One byte fewer is still refused, by name.
    with pytest.raises(
        InputError,
        match=r"^32FC1 image data must hold 2 rows of step 8 \(16 bytes, or 12 without the last "
        r"row's padding\); got 11$",
    ):
        float_image_to_array(_raw(data[:-1], 2, 1, '32FC1', step=8))
    with pytest.raises(InputError, match=r'^16UC1 depth image data must hold 2 rows .*; got 5$'):
        depth_image_to_array(_raw(b'\x00' * 5, 2, 1, '16UC1', step=4))
    # The same checks as image_to_array's (they were a copy that let these through): data
    # longer than the rows, a zero size, a step shorter than a row; named by the caller.
    with pytest.raises(InputError, match=r'^32FC1 image data must hold .*; got 17$'):
        float_image_to_array(_raw(data + b'\x00' * 5, 2, 1, '32FC1', step=8))
    with pytest.raises(InputError, match=r'^range image must have a positive size; got 1×0$'):
        depth_image_to_array(_raw(b'', 0, 1, '32FC1', step=4), 'range image')
    with pytest.raises(InputError, match=r'^16UC1 depth image step must be ≥ 4 bytes for 2 px'):
        depth_image_to_array(_raw(b'\x00' * 6, 2, 2, '16UC1', step=3))
    with pytest.raises(InputError, match=r"^disparity image: expected 32FC1; got 'mono8'$"):
        float_image_to_array(_raw(b'\x00' * 2, 2, 1, 'mono8', step=1), 'disparity image')
    with pytest.raises(InputError, match=r"^depth image: expected 32FC1 or 16UC1; got 'mono8'$"):
        depth_image_to_array(_raw(b'\x00' * 2, 2, 1, 'mono8', step=1))


@pytest.mark.parametrize(
    ('call', 'match'),
    [
        (lambda: depth_to_image(np.ones((2, 2)), Header(), '16UC2'), '32FC1'),
        (lambda: depth_to_image(np.ones((2, 2, 1)), Header()), '2-D'),
        (lambda: depth_to_image(np.ones((2, 2), bool), Header()), 'real'),
        (lambda: depth_image_to_array(image_msg(np.zeros((2, 2), np.uint8), 0)), 'mono8'),
        (lambda: depth_image_to_array(_raw(bytes(6), 2, 2, '16UC1', step=4)), 'bytes'),
    ],
)
def test_depth_image_refuses(call, match: str) -> None:
    with pytest.raises(InputError, match=match):
        call()


def test_camera_info_geometry_and_size_check() -> None:
    left_info, right_info = info_msgs(0, height=64, width=96, fx=100.0, baseline=0.1)
    geometry = camera_info_to_geometry(left_info, right_info, 96, 64)
    assert (geometry.fx, geometry.fy, geometry.cx, geometry.cy) == (100.0, 100.0, 48.0, 32.0)
    assert geometry.cx_right == 48.0
    assert geometry.baseline == pytest.approx(0.1)
    with pytest.raises(InputError, match='left camera info must be for 97×64'):
        camera_info_to_geometry(left_info, right_info, 97, 64)
    right_info.p[3] = 5.0  # a "right" camera to the left
    with pytest.raises(InputError, match='baseline'):
        camera_info_to_geometry(left_info, right_info, 96, 64)
    right_info.p[3] = np.nan
    with pytest.raises(InputError, match='finite'):
        camera_info_to_geometry(left_info, right_info, 96, 64)


def test_binning_and_region_of_interest_are_folded_in_as_image_geometry_does() -> None:
    # The full-sensor calibration (192×128, fx 200, cx 96, cy 64) with binning 2: 96×64 images
    # of fx 100 and cx 48, the geometry of an info made for them directly.
    left_info, right_info = info_msgs(0, height=128, width=192, fx=200.0, baseline=0.1)
    for info in (left_info, right_info):
        info.binning_x = info.binning_y = 2
    binned = camera_info_to_geometry(left_info, right_info, 96, 64)
    direct = camera_info_to_geometry(*info_msgs(0, height=64, width=96, fx=100.0,
                                                 baseline=0.1), 96, 64)
    assert binned == direct
    out = image_camera_info(left_info, 96, 64)
    assert (out.width, out.height, out.binning_x, out.binning_y) == (96, 64, 0, 0)
    assert list(out.k) == [100.0, 0.0, 48.0, 0.0, 100.0, 32.0, 0.0, 0.0, 1.0]
    assert list(out.p)[:4] == [100.0, 0.0, 48.0, 0.0]
    # A 96×64 region of interest at (50, 20) of the sensor, not binned: the principal point
    # moves by the offset, fx and the baseline stay.
    left_info, right_info = info_msgs(0, height=128, width=192, fx=200.0, baseline=0.1)
    for info in (left_info, right_info):
        info.roi.x_offset, info.roi.y_offset, info.roi.width, info.roi.height = 50, 20, 96, 64
    cropped = camera_info_to_geometry(left_info, right_info, 96, 64)
    assert (cropped.fx, cropped.cx, cropped.cy, cropped.cx_right) == (200.0, 46.0, 44.0, 46.0)
    assert cropped.baseline == pytest.approx(0.1)
    # Images of the info's own size take it as it is (P is for the full resolution; drivers
    # that fill the ROI with the valid rectified area).
    whole = camera_info_to_geometry(left_info, right_info, 192, 128)
    assert (whole.cx, whole.cy) == (96.0, 64.0)
    # ... and publish it so (review 31): the same K and P, no ROI left to misread them by.
    published = image_camera_info(left_info, 192, 128)
    assert list(published.p) == list(left_info.p) and list(published.k) == list(left_info.k)
    assert (published.roi.width, published.roi.height, published.roi.x_offset) == (0, 0, 0)
    with pytest.raises(InputError, match=r'got 96×64 \(binning 0×0 and region of interest '
                                         r'96×64 at \(50, 20\) of its 192×128\)'):
        camera_info_to_geometry(left_info, right_info, 48, 32)


def test_stereo_pair_from_messages() -> None:
    rng = np.random.default_rng(0)
    mono16 = rng.integers(0, 4096, (64, 96), dtype=np.uint16)  # a 12-bit camera
    infos = info_msgs(0, height=64, width=96, fx=100.0, baseline=0.1)
    left, right, geometry = stereo_pair_from_messages(
        image_msg(mono16, 0), image_msg(mono16 // 2, 0), *infos
    )
    assert left.dtype == right.dtype == np.uint8 and left.max() == 255
    assert geometry.baseline == pytest.approx(0.1)
    narrow = image_msg(np.zeros((64, 95), np.uint16), 0)
    with pytest.raises(InputError, match='same size; got 96×64 and 95×64'):
        stereo_pair_from_messages(image_msg(mono16, 0), narrow, *infos)
    with pytest.raises(InputError, match='must both be 8-bit or both 16-bit'):
        stereo_pair_from_messages(image_msg(mono16, 0), image_msg(left, 0), *infos)
    with pytest.raises(InputError, match='camera info must be for 48×32'):
        small = image_msg(mono16[::2, ::2].copy(), 0)
        stereo_pair_from_messages(small, small, *infos)
    # Which side is bad is part of the reason, so the node's log throttle keeps them apart.
    short = image_msg(mono16, 0)
    short.data = short.data[:-10]
    for side, pair in (('left', (short, image_msg(mono16, 0))),
                       ('right', (image_msg(mono16, 0), short))):
        with pytest.raises(InputError, match=f'^{side} image data must hold 64 rows'):
            stereo_pair_from_messages(*pair, *infos)
    odd = image_msg(left, 0)
    odd.encoding = 'yuv422'
    with pytest.raises(InputError, match="^right image encoding must be one of .*'yuv422'"):
        stereo_pair_from_messages(image_msg(left, 0), odd, *infos)


def test_disparity_message_like_stereo_image_proc() -> None:
    # cx_left = 48, cx_right = 50: published values are d + 2, invalid = min_disparity − 1.
    geometry = StereoGeometry(fx=100.0, fy=100.0, cx=48.0, cy=32.0, cx_right=50.0, baseline=0.1)
    disparity = np.array([[3.0, np.nan, 0.0, 7.5]], np.float32)
    header = Header(frame_id='left', stamp=ns_to_stamp(42))
    msg = disparity_to_message(disparity, header, geometry, max_disparity=16, delta_d=0.25)
    assert msg.header.frame_id == 'left' and msg.image.header.stamp.nanosec == 42
    assert msg.image.encoding == '32FC1' and (msg.image.height, msg.image.width) == (1, 4)
    assert msg.f == pytest.approx(100.0) and msg.t == pytest.approx(0.1)
    assert msg.min_disparity == pytest.approx(2.0) and msg.max_disparity == pytest.approx(17.0)
    assert msg.delta_d == pytest.approx(0.25)
    np.testing.assert_array_equal(float_image_to_array(msg.image), [[5.0, 1.0, 2.0, 9.5]])
    # Z = f·T/d holds on the published value: d = 3 → 5 → Z = 2 (Z = fB/(d + Δ) in the core).
    assert msg.f * msg.t / 5.0 == pytest.approx(2.0)
    np.testing.assert_array_equal(disparity_from_message(msg), [[5.0, np.nan, 2.0, 9.5]])
    window = msg.valid_window
    assert (window.x_offset, window.y_offset, window.width, window.height) == (4, 0, 0, 1)


def test_valid_window() -> None:
    geometry = StereoGeometry(fx=1.0, fy=1.0, cx=0.0, cy=0.0, cx_right=0.0, baseline=1.0)
    msg = disparity_to_message(np.zeros((5, 40), np.float32), Header(), geometry, 16)
    window = msg.valid_window
    assert (window.x_offset, window.y_offset, window.width, window.height) == (15, 0, 25, 5)


def test_cloud_message_round_trip() -> None:
    points = np.arange(2 * 3 * 3, dtype=np.float32).reshape(2, 3, 3)
    points[0, 1] = np.nan
    colours = np.zeros((2, 3), np.float32)
    header = Header(frame_id='left')
    organised = cloud_to_message(make_cloud(points, colours, True), header)
    assert (organised.height, organised.width, organised.is_dense) == (2, 3, False)
    assert (organised.point_step, organised.row_step) == (16, 48)
    assert [(f.name, f.offset, f.datatype) for f in organised.fields] == [
        ('x', 0, PointField.FLOAT32),
        ('y', 4, PointField.FLOAT32),
        ('z', 8, PointField.FLOAT32),
        ('rgb', 12, PointField.FLOAT32),
    ]
    back = cloud_to_array(organised)
    assert back.dtype == CLOUD_DTYPE and back.shape == (2, 3)
    np.testing.assert_array_equal(back['z'], points[..., 2])
    dense = cloud_to_message(make_cloud(points, colours, False), header)
    assert (dense.height, dense.width, dense.is_dense) == (1, 5, True)
    assert len(dense.data) == 5 * 16
    with pytest.raises(InputError, match='dtype'):
        cloud_to_message(np.zeros(3, np.float32), header)


def test_cloud_with_confidence_round_trip() -> None:
    points = np.ones((2, 3, 3), np.float32)
    points[1, 2] = np.nan
    confidence = np.linspace(0, 1, 6, dtype=np.float32).reshape(2, 3)
    cloud = make_cloud(points, np.zeros((2, 3), np.float32), True, confidence=confidence)
    msg = cloud_to_message(cloud, Header(frame_id='left'))
    assert (msg.point_step, msg.row_step) == (20, 60)
    assert [(f.name, f.offset, f.datatype, f.count) for f in msg.fields][-1] == (
        'confidence', 16, PointField.FLOAT32, 1
    )
    back = cloud_to_array(msg)
    assert back.dtype == CLOUD_CONFIDENCE_DTYPE
    np.testing.assert_array_equal(back['confidence'], confidence)


def _point_fields(*extra: tuple[str, int, int, int]) -> list[PointField]:
    """float32 x, y, z at 0, 4, 8, then ``(name, offset, datatype, count)`` fields."""
    xyz = [(name, 4 * k, PointField.FLOAT32, 1) for k, name in enumerate('xyz')]
    return [
        PointField(name=name, offset=offset, datatype=datatype, count=count)
        for name, offset, datatype, count in (*xyz, *extra)
    ]


def _foreign_cloud() -> PointCloud2:
    # x, y, z float32; a uint8[3] colour at 12; float64 score at 16; 24-byte points; 4 points
    # a row and 5 padding bytes at each row's end; 2 rows.
    fields = _point_fields(('bgr', 12, PointField.UINT8, 3), ('score', 16, PointField.FLOAT64, 1))
    dtype = np.dtype({'names': ['x', 'y', 'z', 'bgr', 'score'],
                      'formats': ['<f4', '<f4', '<f4', ('u1', (3,)), '<f8'],
                      'offsets': [0, 4, 8, 12, 16], 'itemsize': 24})
    records = np.zeros((2, 4), dtype)
    records['x'] = np.arange(8).reshape(2, 4)
    records['bgr'] = [1, 2, 3]
    records['score'] = np.linspace(0, 1, 8).reshape(2, 4)
    rows = np.full((2, 4 * 24 + 5), 0xEE, np.uint8)
    rows[:, : 4 * 24] = records.view(np.uint8).reshape(2, -1)
    return PointCloud2(header=Header(frame_id='lidar'), height=2, width=4, fields=fields,
                       is_bigendian=False, point_step=24, row_step=4 * 24 + 5,
                       data=rows.tobytes(), is_dense=True)


def test_foreign_cloud_records_round_trip() -> None:
    msg = _foreign_cloud()
    records = point_cloud_to_records(msg)
    assert records.shape == (2, 4) and records.dtype.itemsize == 24
    np.testing.assert_array_equal(records['x'], np.arange(8).reshape(2, 4))
    np.testing.assert_array_equal(records['bgr'][1, 3], [1, 2, 3])
    np.testing.assert_allclose(records['score'].ravel(), np.linspace(0, 1, 8))
    again = records_to_point_cloud(records[1], msg.header)  # one row: (N,)
    assert (again.height, again.width, again.row_step, again.is_dense) == (1, 4, 96, True)
    assert [(f.name, f.offset, f.datatype, f.count) for f in again.fields] == [
        (f.name, f.offset, f.datatype, f.count) for f in msg.fields
    ]
    np.testing.assert_array_equal(point_cloud_to_records(again)[0]['x'], records[1]['x'])
    with pytest.raises(InputError, match='x, y, z, rgb'):
        cloud_to_array(msg)


@pytest.mark.parametrize(
    ('change', 'match'),
    [
        ({'is_bigendian': True}, 'big-endian'),
        ({'row_step': 10}, 'row_step 10 is shorter'),
        ({'data': b'\0' * 50}, 'holds 50 bytes'),
        ({'point_step': 20}, "'score' .* does not fit in point_step 20"),
        ({'point_step': 0}, r'point_step is 0 for a cloud of 2×4 points'),
    ],
)
def test_point_cloud_to_records_refuses(change: dict, match: str) -> None:
    msg = _foreign_cloud()
    for key, value in change.items():
        setattr(msg, key, value)
    with pytest.raises(InputError, match=match):
        point_cloud_to_records(msg)


def test_point_cloud_to_records_refuses_bad_fields() -> None:
    msg = _foreign_cloud()
    msg.fields[3].datatype = 42
    with pytest.raises(InputError, match="'bgr' has unknown datatype 42"):
        point_cloud_to_records(msg)
    msg = _foreign_cloud()
    msg.fields[4].name = 'x'
    with pytest.raises(InputError, match="'x' appears twice"):
        point_cloud_to_records(msg)
    with pytest.raises(InputError, match='structured'):
        records_to_point_cloud(np.zeros(3), Header())


def test_pcl_padding_fields_are_padding() -> None:
    # ROS 1 PCL clouds declare each gap as a field named '_', several per point: read as
    # padding (the bytes kept in the item size), not refused as a field that appears twice.
    fields = _point_fields(
        ('_', 12, PointField.UINT8, 4),
        ('confidence', 16, PointField.FLOAT32, 1),
        ('_', 20, PointField.UINT8, 12),
    )
    points = np.zeros(3, np.dtype({'names': ['x', 'y', 'z', 'confidence'],
                                   'formats': ['<f4'] * 4, 'offsets': [0, 4, 8, 16],
                                   'itemsize': 32}))
    points['z'] = [1.0, 2.0, 3.0]
    points['confidence'] = [0.1, 0.5, 0.9]
    msg = PointCloud2(header=Header(), height=1, width=3, fields=fields, is_bigendian=False,
                      point_step=32, row_step=96, data=points.tobytes(), is_dense=True)
    records = point_cloud_to_records(msg)
    assert records.dtype.names == ('x', 'y', 'z', 'confidence')
    assert records.dtype.itemsize == 32
    np.testing.assert_array_equal(records['confidence'][0], points['confidence'])
    np.testing.assert_array_equal(records['z'][0], points['z'])


def test_scale_camera_info() -> None:
    left_info, right_info = info_msgs(7, height=65, width=97, fx=100.0, baseline=0.1)
    roi = left_info.roi
    roi.x_offset, roi.width, roi.height = 10, 80, 65  # REP 104: images of 80×65
    header = Header(frame_id='out', stamp=ns_to_stamp(7))
    half = scale_camera_info(left_info, 2, header)
    assert (half.width, half.height) == (40, 32)  # 80 → 40 and 65 → 64 → 32
    assert half.header.frame_id == 'out'
    # The ROI folded in (review 33): cx = 48.5 − 10 = 38.5 → (38.5 + 0.5)/2 − 0.5 = 19;
    # cy = 32.5 → 16; no ROI left.
    np.testing.assert_allclose(half.k, [50, 0, 19, 0, 50, 16, 0, 0, 1])
    np.testing.assert_allclose(half.p, [50, 0, 19, 0, 0, 50, 16, 0, 0, 0, 1, 0])
    assert (half.roi.x_offset, half.roi.width, half.roi.height) == (0, 0, 0)
    right_half = scale_camera_info(right_info, 2, header)
    assert right_half.p[3] == pytest.approx(-5.0)  # −fx·B at half size
    plain = info_msgs(7, height=65, width=97, fx=100.0)[0]
    plain_half = scale_camera_info(plain, 2, header)
    assert (plain_half.width, plain_half.height) == (48, 32)  # 97 → 96 → 48, 65 → 64 → 32
    geometry = camera_info_to_geometry(plain_half, right_half, 48, 32)
    assert geometry.baseline == pytest.approx(0.1)
    unchanged = scale_camera_info(plain, 1, header)
    np.testing.assert_allclose(unchanged.k, plain.k)
    assert (unchanged.width, unchanged.height) == (97, 65)


def _compressed(array: np.ndarray, extension: str, fmt: str) -> CompressedImage:
    pixels = cv2.cvtColor(array, cv2.COLOR_RGB2BGR) if array.ndim == 3 else array
    ok, data = cv2.imencode(extension, pixels)
    assert ok
    return CompressedImage(header=Header(), format=fmt, data=data.tobytes())


def test_compressed_png_decodes_exactly_in_the_core_layout() -> None:
    rng = np.random.default_rng(0)
    gray = rng.integers(0, 256, (12, 17), dtype=np.uint8)
    rgb = rng.integers(0, 256, (12, 17, 3), dtype=np.uint8)
    deep = rng.integers(0, 4096, (12, 17), dtype=np.uint16)
    assert np.array_equal(image_to_array(_compressed(gray, '.png', 'mono8; png compressed')), gray)
    decoded = image_to_array(_compressed(rgb, '.png', 'rgb8; png compressed'))
    assert decoded.shape == (12, 17, 3) and np.array_equal(decoded, rgb)  # RGB, not OpenCV's BGR
    sixteen = image_to_array(_compressed(deep, '.png', 'mono16; png compressed'))
    assert sixteen.dtype == np.uint16 and np.array_equal(sixteen, deep)
    # JPEG: lossy, same layout; a bare format string as older publishers write it
    jpeg = image_to_array(_compressed(rgb, '.jpg', 'jpeg'))
    assert jpeg.shape == (12, 17, 3) and jpeg.dtype == np.uint8


def test_a_compressed_pair_decodes_like_the_raw_pair() -> None:
    rng = np.random.default_rng(1)
    left, right = (rng.integers(0, 256, (20, 30), dtype=np.uint8) for _ in range(2))
    infos = info_msgs(0, 20, 30)
    raw = stereo_pair_from_messages(image_msg(left, 0), image_msg(right, 0), *infos)
    packed = stereo_pair_from_messages(
        _compressed(left, '.png', 'mono8; png compressed'),
        _compressed(right, '.png', 'mono8; png compressed'),
        *infos,
    )
    assert np.array_equal(packed[0], raw[0]) and np.array_equal(packed[1], raw[1])
    assert packed[2] == raw[2]


@pytest.mark.parametrize(
    ('fmt', 'data', 'message'),
    [
        ('16UC1; compressedDepth png', b'\x00' * 20, 'compressedDepth'),
        ('mono8; png compressed', b'', 'no data'),
        ('mono8; jpeg compressed', b'definitely not a jpeg', 'is neither a JPEG nor a PNG'),
        # A PNG header whose image data is cut off: the size is read, OpenCV cannot decode.
        ('mono8; png compressed',
         cv2.imencode('.png', np.eye(9, dtype=np.uint8))[1].tobytes()[:40],
         'do not decode as an image'),
    ],
)
def test_compressed_images_that_cannot_be_intensity_images_are_refused(
    fmt: str, data: bytes, message: str
) -> None:
    msg = CompressedImage(header=Header(), format=fmt, data=data)
    with pytest.raises(InputError, match=message) as caught:
        image_to_array(msg, 'left image')
    assert 'left image' in str(caught.value)

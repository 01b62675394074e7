"""image_transport's compressed and compressedDepth formats as the node writes them."""

from __future__ import annotations

import re

import cv2
import numpy as np
import pytest
from sensor_msgs.msg import CompressedImage
from std_msgs.msg import Header

from cva_confidence_ros.errors import InputError
from cva_confidence_ros.ros.convert import compressed_image_to_array, depth_to_image
from cva_confidence_ros.ros.transport import (
    COMPRESSED_DEPTH_HEADER,
    compressed_depth_to_array,
    compressed_depth_values,
    depth_image_to_compressed_depth,
    rgb_to_compressed,
)


def _payload(msg: CompressedImage) -> tuple[tuple[int, float, float], np.ndarray]:
    """The header and the 16-bit PNG of a compressedDepth message, read without the module."""
    data = bytes(msg.data)
    codes = cv2.imdecode(np.frombuffer(data[12:], np.uint8), cv2.IMREAD_UNCHANGED)
    return COMPRESSED_DEPTH_HEADER.unpack(data[:12]), codes


def test_32fc1_depth_travels_as_the_plugins_inverse_depth_codes() -> None:
    # A = Q(Q + 1) = 10100, B = 1 − A/depth_max = −1009 with the defaults (Q 100, 10 m);
    # code = trunc(A/z + B): 1 m → 9091, 2 m → 4041, 9.99 m → 2 (the last before 10 m), 0.1 m
    # would be 100991 (> 16 bits) → 65535; NaN, ≤ 0 and ≥ depth_max → 0 (no depth).
    depth = np.array([[1.0, 2.0, 9.99, 0.1], [np.nan, 0.0, 10.0, 25.0]], dtype=np.float32)
    header = Header(frame_id='left_optical')
    msg = depth_image_to_compressed_depth(depth_to_image(depth, header, '32FC1'))
    assert msg.format == '32FC1; compressedDepth png'
    assert msg.header == header
    (kind, a, b), codes = _payload(msg)
    assert (kind, a, b) == (0, 10100.0, -1009.0)
    assert codes.dtype == np.uint16
    np.testing.assert_array_equal(codes, [[9091, 4041, 2, 65535], [0, 0, 0, 0]])
    np.testing.assert_array_equal(codes, compressed_depth_values(depth)[0])


def test_32fc1_round_trip_is_within_the_quantisation_step() -> None:
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.2, 12.0, (40, 50)).astype(np.float32)
    depth[:3] = np.nan
    for quantization, depth_max in ((100.0, 10.0), (400.0, 30.0)):
        msg = depth_image_to_compressed_depth(
            depth_to_image(depth, Header(), '32FC1'), depth_max, quantization, png_level=1
        )
        back = compressed_depth_to_array(msg)
        with np.errstate(invalid='ignore'):
            sent = np.isfinite(depth) & (depth < depth_max)
        np.testing.assert_array_equal(np.isfinite(back), sent)
        # The nearest depth 16 bits hold (0.15 m; 2.26 m for Q 400 and 30 m): nearer ones
        # arrive as it, not wrapped around to a far depth.
        a = quantization * (quantization + 1.0)
        nearest = a / (65535.0 - (1.0 - a / depth_max))
        near = sent & (depth < nearest)
        assert near.any() == (quantization == 400.0)
        np.testing.assert_allclose(back[near], nearest, rtol=1e-4)
        fine = sent & ~near
        step = depth[fine] ** 2 / a
        error = np.abs(back[fine] - depth[fine])
        assert np.all(error <= step * 1.01)
        assert error.max() > 0.3 * step.max()  # a real quantisation, not a float copy


def test_16uc1_depth_travels_as_millimetres_cut_at_depth_max() -> None:
    depth = np.array([[0.5, 1.234, 9.999, 10.001, np.nan]], dtype=np.float32)
    msg = depth_image_to_compressed_depth(depth_to_image(depth, Header(), '16UC1'))
    assert msg.format == '16UC1; compressedDepth png'
    (kind, a, b), codes = _payload(msg)
    assert (kind, a, b) == (0, 0.0, 0.0)
    np.testing.assert_array_equal(codes, [[500, 1234, 9999, 0, 0]])
    back = compressed_depth_to_array(msg)
    np.testing.assert_allclose(back[0, :3], [0.5, 1.234, 9.999], rtol=1e-6)
    assert np.isnan(back[0, 3:]).all()


def test_overlay_as_jpeg_and_png_in_compressed_image_transports_format() -> None:
    # A smooth picture (what the overlay over a scene is): JPEG within a few grey levels, PNG
    # exact; both decode with the node's own compressed-input reader.
    y, x = np.mgrid[0:48, 0:64]
    rgb = np.stack([x * 4, y * 5, (x + y) * 2], axis=-1).astype(np.uint8)
    header = Header(frame_id='left_optical')
    jpeg = rgb_to_compressed(rgb, header)
    assert jpeg.format == 'rgb8; jpeg compressed bgr8' and jpeg.header == header
    assert np.abs(compressed_image_to_array(jpeg).astype(int) - rgb).mean() < 2.0
    small = rgb_to_compressed(rgb, header, jpeg_quality=20)
    assert len(small.data) < len(jpeg.data)
    png = rgb_to_compressed(rgb, header, image_format='png', png_level=1)
    assert png.format == 'rgb8; png compressed bgr8'
    np.testing.assert_array_equal(compressed_image_to_array(png), rgb)


@pytest.mark.parametrize(
    ('call', 'message'),
    [
        (lambda: rgb_to_compressed(np.zeros((4, 4), np.uint8), Header()), '(H, W, 3) uint8'),
        (lambda: rgb_to_compressed(np.zeros((4, 4, 3), np.uint8), Header(), jpeg_quality=0),
         'jpeg_quality must be in [1, 100]'),
        (lambda: rgb_to_compressed(np.zeros((4, 4, 3), np.uint8), Header(), 'webp'),
         "'jpeg' or 'png'"),
        (lambda: compressed_depth_values(np.ones((2, 2)), depth_max=0.0),
         'depth_max must be a positive number'),
        (lambda: compressed_depth_values(np.ones((2, 2)), depth_quantization=float('nan')),
         'depth_quantization must be a positive number'),
    ],
)
def test_encoding_refuses_what_it_cannot_send(call: object, message: str) -> None:
    with pytest.raises(InputError, match=re.escape(message)):
        call()  # type: ignore[operator]


def test_only_depth_images_become_compressed_depth() -> None:
    from cva_confidence_ros.ros.convert import array_to_image

    image = array_to_image(np.ones((2, 2), np.float32), Header())
    image.encoding = 'mono16'
    with pytest.raises(InputError, match="32FC1 or 16UC1 depth images; got 'mono16'"):
        depth_image_to_compressed_depth(image)


@pytest.mark.parametrize(
    ('fmt', 'data', 'message'),
    [
        ('rgb8; jpeg compressed bgr8', b'\xff' * 40, 'not a compressedDepth image'),
        ('32FC1; compressedDepth rvl', b'\x00' * 40, 'RVL compressedDepth is not supported'),
        ('mono8; compressedDepth png', b'\x00' * 40, "compressedDepth of 'mono8'"),
        ('32FC1; compressedDepth png', b'\x00' * 12, 'fewer than its 12-byte header'),
        ('32FC1; compressedDepth png', b'\x00' * 12 + b'not a png', 'not a one-channel 16-bit'),
    ],
)
def test_decoding_names_what_is_wrong(fmt: str, data: bytes, message: str) -> None:
    with pytest.raises(InputError, match=re.escape(message)):
        compressed_depth_to_array(CompressedImage(format=fmt, data=data))

"""Review 30 of ros/transport.py: corrupt compressedDepth payloads and level types."""

from __future__ import annotations

import re
import struct
import warnings
import zlib

import cv2
import numpy as np
import pytest
from sensor_msgs.msg import CompressedImage
from std_msgs.msg import Header

from cva_confidence_ros.errors import InputError
from cva_confidence_ros.ros.convert import depth_to_image
from cva_confidence_ros.ros.transport import (
    COMPRESSED_DEPTH_HEADER,
    compressed_depth_to_array,
    depth_image_to_compressed_depth,
    rgb_to_compressed,
)


def _png_chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack('>I', len(body)) + kind + body + struct.pack('>I', zlib.crc32(kind + body))


def test_a_png_naming_more_pixels_than_opencv_reads_is_an_input_error() -> None:
    # A 60-byte message whose PNG header claims 40000 × 40000 16-bit pixels (1.6e9, beyond
    # OpenCV's 2**30): cv2.imdecode raised cv2.error out of the decoder instead of InputError.
    header = struct.pack('>IIBBBBB', 40000, 40000, 16, 0, 0, 0, 0)
    png = (
        b'\x89PNG\r\n\x1a\n'
        + _png_chunk(b'IHDR', header)
        + _png_chunk(b'IDAT', zlib.compress(b'\x00' * 8))
        + _png_chunk(b'IEND', b'')
    )
    msg = CompressedImage(
        format='32FC1; compressedDepth png',
        data=COMPRESSED_DEPTH_HEADER.pack(0, 10100.0, -1009.0) + png,
    )
    with pytest.raises(InputError, match='does not decode as a 16-bit PNG'):
        compressed_depth_to_array(msg, 'depth')


def test_a_header_whose_depths_overflow_float32_is_refused() -> None:
    # A = 3e38 > 0 and B = 0.9999999 < 1 passed the header check, but A / (q − B) is beyond
    # float32 for code 1: every pixel came back inf (a depth), with a RuntimeWarning.
    ok, png = cv2.imencode('.png', np.ones((2, 3), np.uint16))
    assert ok
    msg = CompressedImage(
        format='32FC1; compressedDepth png',
        data=COMPRESSED_DEPTH_HEADER.pack(0, 3e38, 0.9999999) + png.tobytes(),
    )
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        with pytest.raises(InputError, match=re.escape('beyond float32')):
            compressed_depth_to_array(msg, 'depth')
    # A header a valid encoder writes still decodes (code 1 is depth_max).
    msg.data = COMPRESSED_DEPTH_HEADER.pack(0, 10100.0, -1009.0) + png.tobytes()
    np.testing.assert_allclose(compressed_depth_to_array(msg), 10.0)


@pytest.mark.parametrize('level', [True, 2.5, '3', np.float64(3.0)])
def test_compression_levels_must_be_integers(level: object) -> None:
    # True was quality 1 (the worst), 2.5 was cut to 2, '3' a TypeError from the comparison.
    rgb = np.zeros((4, 5, 3), np.uint8)
    with pytest.raises(InputError, match=re.escape('jpeg_quality must be in [1, 100], an int')):
        rgb_to_compressed(rgb, Header(), jpeg_quality=level)  # type: ignore[arg-type]
    with pytest.raises(InputError, match=re.escape('png_level must be in [0, 9], an integer')):
        rgb_to_compressed(rgb, Header(), image_format='png', png_level=level)  # type: ignore[arg-type]
    depth = depth_to_image(np.ones((2, 2), np.float32), Header(), '32FC1')
    with pytest.raises(InputError, match=re.escape('png_level must be in [0, 9], an integer')):
        depth_image_to_compressed_depth(depth, png_level=level)  # type: ignore[arg-type]
    # Integers, numpy ones too, stay accepted.
    assert rgb_to_compressed(rgb, Header(), jpeg_quality=np.int64(80)).data
    assert depth_image_to_compressed_depth(depth, png_level=np.uint8(1)).data

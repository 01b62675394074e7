"""Review 38 of the message conversions, against the conventions of the ROS packages that
produce and consume them (image_transport's plugins, stereo_image_proc, REP 117 / 118); each
test is the regression test of a fault found in the review."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from sensor_msgs.msg import CompressedImage, Image

from cva_confidence_ros.errors import InputError
from cva_confidence_ros.ros.convert import compressed_image_to_array, image_to_array


@pytest.mark.parametrize(
    ('encoding', 'extension'),
    [('bayer_rggb8', '.png'), ('bayer_grbg8', '.jpg'), ('BAYER_BGGR8', '.png')],
)
def test_a_compressed_bayer_image_is_refused_as_the_raw_one_is(
    encoding: str, extension: str
) -> None:
    # compressed_image_transport compresses a non-colour encoding as it is and names it before
    # the ';' ("bayer_rggb8; png compressed "): the raw mosaic decoded as a gray image and was
    # matched as one, while the same image uncompressed is refused.
    ok, data = cv2.imencode(extension, np.random.default_rng(0).integers(0, 255, (8, 8), np.uint8))
    assert ok
    kind = extension.lstrip('.').replace('jpg', 'jpeg')
    msg = CompressedImage(format=f'{encoding}; {kind} compressed ', data=data.tobytes())
    with pytest.raises(InputError, match='raw Bayer .* image_proc'):
        compressed_image_to_array(msg, 'left image')
    with pytest.raises(InputError, match='raw Bayer'):
        image_to_array(msg, 'left image')  # the node's entry point for either kind
    # Gray and colour ones, of any spelling the plugin writes, are still decoded.
    gray = np.arange(48, dtype=np.uint8).reshape(6, 8)
    ok, data = cv2.imencode('.png', gray)
    for text in ('mono8; png compressed ', 'png', '8UC1; png compressed '):
        out = compressed_image_to_array(CompressedImage(format=text, data=data.tobytes()))
        np.testing.assert_array_equal(out, gray)
    bgr = np.zeros((4, 4, 3), np.uint8)
    bgr[..., 2] = 200
    ok, data = cv2.imencode('.png', bgr)
    formats = ('bgr8; png compressed bgr8', 'rgb8; png compressed bgr8', '8UC3; png compressed ')
    for text in formats:
        out = compressed_image_to_array(CompressedImage(format=text, data=data.tobytes()))
        assert out[0, 0].tolist() == [200, 0, 0]


def _raw(encoding: str, pixel_bytes: int) -> Image:
    return Image(
        height=2, width=3, encoding=encoding, step=3 * pixel_bytes, data=bytes(6 * pixel_bytes)
    )


@pytest.mark.parametrize('encoding', ['bgr16', 'rgb16', 'bgra16', 'rgba16'])
def test_a_16_bit_colour_image_says_to_take_the_16_bit_gray_one(encoding: str) -> None:
    # stereo_image_proc's image_rect_color of a 16-bit Bayer camera is bgr16 (image_proc's
    # debayer), which the node does not read. Was: only "encoding must be one of (...)".
    with pytest.raises(InputError, match=f"got '{encoding}': 16-bit colour .*image_rect .mono16."):
        image_to_array(_raw(encoding, 8), 'left image')
    # compressed, the same image is a 16-bit colour PNG and read as 16-bit gray, as before
    ok, data = cv2.imencode('.png', np.full((2, 3, 3), 1000, np.uint16))
    msg = CompressedImage(format=f'{encoding}; png compressed bgr16', data=data.tobytes())
    out = compressed_image_to_array(msg)
    assert out.dtype == np.uint16 and out.shape == (2, 3)


def test_a_16_bit_bayer_image_names_the_topic_the_node_reads() -> None:
    # Was: "give the node its image_rect (mono8) or image_rect_color (bgr8)"; of a 16-bit
    # Bayer camera, debayer publishes mono16 and bgr16, and image_rect_color is refused.
    with pytest.raises(InputError, match=r'raw Bayer .*image_rect \(mono16\)$'):
        image_to_array(_raw('bayer_rggb16', 2), 'left image')
    with pytest.raises(InputError, match=r'image_rect_color \(bgr8\)$'):
        image_to_array(_raw('bayer_rggb8', 1), 'left image')

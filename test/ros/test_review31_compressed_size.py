"""Review 31: the node's compressed input reads the size a JPEG or PNG names in its header
before OpenCV decodes it; a message of a few kilobytes could name gigabytes."""

from __future__ import annotations

import struct
from types import SimpleNamespace
import zlib

import cv2
import numpy as np
import pytest

from cva_confidence_ros.errors import InputError
from cva_confidence_ros.ros.convert import compressed_image_to_array, compressed_size
from cva_confidence_ros.ros.transport import MAX_PNG_PIXELS


def _chunk(kind: bytes, payload: bytes) -> bytes:
    body = kind + payload
    return struct.pack('>I', len(payload)) + body + struct.pack('>I', zlib.crc32(body))


def one_bit_png(width: int, height: int) -> bytes:
    """A black 1-bit gray PNG: some kilobytes for many megapixels."""
    rows = (b'\0' + bytes((width + 7) // 8)) * height
    return (b'\x89PNG\r\n\x1a\n'
            + _chunk(b'IHDR', struct.pack('>IIBBBBB', width, height, 1, 0, 0, 0, 0))
            + _chunk(b'IDAT', zlib.compress(rows, 9)) + _chunk(b'IEND', b''))


def jpeg_naming(width: int, height: int) -> bytes:
    """A real 8×8 JPEG whose frame header is changed to name ``width``×``height``."""
    ok, buffer = cv2.imencode('.jpg', np.full((8, 8), 128, np.uint8))
    assert ok
    data = bytearray(buffer.tobytes())
    at = data.index(b'\xff\xc0')
    data[at + 5:at + 9] = struct.pack('>HH', height, width)
    return bytes(data)


def message(data: bytes, image_format: str = 'mono8; png compressed') -> SimpleNamespace:
    return SimpleNamespace(format=image_format, data=data)


def test_a_png_naming_more_pixels_than_the_bound_is_refused_before_decoding() -> None:
    data = one_bit_png(8000, 6000)  # 48 MP, some kilobytes
    assert len(data) < 100_000 and 8000 * 6000 > MAX_PNG_PIXELS
    # Before: decoded into a 48 MB array and accepted (a palette one: 2.3 GB, 15 s).
    with pytest.raises(InputError, match=r'^left: the compressed image names 8000×6000 = '
                                         r'48000000 pixels; at most 33554432 are decoded$'):
        compressed_image_to_array(message(data), 'left')


def test_a_jpeg_naming_more_pixels_than_the_bound_is_refused_before_decoding() -> None:
    with pytest.raises(InputError, match='names 6000×6000 = 36000000 pixels'):
        compressed_image_to_array(message(jpeg_naming(6000, 6000), 'jpeg'), 'right')


def test_a_payload_that_is_no_jpeg_or_png_is_refused() -> None:
    # OpenCV decodes PGM, BMP, TIFF … by their own signatures: a PGM came out as an image.
    ok, pgm = cv2.imencode('.pgm', np.zeros((3, 4), np.uint8))
    assert ok
    with pytest.raises(InputError, match=r"is neither a JPEG nor a PNG \(it starts b'P5"):
        compressed_image_to_array(message(pgm.tobytes(), 'jpeg'))


@pytest.mark.parametrize('data', [b'\xff\xd8', b'\xff\xd8\xff\xe0\x00\x10JFIF\x00',
                                  jpeg_naming(8, 8)[:20]])
def test_a_jpeg_cut_before_its_frame_header_is_refused(data: bytes) -> None:
    with pytest.raises(InputError, match='a JPEG without a frame header'):
        compressed_image_to_array(message(data, 'jpeg'))


def test_a_jpeg_naming_an_empty_image_is_refused() -> None:
    with pytest.raises(InputError, match='the JPEG header names an empty 0×8 image'):
        compressed_size(jpeg_naming(0, 8))


@pytest.mark.parametrize('shape', [(1, 1), (37, 53), (48, 64, 3), (600, 1001)])
@pytest.mark.parametrize(('ext', 'params'), [
    ('.jpg', []), ('.jpg', [cv2.IMWRITE_JPEG_PROGRESSIVE, 1]),
    ('.jpg', [cv2.IMWRITE_JPEG_OPTIMIZE, 1]), ('.png', []),
    ('.png', [cv2.IMWRITE_PNG_COMPRESSION, 0]),
])
def test_the_header_size_is_the_decoded_size(shape: tuple[int, ...], ext: str,
                                             params: list[int]) -> None:
    image = np.random.default_rng(0).integers(0, 256, shape, dtype=np.uint8)
    ok, buffer = cv2.imencode(ext, image, params)
    assert ok
    assert compressed_size(buffer.tobytes()) == (shape[1], shape[0])
    decoded = compressed_image_to_array(message(buffer.tobytes(), ext[1:]))
    assert decoded.shape[:2] == shape[:2]

"""Hostile or damaged files given to the readers: a small file must not decode to gigabytes,
a header must not make the reader allocate what the file does not hold, and every fault is a
short error of the package's own classes."""

from __future__ import annotations

from pathlib import Path
import struct
import zlib

import cv2
import numpy as np
import pytest

from cva_confidence_ros.datasets import io, loaders
from cva_confidence_ros.datasets.io import read_disparity_png, read_image, read_pfm
from cva_confidence_ros.errors import ConfigError, DataError
from cva_confidence_ros.mask import load_mask


def _chunk(kind: bytes, data: bytes) -> bytes:
    crc = zlib.crc32(kind + data) & 0xFFFFFFFF
    return struct.pack('>I', len(data)) + kind + data + struct.pack('>I', crc)


def _png_header_only(width: int, height: int) -> bytes:
    """A valid PNG signature and IHDR (8-bit RGB) declaring ``width × height``, with one row
    of data: about 100 bytes."""
    ihdr = struct.pack('>IIBBBBB', width, height, 8, 2, 0, 0, 0)
    row = zlib.compress(b'\0' * (1 + 3 * width))
    return (
        b'\x89PNG\r\n\x1a\n' + _chunk(b'IHDR', ihdr) + _chunk(b'IDAT', row)
        + _chunk(b'IEND', b'')
    )


def _no_decoding(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*args: object) -> None:
        raise AssertionError('cv2.imread was called: the image was decoded')

    monkeypatch.setattr(cv2, 'imread', refuse)


def test_a_png_declaring_too_many_pixels_is_refused_before_decoding(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A 2.6 MB PNG of 30000 × 30000 decoded to 2.7 GB (5.3 GB peak, 31 s) before this check.
    bomb = tmp_path / 'bomb.png'
    bomb.write_bytes(_png_header_only(30000, 30000))
    assert bomb.stat().st_size < 1000
    _no_decoding(monkeypatch)
    with pytest.raises(DataError, match=r'bomb\.png declares more than \d+ pixels'):
        read_image(bomb)
    with pytest.raises(DataError, match='declares more than'):
        read_disparity_png(bomb, 256.0)


def test_the_pixel_limit_is_checked_on_the_header(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / 'small.png'
    assert cv2.imwrite(str(path), np.zeros((20, 30, 3), np.uint8))
    assert read_image(path).shape == (20, 30, 3)
    monkeypatch.setattr(io, 'MAX_IMAGE_PIXELS', 599, raising=False)
    _no_decoding(monkeypatch)
    with pytest.raises(DataError, match=r'small\.png declares 30×20 pixels, more than 599'):
        read_image(path)
    ppm = tmp_path / 'bomb.ppm'  # a 100-byte PPM declaring 20000 × 20000
    ppm.write_bytes(b'P6\n20000 20000\n255\n' + b'\0' * 100)
    with pytest.raises(DataError, match='declares'):
        read_image(ppm)


def test_a_mask_declaring_too_many_pixels_is_a_config_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    bomb = tmp_path / 'robot.png'
    bomb.write_bytes(_png_header_only(30000, 30000))
    _no_decoding(monkeypatch)
    with pytest.raises(ConfigError, match=r"mask_path '.*robot\.png' cannot be used as a mask: "
                                          r'.*declares more than'):
        load_mask(bomb)


def test_a_truncated_jpeg_mask_is_refused(tmp_path: Path) -> None:
    # Its missing rows decoded grey, i.e. 'judge': the robot's body there was published.
    mask = np.random.default_rng(0).integers(128, 256, (48, 64), dtype=np.uint8)
    mask[:, 32:] = 0
    path = tmp_path / 'mask.jpg'
    assert cv2.imwrite(str(path), mask)
    assert load_mask(path)[:, :30].all()
    data = path.read_bytes()
    path.write_bytes(data[: len(data) * 3 // 4])
    with io._quiet_opencv():
        decoded = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert decoded is not None  # OpenCV decodes it, with grey rows
    with pytest.raises(ConfigError, match='truncated JPEG'):
        load_mask(path)


def _npy_header(shape: tuple[int, ...], descr: str = '<f4') -> bytes:
    header = f"{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}"
    header += ' ' * (118 - len(header)) + '\n'
    return b'\x93NUMPY\x01\x00' + struct.pack('<H', len(header)) + header.encode('ascii')


def test_an_npy_header_declaring_more_than_the_file_holds_allocates_nothing(
    tmp_path: Path,
) -> None:
    # 100 bytes declaring 10^7 × 10^7 float32 (400 TB): np.load raised MemoryError.
    path = tmp_path / 'disparity.npy'
    path.write_bytes(_npy_header((10**7, 10**7)) + b'\0' * 100)
    with pytest.raises(DataError, match='less data than its header declares'):
        loaders._read_npy(path)
    # Mapped, an object array is still refused, not unpickled.
    np.save(path, np.array([{'a': 1}], dtype=object), allow_pickle=True)
    with pytest.raises(DataError, match='cannot read'):
        loaders._read_npy(path)


def test_an_npy_disparity_beyond_the_pixel_limit_is_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / 'disparity.npy'
    np.save(path, np.asfortranarray(np.arange(12, dtype=np.float64).reshape(3, 4)))
    values = loaders._read_npy(path)
    assert values.dtype == np.float32 and values.flags['C_CONTIGUOUS']
    np.testing.assert_array_equal(values, np.arange(12).reshape(3, 4))
    monkeypatch.setattr(loaders, 'MAX_IMAGE_PIXELS', 11, raising=False)
    with pytest.raises(DataError, match=r'a 4×3 array is more than 11 pixels'):
        loaders._read_npy(path)


def test_a_pfm_header_of_thousands_of_digits_gives_a_short_message(tmp_path: Path) -> None:
    path = tmp_path / 'disp.pfm'
    path.write_bytes(b'Pf\n' + b'9' * 4000 + b' 2\n-1.0\n' + b'\0' * 24)
    with pytest.raises(DataError) as caught:
        read_pfm(path)
    assert len(str(caught.value)) < 300
    path.write_bytes(b'Pf\n' + b'9' * 5000 + b' 2\n-1.0\n' + b'\0' * 24)  # beyond int()
    with pytest.raises(DataError, match='bad PFM size or scale') as caught:
        read_pfm(path)
    assert len(str(caught.value)) < 300

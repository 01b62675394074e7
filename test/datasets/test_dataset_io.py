"""File formats: PFM, images, encoded disparity PNGs, calibration files."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from cva_confidence_ros.datasets.io import (
    Calibration,
    read_disparity_png,
    read_image,
    read_kitti_calibration,
    read_middlebury_calibration,
    read_pfm,
    write_pfm,
)
from cva_confidence_ros.errors import DataError


def test_pfm_round_trip_gray_and_colour(tmp_path: Path) -> None:
    gray = np.arange(12, dtype=np.float32).reshape(3, 4) - 2.5
    gray[0, 0] = np.inf
    colour = np.random.default_rng(0).random((2, 3, 3), dtype=np.float32)
    write_pfm(tmp_path / 'g.pfm', gray)
    write_pfm(tmp_path / 'c.pfm', colour)
    np.testing.assert_array_equal(read_pfm(tmp_path / 'g.pfm'), gray)
    np.testing.assert_array_equal(read_pfm(tmp_path / 'c.pfm'), colour)
    assert read_pfm(tmp_path / 'g.pfm').dtype == np.float32


def test_pfm_rows_bottom_to_top_and_big_endian(tmp_path: Path) -> None:
    # Hand-written big-endian file (positive scale), rows stored bottom first, with the
    # trailing spaces some writers put in the header.
    body = np.array([[3.0, 4.0], [1.0, 2.0]], dtype='>f4').tobytes()
    (tmp_path / 'be.pfm').write_bytes(b'Pf \n2 2 \n1.0\n' + body)
    np.testing.assert_array_equal(read_pfm(tmp_path / 'be.pfm'), [[1.0, 2.0], [3.0, 4.0]])
    # The same values little-endian (negative scale).
    body = np.array([[3.0, 4.0], [1.0, 2.0]], dtype='<f4').tobytes()
    (tmp_path / 'le.pfm').write_bytes(b'Pf\n2 2\n-1.0\n' + body)
    np.testing.assert_array_equal(read_pfm(tmp_path / 'le.pfm'), [[1.0, 2.0], [3.0, 4.0]])


def test_written_pfm_header_is_little_endian(tmp_path: Path) -> None:
    write_pfm(tmp_path / 'x.pfm', np.ones((2, 5)))
    assert (tmp_path / 'x.pfm').read_bytes().startswith(b'Pf\n5 2\n-1.0\n')


@pytest.mark.parametrize(
    'content', [b'P6\n2 2\n255\n' + bytes(12), b'Pf\n2 2\n-1.0\n' + bytes(8), b'Pf\n2\n']
)
def test_bad_pfm(tmp_path: Path, content: bytes) -> None:
    (tmp_path / 'bad.pfm').write_bytes(content)
    with pytest.raises(DataError):
        read_pfm(tmp_path / 'bad.pfm')


def test_missing_pfm(tmp_path: Path) -> None:
    with pytest.raises(DataError, match='cannot read'):
        read_pfm(tmp_path / 'none.pfm')


def test_read_image_rgb_order_gray_and_alpha(tmp_path: Path) -> None:
    rgb = np.zeros((2, 3, 3), np.uint8)
    rgb[..., 0] = 200  # red
    cv2.imwrite(str(tmp_path / 'rgb.png'), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    np.testing.assert_array_equal(read_image(tmp_path / 'rgb.png'), rgb)
    gray = np.arange(6, dtype=np.uint8).reshape(2, 3)
    cv2.imwrite(str(tmp_path / 'g.pgm'), gray)
    np.testing.assert_array_equal(read_image(tmp_path / 'g.pgm'), gray)
    bgra = np.dstack([np.full((2, 3), c, np.uint8) for c in (10, 20, 30, 255)])
    cv2.imwrite(str(tmp_path / 'a.png'), bgra)
    assert read_image(tmp_path / 'a.png')[0, 0].tolist() == [30, 20, 10]
    with pytest.raises(DataError, match='cannot read image'):
        read_image(tmp_path / 'missing.png')


def test_read_disparity_png_scales_and_marks_unknown(tmp_path: Path) -> None:
    raw = np.array([[0, 256, 1000], [65535, 128, 0]], dtype=np.uint16)
    cv2.imwrite(str(tmp_path / 'd.png'), raw)
    disparity = read_disparity_png(tmp_path / 'd.png', 256.0)
    assert disparity.dtype == np.float32
    expected = np.array([[np.nan, 1.0, 1000 / 256], [65535 / 256, 0.5, np.nan]])
    np.testing.assert_allclose(disparity, expected, equal_nan=True)
    cv2.imwrite(str(tmp_path / 'd8.png'), np.array([[0, 3, 255]], np.uint8))
    np.testing.assert_allclose(
        read_disparity_png(tmp_path / 'd8.png', 3.0), [[np.nan, 1.0, 85.0]], equal_nan=True
    )


def test_middlebury_calibration(tmp_path: Path) -> None:
    (tmp_path / 'calib.txt').write_text(
        'cam0=[999.421 0 294.182; 0 999.421 252.932; 0 0 1]\n'
        'cam1=[999.421 0 326.96; 0 999.421 252.932; 0 0 1]\n'
        'doffs=32.778\nbaseline=193.001\nwidth=741\nheight=497\nndisp=70\n'
    )
    calib = read_middlebury_calibration(tmp_path / 'calib.txt')
    assert calib == Calibration(
        fx=999.421, fy=999.421, cx=294.182, cy=252.932, baseline=0.193001, doffs=32.778
    )
    # depth = f B / (d + doffs): 999.421 × 0.193001 / 50 m at d = 17.222.
    assert calib.depth(np.array([17.222]))[0] == pytest.approx(999.421 * 0.193001 / 50.0)
    (tmp_path / 'bad.txt').write_text('doffs=1\n')
    with pytest.raises(DataError, match='cam0'):
        read_middlebury_calibration(tmp_path / 'bad.txt')


def test_kitti_calibration(tmp_path: Path) -> None:
    p2 = '7.2e+02 0 6.0e+02 4.5e+01 0 7.2e+02 1.8e+02 0 0 0 1 0'
    p3 = '7.2e+02 0 6.0e+02 -3.15e+02 0 7.2e+02 1.8e+02 0 0 0 1 0'
    (tmp_path / 'c.txt').write_text(f'P0: {p2}\nP1: {p3}\nP2: {p2}\nP3: {p3}\n')
    calib = read_kitti_calibration(tmp_path / 'c.txt')
    assert calib.fx == 720.0 and calib.cx == 600.0 and calib.cy == 180.0
    assert calib.baseline == pytest.approx(360.0 / 720.0)
    assert calib.doffs == 0.0
    (tmp_path / 'r.txt').write_text(f'P_rect_02: {p2}\nP_rect_03: {p3}\n')
    assert read_kitti_calibration(tmp_path / 'r.txt', 'P_rect_02', 'P_rect_03') == calib
    with pytest.raises(DataError, match='P_rect_02'):
        read_kitti_calibration(tmp_path / 'c.txt', 'P_rect_02', 'P_rect_03')


def test_disparity_png_of_the_wrong_bit_depth_is_refused(tmp_path: Path) -> None:
    cv2.imwrite(str(tmp_path / 'd8.png'), np.array([[0, 3, 255]], np.uint8))
    with pytest.raises(DataError, match=r'expected a 16-bit .* got 8-bit.*wrong scale'):
        read_disparity_png(tmp_path / 'd8.png', 256.0, bits=16)
    cv2.imwrite(str(tmp_path / 'd16.png'), np.array([[0, 3, 255]], np.uint16))
    with pytest.raises(DataError, match='expected a 8-bit'):
        read_disparity_png(tmp_path / 'd16.png', 4.0, bits=8)


def test_truncated_jpeg_is_refused_quietly(tmp_path: Path, capfd) -> None:
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (64, 96, 3), dtype=np.uint8)
    whole = tmp_path / 'whole.jpg'
    assert cv2.imwrite(str(whole), image)
    assert read_image(whole).shape == (64, 96, 3)
    cut = tmp_path / 'cut.jpg'
    cut.write_bytes(whole.read_bytes()[: whole.stat().st_size // 3])
    # OpenCV alone decodes it, the missing rows grey, and only libjpeg's warning says so.
    with pytest.raises(DataError, match='truncated JPEG'):
        read_image(cut)
    # A truncated PPM: our one error, not OpenCV's log line beside it.
    ppm = tmp_path / 'cut.ppm'
    assert cv2.imwrite(str(tmp_path / 'whole.ppm'), image)
    ppm.write_bytes((tmp_path / 'whole.ppm').read_bytes()[:200])
    capfd.readouterr()
    with pytest.raises(DataError, match='cannot read image'):
        read_image(ppm)
    assert capfd.readouterr().err == ''


def test_bad_pfm_header_is_quoted_short(tmp_path: Path) -> None:
    (tmp_path / 'noise.pfm').write_bytes(bytes(range(256)) * 8)
    with pytest.raises(DataError, match='is not a PFM file') as caught:
        read_pfm(tmp_path / 'noise.pfm')
    assert len(str(caught.value)) < len(str(tmp_path)) + 200


@pytest.mark.parametrize('scale', [b'nan', b'-nan', b'inf', b'-inf'])
def test_pfm_with_a_non_finite_scale_is_refused(tmp_path: Path, scale: bytes) -> None:
    # The sign of the scale is the byte order; a NaN one was read as big-endian garbage.
    body = np.array([[1.0, 2.0]], dtype='<f4').tobytes()
    (tmp_path / 's.pfm').write_bytes(b'Pf\n2 1\n' + scale + b'\n' + body)
    with pytest.raises(DataError, match='finite, non-zero scale'):
        read_pfm(tmp_path / 's.pfm')


def test_write_pfm_refuses_what_cannot_be_read_back(tmp_path: Path) -> None:
    for shape in ((0, 3), (2, 0), (0, 0, 3)):
        with pytest.raises(DataError, match='at least one pixel'):
            write_pfm(tmp_path / 'e.pfm', np.zeros(shape, np.float32))
    for scale in (float('inf'), float('nan')):
        with pytest.raises(DataError, match='finite and > 0'):
            write_pfm(tmp_path / 's.pfm', np.ones((1, 1)), scale)
    assert not (tmp_path / 'e.pfm').exists() and not (tmp_path / 's.pfm').exists()
    write_pfm(tmp_path / 'one.pfm', np.full((1, 1), 2.5))
    np.testing.assert_array_equal(read_pfm(tmp_path / 'one.pfm'), [[2.5]])


_CALIB = (
    'cam0=[999.421 0 294.182; 0 999.421 252.932; 0 0 1]\n'
    'cam1=[999.421 0 326.96; 0 999.421 252.932; 0 0 1]\n'
    'doffs=32.778\nbaseline=193.001\n'
)
_CALIB_VALUES = Calibration(
    fx=999.421, fy=999.421, cx=294.182, cy=252.932, baseline=0.193001, doffs=32.778
)


def test_middlebury_calibration_with_a_byte_order_mark_or_commas(tmp_path: Path) -> None:
    # Saved by a Windows editor: the mark used to stick to the first key ('cam0' missing).
    (tmp_path / 'bom.txt').write_bytes(('\ufeff' + _CALIB).encode('utf-8'))
    assert read_middlebury_calibration(tmp_path / 'bom.txt') == _CALIB_VALUES
    (tmp_path / 'commas.txt').write_text(
        _CALIB.replace('999.421 0 294.182; 0 999.421 252.932; 0 0 1',
                       '999.421, 0, 294.182; 0, 999.421, 252.932; 0, 0, 1')
    )
    assert read_middlebury_calibration(tmp_path / 'commas.txt') == _CALIB_VALUES


@pytest.mark.parametrize(
    ('old', 'new', 'match'),
    [
        ('baseline=193.001', 'baseline=0', 'baseline must be > 0'),
        ('baseline=193.001', 'baseline=-193.001', 'baseline must be > 0'),
        ('baseline=193.001', 'baseline=nan', 'finite'),
        ('[999.421 0 294.182', '[0 0 294.182', 'focal lengths must be > 0'),
    ],
)
def test_middlebury_calibration_that_gives_no_depth_is_refused(
    tmp_path: Path, old: str, new: str, match: str
) -> None:
    (tmp_path / 'calib.txt').write_text(_CALIB.replace(old, new))
    with pytest.raises(DataError, match=match):
        read_middlebury_calibration(tmp_path / 'calib.txt')


def test_kitti_calibration_that_gives_no_depth_is_refused(tmp_path: Path) -> None:
    p2 = '7.2e+02 0 6.0e+02 4.5e+01 0 7.2e+02 1.8e+02 0 0 0 1 0'
    p3 = '7.2e+02 0 6.0e+02 -3.15e+02 0 7.2e+02 1.8e+02 0 0 0 1 0'
    (tmp_path / 'c.txt').write_text(f'P2: {p2}\nP3: {p3}\nP4: {"0 " * 12}\n')
    # The right camera's keys first: a negative baseline, every depth negative.
    with pytest.raises(DataError, match='baseline must be > 0'):
        read_kitti_calibration(tmp_path / 'c.txt', 'P3', 'P2')
    # A zeroed matrix: ZeroDivisionError before.
    with pytest.raises(DataError, match=r'P4\[0, 0\] \(fx\) must be > 0'):
        read_kitti_calibration(tmp_path / 'c.txt', 'P4', 'P3')
    assert read_kitti_calibration(tmp_path / 'c.txt').baseline == pytest.approx(0.5)

"""Review of datasets.io and datasets.resize: PFM size checks, disparity PNG scale, resize
shapes and dtypes."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from cva_confidence_ros.datasets.io import read_disparity_png, read_pfm
from cva_confidence_ros.datasets.resize import resize_disparity, resize_image
from cva_confidence_ros.errors import ConfigError, DataError, InputError


def test_pfm_with_more_data_than_its_header_is_refused(tmp_path: Path) -> None:
    # A colour map labelled 'Pf' was read as the first third of its values, scrambled.
    colour = np.arange(2 * 2 * 3, dtype='<f4').reshape(2, 2, 3)
    path = tmp_path / 'mislabelled.pfm'
    path.write_bytes(b'Pf\n2 2\n-1.0\n' + colour.tobytes())
    with pytest.raises(DataError, match=r'mislabelled\.pfm: header Pf 2×2 declares 4 .* holds 12'):
        read_pfm(path)
    # A trailing newline (less than one value) is still read.
    body = np.array([[3.0, 4.0], [1.0, 2.0]], dtype='<f4').tobytes()
    (tmp_path / 'nl.pfm').write_bytes(b'Pf\n2 2\n-1.0\n' + body + b'\n')
    np.testing.assert_array_equal(read_pfm(tmp_path / 'nl.pfm'), [[1.0, 2.0], [3.0, 4.0]])


@pytest.mark.parametrize('scale', [0, 0.0, -256.0, float('nan'), float('inf'), True, '256'])
def test_disparity_png_scale_must_be_finite_and_positive(tmp_path: Path, scale: object) -> None:
    # Scale 0 gave inf disparities, a negative one negative disparities, NaN none at all.
    cv2.imwrite(str(tmp_path / 'd.png'), np.array([[0, 256, 512]], np.uint16))
    with pytest.raises(ConfigError, match='scale must be finite and > 0; got'):
        read_disparity_png(tmp_path / 'd.png', scale)  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match='bits must be 8, 16 or None; got 12'):
        read_disparity_png(tmp_path / 'd.png', 256.0, bits=12)
    np.testing.assert_allclose(
        read_disparity_png(tmp_path / 'd.png', np.float32(256.0), bits=16),
        [[np.nan, 1.0, 2.0]],
        equal_nan=True,
    )


def test_resize_image_keeps_a_single_channel_axis() -> None:
    image = np.arange(4 * 6, dtype=np.uint8).reshape(4, 6, 1)
    small = resize_image(image, 2)
    assert small.shape == (2, 3, 1)  # was (2, 3)
    np.testing.assert_array_equal(small[..., 0], resize_image(image[..., 0], 2))


@pytest.mark.parametrize('dtype', [np.float16, np.int32, np.bool_])
def test_resize_image_refuses_dtypes_opencv_cannot_shrink(dtype: type) -> None:
    with pytest.raises(InputError, match=f'cannot shrink an image of dtype {np.dtype(dtype)}'):
        resize_image(np.ones((4, 6, 3), dtype), 2)


def test_resize_image_refuses_other_ranks() -> None:
    with pytest.raises(InputError, match=r'image must be \(H, W\) or \(H, W, C\); got shape'):
        resize_image(np.ones(8, np.uint8), 2)


def test_resize_disparity_refuses_other_ranks() -> None:
    with pytest.raises(InputError, match=r'disparity must be \(H, W\); got shape \(4, 4, 2\)'):
        resize_disparity(np.zeros((4, 4, 2), np.float32), 2)


def test_resize_disparity_factor_one_marks_inf_unknown_like_larger_factors() -> None:
    # Middlebury / ETH3D store unknown as inf: factor 2 gave NaN, factor 1 kept inf.
    disparity = np.array([[np.inf, 1.0], [-np.inf, 2.0]], np.float32)
    same = resize_disparity(disparity, 1)
    assert same.dtype == np.float32
    np.testing.assert_array_equal(same, [[np.nan, 1.0], [np.nan, 2.0]])
    assert np.isinf(disparity[0, 0])  # the input is left alone
    assert np.isnan(resize_disparity(np.full((2, 2), np.inf, np.float32), 2)).all()

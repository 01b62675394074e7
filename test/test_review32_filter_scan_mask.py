"""Review 32: ignore masks that are not (H, W) and laser scans of images without a row."""

from __future__ import annotations

import numpy as np
import pytest

from cva_confidence_ros.errors import InputError
from cva_confidence_ros.mask import check_mask_size, mask_rows, reduce_mask
from cva_confidence_ros.pointcloud import StereoGeometry
from cva_confidence_ros.scan import disparity_to_scan

GEOMETRY = StereoGeometry(fx=100.0, fy=100.0, cx=47.5, cy=31.5, cx_right=47.5, baseline=0.1)


def test_a_colour_mask_of_the_right_size_is_named_by_its_shape() -> None:
    # Was: "the mask (mask_path) is 640×480 px but the images are 640×480 px".
    with pytest.raises(InputError, match=r'must be \(H, W\).*got shape \(48, 64, 3\)'):
        check_mask_size(np.ones((48, 64, 3), bool), 64, 48)


def test_a_flat_mask_is_an_input_error_not_an_index_error() -> None:
    with pytest.raises(InputError, match=r'\(--mask\) must be \(H, W\).*got shape \(64,\)'):
        check_mask_size(np.ones(64, bool), 64, 48, '--mask')


def test_mask_rows_of_a_colour_mask_is_refused_not_counted_across_channels() -> None:
    # Was (11, 12) for a 4-row mask: rows and channels flattened together.
    mask = np.zeros((4, 5, 3), bool)
    mask[3, 0, 2] = True
    with pytest.raises(InputError, match=r'got shape \(4, 5, 3\)'):
        mask_rows(mask)


@pytest.mark.parametrize('shape', [(48, 64, 3), (64,)])
def test_reduce_mask_names_a_mask_that_is_not_h_w(shape: tuple[int, ...]) -> None:
    # Was numpy's "cannot reshape array" ValueError or an IndexError.
    with pytest.raises(InputError, match=r'must be \(H, W\)'):
        reduce_mask(np.ones(shape, bool), 2)


def test_reduce_mask_refuses_a_mask_smaller_than_one_block() -> None:
    # Was an empty (0, 0) mask, where resize_image refuses such an image.
    with pytest.raises(InputError, match=r'cannot shrink a 3×5 px mask by 4'):
        reduce_mask(np.ones((5, 3), bool), 4)
    assert reduce_mask(np.ones((4, 9), bool), 4).shape == (1, 2)


def test_a_scan_of_an_image_without_a_row_is_refused() -> None:
    # Was a scan of 89 NaN beams, its bearings taken at row -1.
    with pytest.raises(InputError, match=r'1 row high; got 96×0'):
        disparity_to_scan(np.zeros((0, 96), np.float32), GEOMETRY)
    level = StereoGeometry(fx=100.0, fy=100.0, cx=47.5, cy=0.0, cx_right=47.5, baseline=0.1)
    scan = disparity_to_scan(np.full((1, 96), 5.0, np.float32), level)
    assert np.isfinite(scan.ranges).all()

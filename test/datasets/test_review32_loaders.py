"""Review of the data set loaders (StereoSample, split errors): regressions on tiny arrays."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from cva_confidence_ros.datasets import StereoSample, list_scenes, read_pfm, write_pfm
from cva_confidence_ros.errors import DataError

H, W = 4, 6


def test_inf_ground_truth_is_stored_as_nan(tmp_path: Path) -> None:
    # Middlebury / ETH3D PFMs mark unknown with +inf and read_pfm returns it as stored; the
    # sample kept it as a disparity ∞ although its docstring says NaN = unknown.
    image = np.zeros((H, W), np.uint8)
    disparity = np.full((H, W), 2.0, np.float32)
    disparity[1, 2] = np.inf
    write_pfm(tmp_path / 'disp0GT.pfm', disparity)
    stored = read_pfm(tmp_path / 'disp0GT.pfm')
    assert np.isposinf(stored[1, 2])
    sample = StereoSample('t', 's', image, image, stored)
    assert np.isnan(sample.disparity[1, 2])
    assert not np.isinf(sample.disparity).any()
    assert sample.disparity.dtype == np.float32 and sample.max_disparity == 2.0
    assert np.isposinf(stored[1, 2])  # the caller's array is left as it was
    disparity[1, 2] = -np.inf  # below 0: still refused, as a negative disparity
    with pytest.raises(DataError, match='disparity must be ≥ 0'):
        StereoSample('t', 's', image, image, disparity)


@pytest.mark.parametrize(
    ('field', 'value', 'got'),
    [
        ('disparity', [[1.0] * W] * H, 'list'),
        ('disparity', None, 'NoneType'),
        ('nonocc', [[True] * W] * H, 'list'),
    ],
)
def test_sample_refuses_a_disparity_or_mask_that_is_no_array(
    field: str, value: object, got: str
) -> None:
    # Both failed with AttributeError: 'list' object has no attribute 'dtype'.
    image = np.zeros((H, W), np.uint8)
    fields = {'disparity': np.zeros((H, W), np.float32), field: value}
    with pytest.raises(DataError, match=rf't/s: {field} must be a numpy array .*got {got}'):
        StereoSample('t', 's', image, image, **fields)


def test_no_pairs_without_a_split_names_the_split_folders_that_hold_pairs(
    tmp_path: Path,
) -> None:
    # The original Middlebury 2005 layout <root>/ThirdSize/<scene>/ without split= said only
    # 'no pairs found' (the error named the splits holding pairs only for a given split).
    folder = tmp_path / 'ThirdSize' / 'Art'
    folder.mkdir(parents=True)
    image = np.random.default_rng(0).integers(0, 256, (H, W, 3), np.uint8)
    for name in ('view1.png', 'view5.png'):
        assert cv2.imwrite(str(folder / name), image)
    assert cv2.imwrite(str(folder / 'disp1.png'), np.full((H, W), 6, np.uint8))
    assert list_scenes('middlebury2005', tmp_path, 'ThirdSize') == ['Art']
    with pytest.raises(
        DataError, match=r"without a split; split\(s\) \['ThirdSize'\] hold pairs there"
    ):
        list_scenes('middlebury2005', tmp_path)

"""``remove_speckles``: hand-made regions, OpenCV's ``filterSpeckles`` as a second opinion, a
real pair, and refusals."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.matching import compute_cost_volume, remove_speckles, wta_disparity

NAN = np.float32(np.nan)


def _islands() -> np.ndarray:
    """NaN background with islands of 3, 10 and 30 pixels at disparities 5, 9 and 20."""
    disparity = np.full((12, 20), NAN, np.float32)
    disparity[1, 1:4] = 5.0  # 3 px
    disparity[4:6, 1:6] = 9.0  # 10 px
    disparity[6:11, 10:16] = 20.0  # 30 px
    return disparity


@pytest.mark.parametrize(
    ('max_size', 'left'),
    [(0, {3, 10, 30}), (2, {3, 10, 30}), (3, {10, 30}), (9, {10, 30}), (10, {30}), (30, set())],
)
def test_regions_of_at_most_max_size_pixels_go(max_size, left):
    disparity = _islands()
    kept = remove_speckles(disparity, max_size=max_size)
    sizes = {3: disparity == 5, 10: disparity == 9, 30: disparity == 20}
    for size, region in sizes.items():
        assert np.all(kept[region]) == (size in left)
        assert not np.any(kept[region]) == (size not in left)
    assert not kept[np.isnan(disparity)].any()


def test_neighbours_join_within_max_range_only():
    # A ramp of 0.9 px a column: one region of 40 with range 1, forty regions of 4 with 0.5.
    disparity = np.tile(np.arange(10, dtype=np.float32) * 0.9, (4, 1))
    assert remove_speckles(disparity, max_size=39, max_range=1.0).all()
    assert not remove_speckles(disparity, max_size=4, max_range=0.5).any()
    # Equal steps are inside the range (≤), the same as OpenCV's maxDiff.
    steps = np.tile(np.arange(10, dtype=np.float32) * 0.5, (4, 1))
    assert remove_speckles(steps, max_size=39, max_range=0.5).all()
    # Diagonal neighbours do not join: two 1-px regions.
    diagonal = np.array([[1.0, NAN], [NAN, 1.0]], np.float32)
    assert not remove_speckles(diagonal, max_size=1).any()


def test_regions_grow_over_the_kept_pixels_only():
    disparity = np.full((4, 13), 7.0, np.float32)
    keep = np.ones(disparity.shape, bool)
    keep[:, 6] = False  # splits the 52 px into two regions of 24
    assert remove_speckles(disparity, keep, max_size=25).sum() == 0
    assert remove_speckles(disparity, keep, max_size=23).sum() == 48
    assert remove_speckles(disparity, None, max_size=25).all()
    # A non-finite disparity is never kept, whatever keep says.
    disparity[0, 0] = np.inf
    disparity[1, 0] = NAN
    kept = remove_speckles(disparity, keep, max_size=0)
    assert not kept[0, 0] and not kept[1, 0] and kept[2, 0]
    # The input mask is not changed.
    assert keep[0, 0] and keep.sum() == 48


def test_same_as_opencv_filter_speckles_on_sixteenth_pixel_disparities():
    # OpenCV works on int16 disparities in 1/16 px with a sentinel for 'none'; on values it can
    # represent the two must agree exactly, here on random maps with many small regions.
    rng = np.random.default_rng(1)
    for trial in range(40):
        height, width = (int(v) for v in rng.integers(4, 50, 2))
        levels = rng.integers(0, 5, (height, width)) * 24 + rng.integers(0, 20, (height, width))
        keep = rng.random((height, width)) < 0.85
        max_size = int(rng.integers(1, 40))
        max_diff = int(rng.integers(0, 40))
        reference = np.where(keep, levels, -1).astype(np.int16)
        cv2.filterSpeckles(reference, -1, max_size, max_diff)
        ours = remove_speckles(
            (levels / 16).astype(np.float32), keep, max_size, max_diff / 16
        )
        np.testing.assert_array_equal(ours, reference != -1, err_msg=f'trial {trial}')


def test_a_real_pair_loses_its_small_wrong_islands():
    # The Motorcycle pair (scikit-image) at a quarter of its size, Census-BM: the speckles
    # dropped hold a far larger share of wrong disparities than the pixels left.
    from skimage.data import stereo_motorcycle

    left, right, truth = stereo_motorcycle()
    size = (left.shape[1] // 4, left.shape[0] // 4)
    left = cv2.resize(left, size, interpolation=cv2.INTER_AREA)
    right = cv2.resize(right, size, interpolation=cv2.INTER_AREA)
    truth = cv2.resize(truth, size, interpolation=cv2.INTER_NEAREST) / 4
    disparity = wta_disparity(compute_cost_volume(left, right, 'census_bm', 64))
    kept = remove_speckles(disparity, max_size=20)
    dropped = np.isfinite(disparity) & ~kept
    known = np.isfinite(truth)
    wrong = np.abs(disparity - truth) >= 3
    assert 0.01 < dropped.mean() < 0.3
    assert wrong[dropped & known].mean() > 3 * wrong[kept & known].mean()


@pytest.mark.parametrize(
    ('kwargs', 'error', 'message'),
    [
        ({'disparity': np.zeros((2, 3, 4), np.float32)}, InputError, 'non-empty \\(H, W\\)'),
        ({'disparity': np.zeros((0, 3), np.float32)}, InputError, 'non-empty \\(H, W\\)'),
        ({'disparity': [[1.0]]}, InputError, 'numpy array; got list'),
        ({'keep': np.ones((4, 5), np.uint8)}, InputError, 'bool numpy array; got uint8'),
        ({'keep': np.ones((5, 4), bool)}, InputError, 'shape of disparity \\(4, 5\\)'),
        ({'max_size': -1}, ConfigError, 'max_size must be an integer ≥ 0; got -1'),
        ({'max_size': 2.5}, ConfigError, 'max_size must be an integer'),
        ({'max_size': True}, ConfigError, 'max_size must be an integer'),
        ({'max_range': float('nan')}, ConfigError, 'max_range must be a finite number'),
        ({'max_range': -0.5}, ConfigError, 'max_range must be a finite number ≥ 0'),
        ({'max_range': '1'}, ConfigError, 'max_range must be a finite number'),
    ],
)
def test_bad_arguments_are_named(kwargs, error, message):
    arguments = {'disparity': np.ones((4, 5), np.float32), **kwargs}
    with pytest.raises(error, match=message):
        remove_speckles(**arguments)

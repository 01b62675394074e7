"""Shrinking samples: NaN-aware ground truth, images, masks, calibration, disparity-range fit."""

from __future__ import annotations

import numpy as np
import pytest

from cva_confidence_ros.datasets import (
    Calibration,
    StereoSample,
    fit_disparity_range,
    resize_disparity,
    resize_sample,
)
from cva_confidence_ros.datasets.resize import resize_image
from cva_confidence_ros.errors import ConfigError, DataError, InputError

nan = np.nan


def test_resize_disparity_hand_values() -> None:
    disparity = np.array(
        [
            [2, 2, 2, nan, 9, 9],
            [2, 2, 2, 4, 9, 9],
            [nan, nan, 10, 10, nan, nan],
            [nan, 6, 2, 2, 4, 4],
            [1, 1, 1, 1, 1, 1],  # cropped: 5 rows → 2 output rows
        ],
        dtype=np.float32,
    )
    expected = [
        [1.0, (2 + 2 + 4) / 3 / 2, 4.5],  # full block; 3 valid, spread 2 ≤ 2; constant 9
        [nan, nan, 2.0],  # 1 valid of 4; spread 8 > 2 (depth edge); 2 valid of 4
    ]
    result = resize_disparity(disparity, 2)
    assert result.dtype == np.float32 and result.shape == (2, 3)
    np.testing.assert_allclose(result, expected, rtol=1e-6, equal_nan=True)


def test_resize_disparity_factor_one_copies() -> None:
    disparity = np.array([[1.0, nan]], dtype=np.float32)
    result = resize_disparity(disparity, 1)
    np.testing.assert_array_equal(result, disparity)
    assert result is not disparity


@pytest.mark.parametrize('factor', [0, -2, 1.5, True, '2'])
def test_bad_factor(factor: object) -> None:
    with pytest.raises(ConfigError, match='factor'):
        resize_disparity(np.zeros((4, 4), np.float32), factor)  # type: ignore[arg-type]


@pytest.mark.parametrize('factor', [0, -1, -2, 1.5, 2.0, True, '2'])
def test_resize_image_refuses_bad_factors_as_resize_disparity_does(factor: object) -> None:
    # Factor 0 raised ZeroDivisionError, negative ones an OpenCV assertion, floats a TypeError
    # from slicing, and True passed as factor 1.
    image = np.zeros((4, 6, 3), np.uint8)
    with pytest.raises(ConfigError, match='factor must be an integer ≥ 1; got'):
        resize_image(image, factor)  # type: ignore[arg-type]


def test_resize_image_factors_and_too_small_images() -> None:
    image = np.arange(5 * 7, dtype=np.uint8).reshape(5, 7)
    assert resize_image(image, 1) is image
    small = resize_image(image, np.int64(2))
    assert small.shape == (2, 3) and small.dtype == np.uint8
    np.testing.assert_array_equal(small, resize_image(image, 2))
    # Smaller than one block: a clear InputError, not an OpenCV assertion.
    with pytest.raises(InputError, match='cannot shrink a 1×7 image by 2'):
        resize_image(image[:1], 2)


def shifted_sample(height: int, width: int, shift: int, channels: int = 3) -> StereoSample:
    """Random texture with a constant disparity: left[y, x] = right[y, x - shift]."""
    rng = np.random.default_rng(0)
    shape = (height, width + shift) + ((channels,) if channels > 1 else ())
    scene = rng.integers(0, 256, shape, dtype=np.uint8)
    left = np.ascontiguousarray(scene[:, :width])
    right = np.ascontiguousarray(scene[:, shift:])
    nonocc = np.ones((height, width), bool)
    nonocc[:, :shift] = False
    return StereoSample(
        dataset='test',
        scene='shift',
        left=left,
        right=right,
        disparity=np.full((height, width), shift, np.float32),
        nonocc=nonocc,
        calib=Calibration(fx=100.0, fy=90.0, cx=5.5, cy=3.5, baseline=0.2, doffs=4.0),
    )


@pytest.mark.parametrize('channels', [1, 3])
def test_resize_sample_keeps_the_pair_consistent(channels: int) -> None:
    sample = shifted_sample(8, 24, 4, channels)
    small = resize_sample(sample, 2)
    assert small.left.shape[:2] == (4, 12) and small.left.dtype == np.uint8
    assert small.left.shape == small.right.shape
    np.testing.assert_array_equal(small.disparity, np.full((4, 12), 2.0, np.float32))
    # A shift by a multiple of the factor survives the block mean exactly.
    np.testing.assert_array_equal(small.left[:, 2:], small.right[:, :-2])
    block_mean = sample.left[:2, :2].reshape(4, -1).astype(float).mean(axis=0)
    np.testing.assert_allclose(small.left[0, 0].reshape(-1), np.rint(block_mean), atol=0.5)
    assert small.nonocc is not None
    np.testing.assert_array_equal(small.nonocc[0], np.arange(12) >= 2)
    assert small.calib == Calibration(
        fx=50.0, fy=45.0, cx=2.5, cy=1.5, baseline=0.2, doffs=2.0
    )
    assert small.dataset == 'test' and small.scene == 'shift'


def test_resize_sample_factor_one_is_identity() -> None:
    sample = shifted_sample(4, 8, 2)
    assert resize_sample(sample, 1) is sample


@pytest.mark.parametrize(
    ('max_disparity', 'factor'), [(128, 1), (101, 1), (100, 2), (64, 2), (16, 8)]
)
def test_fit_disparity_range(max_disparity: int, factor: int) -> None:
    sample = shifted_sample(16, 32, 4)
    disparity = sample.disparity.copy()
    disparity[0, 0] = 100.0
    disparity[1:, :] = nan
    sample = StereoSample('t', 's', sample.left, sample.right, disparity)
    fitted, got = fit_disparity_range(sample, max_disparity)
    assert got == factor
    assert fitted.shape == (16 // factor, 32 // factor)
    finite = fitted.disparity[np.isfinite(fitted.disparity)]
    assert finite.size == 0 or finite.max() <= max_disparity - 1


@pytest.mark.parametrize(
    ('largest', 'factor'), [(62.9, 1), (63.0, 1), (63.5, 2), (63.99, 2), (64.0, 2), (126.0, 2),
                            (127.0, 4)]
)
def test_fit_disparity_range_halves_while_the_maximum_exceeds_d_minus_1(
    largest: float, factor: int
) -> None:
    # D = 64 holds d = 0 … 63; the paper halves while the maximum exceeds 255 for D = 256.
    sample = shifted_sample(16, 32, 4)
    disparity = np.full((16, 32), 10.0, np.float32)
    disparity[0, 0] = largest
    sample = StereoSample('t', 's', sample.left, sample.right, disparity)
    assert fit_disparity_range(sample, 64)[1] == factor


def test_fit_disparity_range_refuses_to_shrink_to_nothing() -> None:
    sample = shifted_sample(16, 32, 4)
    disparity = sample.disparity.copy()
    disparity[0, 0] = 1e30  # an outlier, or ground truth stored at another scale
    sample = StereoSample('t', 's', sample.left, sample.right, disparity)
    with pytest.raises(DataError, match=r't/s: ground truth reaches 1e\+30 px'):
        fit_disparity_range(sample, 64)


def test_fit_disparity_range_without_ground_truth() -> None:
    sample = shifted_sample(4, 8, 2)
    empty = StereoSample('t', 's', sample.left, sample.right, np.full((4, 8), nan, np.float32))
    fitted, factor = fit_disparity_range(empty, 1)
    assert factor == 1 and fitted is empty
    with pytest.raises(ConfigError, match='max_disparity'):
        fit_disparity_range(empty, 0)

"""Synthetic stereo pairs: deterministic, in range, photometrically consistent, occlusions."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy import ndimage

from cva_confidence_ros.datasets import StereoSample
from cva_confidence_ros.datasets.synthetic import synthetic_pair, synthetic_pairs
from cva_confidence_ros.errors import ConfigError

HEIGHT, WIDTH, DEPTH = 64, 96, 24


@pytest.fixture(scope='module')
def pairs() -> list[StereoSample]:
    return synthetic_pairs(4, first_seed=0, height=HEIGHT, width=WIDTH, max_disparity=DEPTH)


def test_sample_fields(pairs):
    sample = pairs[1]
    assert sample.dataset == 'synthetic' and sample.scene == 'seed1'
    assert sample.left.shape == sample.right.shape == (HEIGHT, WIDTH, 3)
    assert sample.left.dtype == np.uint8
    assert sample.disparity.dtype == np.float32 and sample.disparity.shape == (HEIGHT, WIDTH)
    assert sample.nonocc.dtype == np.bool_
    assert sample.calib is not None and sample.calib.fx == WIDTH


def test_deterministic_by_seed(pairs):
    again = synthetic_pair(2, HEIGHT, WIDTH, DEPTH)
    np.testing.assert_array_equal(again.left, pairs[2].left)
    np.testing.assert_array_equal(again.right, pairs[2].right)
    np.testing.assert_array_equal(again.disparity, pairs[2].disparity)
    np.testing.assert_array_equal(again.nonocc, pairs[2].nonocc)
    assert not np.array_equal(pairs[0].disparity, pairs[1].disparity)


def test_dense_ground_truth_in_range(pairs):
    for sample in pairs:
        assert np.all(np.isfinite(sample.disparity))
        assert sample.disparity.min() >= 0
        assert sample.disparity.max() <= DEPTH - 1
    spread = [s.disparity.max() - s.disparity.min() for s in pairs]
    assert max(spread) > DEPTH / 2  # scenes use the range, not one flat plane


def test_occlusions_are_real(pairs):
    for sample in pairs:
        columns = np.arange(WIDTH)[None, :] - sample.disparity
        # Matches outside the right image are never visible ...
        assert not np.any(sample.nonocc & (columns < 0))
        # ... and there are occlusions beyond the left border strip (objects hide background).
        inner = columns >= 0
        assert 0.01 < 1 - sample.nonocc[inner].mean() < 0.5


def _residual(sample: StereoSample, shift: float) -> float:
    """RMS of right(x − d − shift) against an affine fit of left(x), on visible, smooth pixels."""
    left = sample.left.astype(np.float32).mean(axis=2)
    right = sample.right.astype(np.float32).mean(axis=2)
    yy, xx = np.mgrid[0:HEIGHT, 0:WIDTH].astype(np.float32)
    source = xx - sample.disparity - shift
    warped = cv2.remap(right, source, yy, cv2.INTER_LINEAR)
    edges = ndimage.morphological_gradient(sample.disparity, size=3) > 0.5
    mask = sample.nonocc & ~ndimage.binary_dilation(edges) & (source >= 0)
    design = np.stack([left[mask], np.ones(mask.sum())], axis=1)
    coef = np.linalg.lstsq(design, warped[mask], rcond=None)[0]
    return float(np.sqrt(np.mean((warped[mask] - design @ coef) ** 2)))


def test_photometric_consistency(pairs):
    for sample in pairs:
        correct = _residual(sample, 0.0)
        wrong = _residual(sample, 3.0)
        assert correct < 4.0  # noise (σ ≤ 2 per view) and interpolation only
        assert wrong > 2 * correct


def test_bad_arguments():
    with pytest.raises(ConfigError, match='max_disparity'):
        synthetic_pair(0, 32, 32, 64)
    with pytest.raises(ConfigError, match='16×16'):
        synthetic_pair(0, 8, 32, 8)
    with pytest.raises(ConfigError, match='seed'):
        synthetic_pair(-1, 32, 32, 8)


def test_whole_float_sizes_and_seed_give_the_int_pair():
    # 32.0 passed the check, then numpy's seeding refused it ('seed must be integer'), and a
    # seed of 1.0 named the scene 'seed1.0'.
    reference = synthetic_pair(1, 32, 48, 16)
    pair = synthetic_pair(1.0, 32.0, np.int64(48), 16.0)
    assert pair.scene == 'seed1' and pair.left.shape == (32, 48, 3)
    np.testing.assert_array_equal(pair.left, reference.left)
    np.testing.assert_array_equal(pair.disparity, reference.disparity)
    for bad in ('abc', 32.5, None, float('nan'), True):
        with pytest.raises(ConfigError, match='height must be an integer'):
            synthetic_pair(0, bad, 48, 16)

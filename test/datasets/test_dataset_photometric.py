"""Photometric check of every loader on the real shared data (skipped when it is absent).

Warping the right image by the ground truth must reproduce the left image on visible pixels:
``left[y, x] ≈ right[y, x - d]``. The zero-mean normalised correlation on textured pixels must
be high with the loaded disparity and clearly lower with the disparity shifted by ±2 px or
scaled by 1.25 / 0.8, which catches a wrong sign, scale or row order. Occlusion masks are
checked the same way: occluded pixels must not match.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from cva_confidence_ros.datasets import (
    DATASETS,
    StereoSample,
    fit_disparity_range,
    list_scenes,
    load_scene,
)

DATA_ROOT = Path(
    os.environ.get('CVA_DATA_ROOT', Path(__file__).resolve().parents[2] / '..' / 'shared' / 'data')
)
MIN_CORRELATION = 0.65
MARGIN = 0.03


def gray(image: np.ndarray) -> np.ndarray:
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    return image.astype(np.float32)


def warp_correlation(sample: StereoSample, disparity: np.ndarray, mask: np.ndarray) -> float:
    """ZNCC of left and right-warped-by-disparity over the most textured quarter of ``mask``."""
    left, right = gray(sample.left), gray(sample.right)
    height, width = left.shape
    map_x = (np.arange(width, dtype=np.float32)[None, :] - disparity).astype(np.float32)
    map_x = np.nan_to_num(map_x, nan=-1.0)
    map_y = np.repeat(np.arange(height, dtype=np.float32)[:, None], width, axis=1)
    warped = cv2.remap(right, map_x, map_y, cv2.INTER_LINEAR)
    usable = mask & np.isfinite(disparity) & (map_x >= 1) & (map_x <= width - 2)
    gradient = np.abs(cv2.Sobel(left, cv2.CV_32F, 1, 0))
    assert usable.sum() >= 500, 'too few pixels with ground truth to check'
    usable &= gradient >= np.percentile(gradient[usable], 75)
    a = left[usable] - left[usable].mean()
    b = warped[usable] - warped[usable].mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


def check_warp(
    sample: StereoSample, offsets: tuple[float, ...], scales: tuple[float, ...]
) -> None:
    disparity = sample.disparity
    visible = sample.nonocc if sample.nonocc is not None else np.ones(sample.shape, bool)
    name = f'{sample.dataset}/{sample.scene} {sample.shape}'
    true = warp_correlation(sample, disparity, visible)
    assert true >= MIN_CORRELATION, f'{name}: correlation {true:.3f} with the ground truth'
    wrong = [disparity + offset for offset in offsets] + [disparity * s for s in scales]
    for altered in wrong:
        other = warp_correlation(sample, altered, visible)
        assert true > other + MARGIN, f'{name}: {true:.3f} vs {other:.3f} with altered GT'
    if sample.nonocc is not None:
        occluded = ~sample.nonocc & np.isfinite(disparity)
        width = sample.shape[1]
        occluded &= np.arange(width)[None, :] - np.nan_to_num(disparity) >= 1
        if occluded.sum() >= 2000:
            assert warp_correlation(sample, disparity, occluded) < true - 0.3, name


def data_root(name: str) -> Path | None:
    if name == 'motorcycle':
        return None
    root = DATA_ROOT / name
    if not root.is_dir():
        pytest.skip(f'shared data {root} not present')
    return root


@pytest.mark.parametrize('name', DATASETS.names())
def test_ground_truth_warps_right_onto_left(name: str) -> None:
    root = data_root(name)
    scenes = list_scenes(name, root)
    assert scenes
    for scene in scenes:
        check_warp(load_scene(name, root, scene), offsets=(2.0, -2.0), scales=(1.25, 0.8))


@pytest.mark.parametrize('name', ['middlebury2006', 'middlebury2014', 'flyingthings3d'])
def test_fitted_samples_stay_consistent(name: str) -> None:
    root = data_root(name)
    sample = load_scene(name, root, list_scenes(name, root)[0])
    fitted, factor = fit_disparity_range(sample, 48)
    assert factor > 1
    assert np.nanmax(fitted.disparity) < 48
    check_warp(fitted, offsets=(1.0, -1.0), scales=())

"""Review 37: the synthetic generator's ground truth is geometrically exact (no half-pixel or
sign offset, slanted planes at pixel centres) and its pairs do not depend on OpenCV's threads."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

import cva_confidence_ros.datasets.synthetic as synthetic


@pytest.mark.parametrize(('height', 'width', 'depth'), [(48, 64, 16), (33, 71, 32)])
def test_ground_truth_is_exact_on_coordinate_textures(monkeypatch, height, width, depth):
    # Every texture replaced by its own left-view coordinates (after drawing the original, so
    # that the scene stays the same): the right view at x − d must then show x itself on every
    # visible pixel. Bilinear sampling is exact on a ramp, so any offset of the ground truth
    # (half a pixel, a sign, a corner-vs-centre slant) shows up directly in pixels.
    original_texture, original_render = synthetic._texture, synthetic._render
    renders: dict[str, np.ndarray] = {}

    def ramp_texture(rng, rows, columns, p=synthetic._TEXTURE_P):
        original_texture(rng, rows, columns, p)
        yy, xx = np.mgrid[0:rows, 0:columns].astype(np.float32)
        return np.stack([xx, yy, np.zeros_like(xx)], axis=2)

    def keep_render(surfaces, rows, columns, view):
        result = original_render(surfaces, rows, columns, view)
        renders[view] = result[0]
        return result

    monkeypatch.setattr(synthetic, '_texture', ramp_texture)
    monkeypatch.setattr(synthetic, '_render', keep_render)
    for seed in range(3):
        sample = synthetic.synthetic_pair(seed, height, width, depth)
        yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
        seen = cv2.remap(renders['right'], xx - sample.disparity, yy, cv2.INTER_LINEAR)
        visible = sample.nonocc
        assert visible.mean() > 0.4
        np.testing.assert_allclose(seen[..., 0][visible], xx[visible], atol=0.02)
        np.testing.assert_allclose(seen[..., 1][visible], yy[visible], atol=0.02)


def test_same_pair_with_one_or_more_opencv_threads():
    threads = cv2.getNumThreads()
    try:
        cv2.setNumThreads(1)
        single = synthetic.synthetic_pair(7, 40, 64, 16)
        cv2.setNumThreads(max(2, threads))
        multi = synthetic.synthetic_pair(7, 40, 64, 16)
    finally:
        cv2.setNumThreads(threads)
    for name in ('left', 'right', 'disparity', 'nonocc'):
        np.testing.assert_array_equal(getattr(single, name), getattr(multi, name))

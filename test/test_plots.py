"""Tests of the PNG helpers: pixel-exact maps, the paper's green/red rule, ROC figures."""

from __future__ import annotations

from matplotlib.image import imread
import numpy as np
import pytest

from cva_confidence_ros.errors import InputError
from cva_confidence_ros.metrics import optimal_auc
from cva_confidence_ros.plots import (
    CORRECT_RGB,
    UNKNOWN_RGB,
    WRONG_RGB,
    confidence_overlay,
    correctness_classes,
    optimal_roc_curve,
    save_confidence_map,
    save_correctness_overlay,
    save_disparity_map,
    save_roc_curves,
)


def _rgb(path) -> np.ndarray:
    return np.round(imread(path)[..., :3] * 255.0).astype(np.int64)


def test_correctness_classes_follows_the_paper_rule() -> None:
    # correct & c > tau -> True; wrong & c <= tau -> True; c == tau counts as "not confident".
    confidence = np.array([0.9, 0.9, 0.2, 0.2, 0.5, 0.5])
    error = np.array([False, True, False, True, False, True])
    got = correctness_classes(confidence, error, tau=0.5)
    assert got.tolist() == [True, False, False, True, False, True]


def test_correctness_classes_rejects_shape_mismatch() -> None:
    with pytest.raises(InputError, match='same shape'):
        correctness_classes(np.zeros(3), np.zeros(4, dtype=bool))


def test_confidence_map_is_pixel_exact_black_to_white(tmp_path) -> None:
    confidence = np.array([[0.0, 1.0, np.nan], [0.5, 2.0, -1.0]], dtype=np.float32)
    path = save_confidence_map(confidence, tmp_path / 'sub' / 'conf.png', vmin=0.0, vmax=1.0)
    rgb = _rgb(path)
    assert rgb.shape == (2, 3, 3)
    assert rgb[0, 0].tolist() == [0, 0, 0]
    assert rgb[0, 1].tolist() == [255, 255, 255]
    assert rgb[0, 2].tolist() == list(UNKNOWN_RGB)
    assert abs(int(rgb[1, 0, 0]) - 128) <= 1
    assert rgb[1, 1].tolist() == [255, 255, 255]  # clipped above vmax
    assert rgb[1, 2].tolist() == [0, 0, 0]  # clipped below vmin


def test_confidence_map_default_range_and_infinity(tmp_path) -> None:
    confidence = np.array([[2.0, 4.0, np.inf]])
    rgb = _rgb(save_confidence_map(confidence, tmp_path / 'c.png'))
    assert rgb[0, 0].tolist() == [0, 0, 0]
    assert rgb[0, 1].tolist() == [255, 255, 255]
    assert rgb[0, 2].tolist() == [255, 255, 255]


def test_confidence_map_rejects_bad_shape(tmp_path) -> None:
    with pytest.raises(InputError, match=r'\(H, W\)'):
        save_confidence_map(np.zeros((2, 2, 2)), tmp_path / 'c.png')


def test_disparity_map_marks_unknown(tmp_path) -> None:
    disparity = np.array([[0.0, 10.0], [np.nan, 5.0]], dtype=np.float32)
    rgb = _rgb(save_disparity_map(disparity, tmp_path / 'd.png', max_disparity=10.0))
    assert rgb.shape == (2, 2, 3)
    assert rgb[1, 0].tolist() == list(UNKNOWN_RGB)
    assert rgb[0, 1].sum() > rgb[1, 1].sum() > rgb[0, 0].sum()


def test_overlay_colours_and_mask(tmp_path) -> None:
    confidence = np.array([[0.9, 0.9, 0.1], [0.1, np.nan, 0.9]])
    error = np.array([[False, True, True], [False, False, False]])
    mask = np.array([[True, True, True], [True, True, False]])
    image = np.full((2, 3), 200, dtype=np.uint8)
    path = save_correctness_overlay(confidence, error, tmp_path / 'o.png', 0.5, image, mask)
    rgb = _rgb(path)
    assert rgb[0, 0].tolist() == list(CORRECT_RGB)  # correct and confident
    assert rgb[0, 1].tolist() == list(WRONG_RGB)  # wrong but confident
    assert rgb[0, 2].tolist() == list(CORRECT_RGB)  # wrong and not confident
    assert rgb[1, 0].tolist() == list(WRONG_RGB)  # correct but not confident
    assert rgb[1, 1].tolist() == [100, 100, 100]  # NaN confidence: dimmed image
    assert rgb[1, 2].tolist() == [100, 100, 100]  # outside the mask: dimmed image


def test_overlay_rejects_mismatched_image(tmp_path) -> None:
    with pytest.raises(InputError, match='image'):
        save_correctness_overlay(
            np.zeros((2, 2)), np.zeros((2, 2), bool), tmp_path / 'o.png',
            image=np.zeros((3, 2), np.uint8),
        )


def test_confidence_overlay_tints_the_kept_pixels_red_to_green() -> None:
    image = np.full((2, 4), 100, np.uint8)
    confidence = np.array([[0.0, 0.5, 1.0, np.nan], [0.9, 0.9, 2.0, -1.0]], np.float32)
    kept = np.array([[True, True, True, True], [False, False, True, True]])
    out = confidence_overlay(image, confidence, kept).astype(np.int64)
    assert out.shape == (2, 4, 3) and out.dtype == np.int64
    # 40 % of the grey 100 plus 60 % of the ramp: red at 0, yellow at 0.5, green at 1.
    np.testing.assert_array_equal(out[0, 0], [40 + 138, 40, 40])
    np.testing.assert_allclose(out[0, 1], [40 + 138, 40 + 120, 40], atol=1)  # 256-entry ramp
    np.testing.assert_array_equal(out[0, 2], [40, 40 + 120, 40])
    np.testing.assert_array_equal(out[0, 3], out[0, 0])  # NaN counts as 0
    np.testing.assert_array_equal(out[1, 2], out[0, 2])  # clipped to [0, 1]
    np.testing.assert_array_equal(out[1, 3], out[0, 0])
    # Not kept: the dimmed grey scene, whatever the confidence.
    np.testing.assert_array_equal(out[1, 0], [45, 45, 45])
    np.testing.assert_array_equal(out[1, 1], [45, 45, 45])
    # A colour image is shown in grey (the mean of its channels).
    colour = np.zeros((2, 4, 3), np.uint8)
    colour[..., 0] = 255
    grey = confidence_overlay(colour, confidence, kept)
    np.testing.assert_array_equal(grey[1, 0], [38, 38, 38])


@pytest.mark.parametrize(
    ('image', 'kept', 'message'),
    [
        (np.zeros((2, 3), np.uint8), np.ones((2, 4), bool), 'image must be uint8'),
        (np.zeros((2, 4), np.float32), np.ones((2, 4), bool), 'image must be uint8'),
        (np.zeros((2, 4), np.uint8), np.ones((2, 4), np.uint8), 'kept must be a bool array'),
        (np.zeros((2, 4), np.uint8), np.ones((4, 2), bool), 'kept must be a bool array'),
    ],
)
def test_confidence_overlay_names_what_does_not_fit(image, kept, message) -> None:
    with pytest.raises(InputError, match=message):
        confidence_overlay(image, np.zeros((2, 4), np.float32), kept)


@pytest.mark.parametrize('eps', [0.0, 0.1, 0.5, 0.9])
def test_optimal_roc_curve_integrates_to_eq1(eps: float) -> None:
    density, rate = optimal_roc_curve(eps, samples=4001)
    assert density[-1] == 1.0 and np.all(np.diff(density) > 0)
    assert rate[-1] == pytest.approx(eps)
    assert np.all(rate[density <= 1.0 - eps] == 0.0)
    area = float(np.sum(np.diff(density) * (rate[1:] + rate[:-1]) / 2))
    assert area == pytest.approx(optimal_auc(eps), abs=1e-4)


def test_optimal_roc_curve_rejects_bad_error_rate() -> None:
    with pytest.raises(InputError, match=r'\[0, 1\]'):
        optimal_roc_curve(1.5)


def test_roc_figure_is_written(tmp_path) -> None:
    curves = {'a': (np.array([0.5, 1.0]), np.array([0.0, 0.2])),
              'b': (np.array([0.5, 1.0]), np.array([0.1, 0.2]))}
    path = save_roc_curves(curves, tmp_path / 'r' / 'roc.png', error_rate=0.2, title='t')
    image = imread(path)
    assert image.shape[:2] == (400, 500)
    assert image[..., :3].std() > 0.01  # not blank


def test_roc_figure_rejects_ragged_curve(tmp_path) -> None:
    with pytest.raises(InputError, match="'a'"):
        save_roc_curves({'a': (np.array([0.5, 1.0]), np.array([0.1]))}, tmp_path / 'r.png')


def test_a_one_channel_image_is_as_bright_as_its_grey_twin(tmp_path) -> None:
    confidence = np.array([[0.0, 1.0, 0.5]], np.float32)
    kept = np.array([[True, True, False]])
    grey = np.array([[100, 200, 100]], np.uint8)
    expected = confidence_overlay(grey, confidence, kept)
    np.testing.assert_array_equal(expected[0, 2], [45, 45, 45])  # dimmed 100, not kept
    np.testing.assert_array_equal(confidence_overlay(grey[..., None], confidence, kept),
                                  expected)
    # RGBA: the alpha channel is not part of the mean.
    rgba = np.dstack([grey, grey, grey, np.zeros_like(grey)])
    np.testing.assert_array_equal(confidence_overlay(rgba, confidence, kept), expected)
    # The correctness overlay's background too (dimmed to 50 %).
    error = np.zeros((1, 3), bool)
    mask = np.zeros((1, 3), bool)
    path = save_correctness_overlay(confidence, error, tmp_path / 'c.png',
                                    image=grey[..., None], mask=mask)
    np.testing.assert_array_equal(_rgb(path)[0, :, 0], [50, 100, 50])
    with pytest.raises(InputError, match=r'\(H, W, 1\|3\|4\).*got uint8 \(1, 3, 0\)'):
        confidence_overlay(np.zeros((1, 3, 0), np.uint8), confidence, kept)
    with pytest.raises(InputError, match=r'\(H, W, 1\|3\|4\).*got \(1, 3, 2\)'):
        save_correctness_overlay(confidence, error, tmp_path / 'd.png',
                                 image=np.zeros((1, 3, 2), np.uint8))

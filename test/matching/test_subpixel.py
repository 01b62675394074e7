"""Sub-pixel disparity: hand-made cost curves, the matchers on a fractional shift, refusals."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.matching import (
    SUBPIXEL_METHODS,
    compute_cost_volume,
    refine_subpixel,
    wta_disparity,
)


def _curves(values: np.ndarray) -> np.ndarray:
    """(D, N) costs → a (D, 1, W) volume whose column x holds curve x (W = N + D, so that
    every curve lies far enough right for its neighbours to be inside the other image)."""
    depth, count = values.shape
    volume = np.ones((depth, 1, count + depth), np.float32)
    volume[:, 0, depth:] = values
    return volume


@pytest.mark.parametrize('minimum', [7.0, 7.2, 6.75, 7.5, 8.45])
def test_parabola_and_equiangular_find_the_minimum_of_their_own_curve(minimum: float) -> None:
    d = np.arange(16, dtype=np.float64)
    for method, costs in (
        ('parabola', 0.01 * (d - minimum) ** 2),
        ('equiangular', 0.03 * np.abs(d - minimum)),
    ):
        volume = _curves(costs[:, None])
        disparity = wta_disparity(volume)
        refined = refine_subpixel(volume, disparity, method)
        assert refined.dtype == np.float32 and refined.shape == disparity.shape
        assert refined[0, -1] == pytest.approx(minimum, abs=1e-5), method
        # The curve's formula by hand at the integer minimum.
        w = int(disparity[0, -1])
        low, mid, high = costs[w - 1], costs[w], costs[w + 1]
        expected = (
            (low - high) / (2 * (low - 2 * mid + high)) if method == 'parabola'
            else (low - high) / (2 * max(low - mid, high - mid))
        )
        assert refined[0, -1] == pytest.approx(w + expected, abs=1e-6)


def test_the_integer_stays_where_the_curve_is_undefined() -> None:
    depth = 8
    flat = np.full(depth, 0.5)
    flat[3:6] = 0.2  # three equal costs: WTA takes d = 3, whose left neighbour is higher
    plateau = np.full(depth, 0.5)
    plateau[4] = 0.1  # a sharp minimum with equal neighbours: δ = 0
    edge_low = np.linspace(0.1, 0.9, depth)  # minimum at d = 0
    edge_high = np.linspace(0.9, 0.1, depth)  # minimum at d = D − 1
    volume = _curves(np.stack([flat, plateau, edge_low, edge_high], axis=1))
    disparity = wta_disparity(volume)
    for method in ('parabola', 'equiangular'):
        refined = refine_subpixel(volume, disparity, method)[0, depth:]
        # flat: neighbours 0.5 and 0.2 → δ = +0.5 (parabola: 0.3/(2·0.3)); equiangular 0.3/0.6
        assert refined[0] == pytest.approx(3.5)
        np.testing.assert_array_equal(refined[1:], [4.0, 0.0, depth - 1.0])


def test_neighbours_outside_the_other_image_leave_the_integer() -> None:
    # Left view: a pixel at x needs x − (d + 1) ≥ 0; right view: x + d + 1 < W.
    depth, width = 6, 10
    curve = 0.01 * (np.arange(depth) - 2.3) ** 2
    volume = np.broadcast_to(curve[:, None, None], (depth, 1, width)).astype(np.float32)
    disparity = wta_disparity(volume)  # 2 everywhere
    left = refine_subpixel(volume, disparity, 'parabola', view='left')[0]
    np.testing.assert_array_equal(left[:3], 2.0)
    np.testing.assert_allclose(left[3:], 2.3, atol=1e-5)
    right = refine_subpixel(volume, disparity, 'parabola', view='right')[0]
    np.testing.assert_array_equal(right[width - 3 :], 2.0)
    np.testing.assert_allclose(right[: width - 3], 2.3, atol=1e-5)


def test_nan_stays_nan_and_none_copies() -> None:
    volume = np.random.default_rng(0).random((9, 5, 20)).astype(np.float32)
    disparity = wta_disparity(volume)
    disparity[2, 3] = np.nan
    for method in SUBPIXEL_METHODS:
        refined = refine_subpixel(volume, disparity, method)
        assert np.isnan(refined[2, 3])
        finite = np.isfinite(disparity)
        assert np.all(np.abs(refined[finite] - disparity[finite]) <= 0.5)
    same = refine_subpixel(volume, disparity, 'none')
    np.testing.assert_array_equal(same, disparity)
    assert same is not disparity


def _fractional_pair(shift: float, height: int = 48, width: int = 120) -> tuple:
    """A smooth random texture and its copy moved by ``shift`` px (linear resampling of a
    texture 4× finer, so the sub-pixel shift is what a camera would see)."""
    rng = np.random.default_rng(3)
    fine = cv2.GaussianBlur(rng.random((height, 4 * (width + 32))), (0, 0), 3.0)
    fine = (255 * (fine - fine.min()) / np.ptp(fine)).astype(np.float32)
    columns = np.arange(width, dtype=np.float32)
    rows = np.arange(height, dtype=np.float32)[:, None]

    def view(offset: float) -> np.ndarray:
        map_x = np.broadcast_to((columns + 16 + offset) * 4, (height, width)).astype(np.float32)
        map_y = np.broadcast_to(rows, (height, width)).astype(np.float32)
        return cv2.remap(fine, map_x, map_y, cv2.INTER_LINEAR).round().astype(np.uint8)

    # left(x) = right(x − shift) ⇔ right samples the texture at x + shift.
    return view(0.0), view(shift)


@pytest.mark.parametrize('matcher', ['census_bm', 'census_sgm', 'mccnn_fast'])
def test_a_fractional_shift_is_recovered_by_the_matchers(matcher: str) -> None:
    shift = 6.4
    left, right = _fractional_pair(shift)
    volume = compute_cost_volume(left, right, matcher, 16)
    disparity = wta_disparity(volume)
    inner = (slice(6, -6), slice(24, -6))
    right_integer = np.abs(disparity[inner] - shift) < 1.0  # 6 or 7
    assert right_integer.mean() > 0.95
    wta_error = np.abs(disparity[inner] - shift)[right_integer]  # 0.4 or 0.6
    errors = {}
    for method in ('parabola', 'equiangular'):
        refined = refine_subpixel(volume, disparity, method)
        errors[method] = error = np.abs(refined[inner] - shift)[right_integer]
        assert np.median(error) < 0.25 < np.median(wta_error), (method, np.median(error))
    # The default: the lines fit these Hamming and cosine costs better than the parabola.
    assert errors['equiangular'].mean() < min(0.2, errors['parabola'].mean())


@pytest.mark.parametrize(
    ('volume', 'disparity', 'method', 'error', 'message'),
    [
        (np.zeros((4, 2, 3), np.float32), np.zeros((2, 3)), 'cubic', ConfigError, 'subpixel'),
        (np.zeros((4, 2, 3), np.float32), np.zeros((2, 4)), 'parabola', InputError, r'\(2, 3\)'),
        (np.zeros((2, 3), np.float32), np.zeros((2, 3)), 'parabola', InputError, r'\(D, H, W\)'),
        (np.zeros((4, 2, 3), np.int32), np.zeros((2, 3)), 'parabola', InputError, 'float'),
        (np.zeros((4, 2, 3), np.float32), np.full((2, 3), 0.5), 'parabola', InputError,
         'integers in \\[0, 3\\]'),
        (np.zeros((4, 2, 3), np.float32), np.full((2, 3), 4.0), 'none', InputError, '6 other'),
        (np.zeros((4, 2, 3), np.float32), np.full((2, 3), np.inf), 'parabola', InputError,
         'integers'),
        (np.zeros((4, 2, 3), np.float32), np.zeros((2, 3), bool), 'parabola', InputError,
         'float'),
    ],
)
def test_bad_input_is_refused_naming_the_problem(
    volume: np.ndarray, disparity: np.ndarray, method: str, error: type, message: str
) -> None:
    with pytest.raises(error, match=message):
        refine_subpixel(volume, disparity, method)


@pytest.mark.parametrize('method', ['parabola', 'equiangular'])
@pytest.mark.parametrize('bad', [np.nan, np.inf])
def test_a_non_finite_neighbour_cost_keeps_the_integer(method: str, bad: float) -> None:
    # A caller's own volume may mark invalid costs with NaN or inf; the curve through them is
    # undefined, so the integer stays (the old code gave NaN, turning a valid pixel invalid).
    costs = np.array([[0.5], [0.2], [0.1], [0.3], [0.6]], np.float64)
    volume = _curves(costs)
    volume[3, 0, -1] = bad
    disparity = np.full(volume.shape[1:], 2.0, np.float32)
    refined = refine_subpixel(volume, disparity, method)
    assert refined[0, -1] == 2.0
    # The same curve with a finite neighbour is refined as usual.
    volume[3, 0, -1] = 0.3
    assert refine_subpixel(volume, disparity, method)[0, -1] != 2.0

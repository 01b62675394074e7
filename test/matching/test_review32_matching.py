"""Regressions of review 32: float64 cost volumes kept in their precision by the
winner-takes-all and the sub-pixel step, a Hamming ``out`` that is not an array."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from cva_confidence_ros.errors import InputError
from cva_confidence_ros.matching import refine_subpixel, wta_disparity
from cva_confidence_ros.matching.census import hamming_cost_volume


def test_wta_of_a_float64_volume_picks_the_float64_minimum() -> None:
    # 0.1 + 1e-10 and 0.1 are one float32: the volume was rounded to float32 first, the two
    # costs tied and the winner went to d = 0 where numpy's argmin says d = 1.
    volume = np.array([[[0.1 + 1e-10]], [[0.1]], [[0.2]]], np.float64)
    np.testing.assert_array_equal(wta_disparity(volume), np.argmin(volume, axis=0))
    assert wta_disparity(volume)[0, 0] == 1.0


def test_wta_of_a_float64_volume_beyond_the_float32_range() -> None:
    # 1e40 and 1e39 both became inf (with an overflow warning): a tie, won by d = 0.
    volume = np.array([[[1e40, 0.5]], [[1e39, 0.2]]], np.float64)
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        disparity = wta_disparity(volume)
    np.testing.assert_array_equal(disparity, [[1.0, 1.0]])


def test_subpixel_of_a_float64_volume_uses_the_float64_costs() -> None:
    # c₋, c₀, c₊ = 0.1 + 4e-10, 0.1, 0.1 + 2e-10: one float32 value, so the curve was flat and
    # the integer 2 stayed; in float64 the equiangular offset is (4 − 2) / (2·4) = 0.25.
    curve = np.array([0.5, 0.1 + 4e-10, 0.1, 0.1 + 2e-10, 0.5], np.float64)
    volume = np.ascontiguousarray(np.broadcast_to(curve[:, None, None], (5, 1, 6)))
    disparity = np.full((1, 6), 2.0, np.float32)
    refined = refine_subpixel(volume, disparity, 'equiangular')
    assert refined[0, -1] == pytest.approx(2.25, abs=1e-6)
    # the same curve scaled into float32's precision gives the same offset
    scaled = refine_subpixel((volume - 0.1) * 1e9, disparity, 'equiangular')
    assert scaled[0, -1] == pytest.approx(2.25, abs=1e-6)


def test_hamming_out_that_is_not_an_array_is_an_input_error() -> None:
    # A list (or a tensor) as out failed with AttributeError: 'list' object has no attribute
    # 'shape' although the docstring promises an InputError for a bad out.
    codes = np.zeros((2, 4), np.uint32)
    out = np.zeros((2, 4, 3), np.uint8).tolist()
    with pytest.raises(InputError, match=r'out must be a C-contiguous \(2, 4, 3\) .*got list'):
        hamming_cost_volume(codes, codes, 3, -1, layout='hwd', out=out)  # type: ignore[arg-type]


def test_a_colour_left_with_a_grey_right_is_named_as_such() -> None:
    # Only 'must have the same shape; got (4, 6, 3) and (4, 6)' before: a pair of two camera
    # encodings, not of two sizes.
    from cva_confidence_ros.errors import InputError
    from cva_confidence_ros.matching import check_image_pair

    grey = np.zeros((4, 6), np.uint8)
    colour = np.zeros((4, 6, 3), np.uint8)
    with pytest.raises(InputError, match=r'both be grey or both colour; got a colour left '
                                         r'\(4, 6, 3\) and a grey right \(4, 6\)'):
        check_image_pair(colour, grey)
    with pytest.raises(InputError, match='got a grey left'):
        check_image_pair(grey, colour)
    with pytest.raises(InputError, match='must have the same shape'):
        check_image_pair(grey, np.zeros((4, 7), np.uint8))

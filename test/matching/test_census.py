"""5×5 census transform and Hamming costs, checked against hand-computed codes."""

from __future__ import annotations

import numpy as np
import pytest

from cva_confidence_ros.errors import InputError
from cva_confidence_ros.matching.census import (
    CENSUS_BITS,
    census_transform,
    hamming_cost_volume,
    hamming_distance,
)

# Raster-increasing 4×4 image: every pixel is brighter than those above and to its left.
RAMP = np.array(
    [[10, 20, 30, 40], [50, 60, 70, 80], [90, 100, 110, 120], [130, 140, 150, 160]], np.uint8
)


def test_census_of_a_4x4_image_by_hand() -> None:
    codes = census_transform(RAMP)
    assert codes.shape == (4, 4) and codes.dtype == np.uint32
    # (0, 0) = 10: every neighbour (replicated border included) is ≥ 10, so no bit is set.
    assert codes[0, 0] == 0
    # (1, 1) = 60: its window rows are clamped rows 0, 0, 1, 2, 3 and columns 0, 0, 1, 2, 3.
    # Rows 0 and 0 (10…40) are all darker (10 bits), row 1 gives 50, 50 darker and 70, 80 not,
    # rows 2 and 3 are all brighter: twelve leading ones, twelve zeros.
    assert codes[1, 1] == 0xFFF000
    # (3, 3) = 160: rows 1, 2 are all darker; rows 3, 3, 3 give 140, 150 darker and then the
    # replicated 160s, which are not strictly darker.
    expected = int('11111' '11111' '11' '00' '11000' '11000', 2)
    assert codes[3, 3] == expected


def test_census_bit_k_says_whether_neighbour_k_is_darker() -> None:
    rng = np.random.default_rng(3)
    image = rng.integers(0, 256, (9, 11), dtype=np.uint8)
    codes = census_transform(image)
    padded = np.pad(image, 2, mode='edge')
    offsets = [(dy, dx) for dy in range(-2, 3) for dx in range(-2, 3) if (dy, dx) != (0, 0)]
    for y, x in [(0, 0), (4, 5), (8, 10), (2, 9)]:
        for k, (dy, dx) in enumerate(offsets):
            bit = (int(codes[y, x]) >> (CENSUS_BITS - 1 - k)) & 1
            assert bit == int(padded[y + 2 + dy, x + 2 + dx] < image[y, x])


def test_constant_image_has_zero_codes() -> None:
    assert not census_transform(np.full((5, 6), 77, np.uint8)).any()


@pytest.mark.parametrize(
    ('code_a', 'code_b', 'bits'),
    [(0b1011, 0b0110, 3), (0xFFFFFF, 0, 24), (0xABCDEF, 0xABCDEF, 0), (1 << 23, 1, 2)],
)
def test_hamming_distance(code_a: int, code_b: int, bits: int) -> None:
    assert hamming_distance(np.array([code_a]), np.array([code_b]))[0] == bits


def test_hamming_volume_layouts_and_outside_cost() -> None:
    codes_a = np.array([[0b111, 0b000, 0b101]], np.uint32)
    codes_b = np.array([[0b000, 0b011, 0b001]], np.uint32)
    left = hamming_cost_volume(codes_a, codes_b, 2, -1)
    assert left.shape == (2, 1, 3) and left.dtype == np.uint8
    # d = 0 pairs x with x; d = 1 pairs x with x − 1, outside at x = 0.
    np.testing.assert_array_equal(left[0, 0], [3, 2, 1])
    np.testing.assert_array_equal(left[1, 0], [CENSUS_BITS, 0, 2])
    right = hamming_cost_volume(codes_b, codes_a, 2, 1, layout='hwd')
    assert right.shape == (1, 3, 2)
    # right reference: x pairs with x + d, outside at x = 2 for d = 1.
    np.testing.assert_array_equal(right[0, :, 1], [0, 2, CENSUS_BITS])


@pytest.mark.parametrize(
    'bad',
    [np.zeros((4, 4), np.float32), np.zeros((4, 4, 3), np.uint8), np.zeros((0, 4), np.uint8)],
)
def test_census_rejects_bad_input(bad: np.ndarray) -> None:
    with pytest.raises(InputError, match='census_transform expects'):
        census_transform(bad)


def test_hamming_volume_fills_a_given_array_and_checks_it() -> None:
    codes = census_transform(np.random.default_rng(9).integers(0, 256, (5, 6), dtype=np.uint8))
    out = np.full((5, 6, 3), 99, np.uint8)
    result = hamming_cost_volume(codes, codes, 3, -1, layout='hwd', out=out)
    assert result is out
    np.testing.assert_array_equal(out[:, :, 0], 0)  # a view matched with itself at d = 0
    with pytest.raises(InputError, match='C-contiguous'):
        hamming_cost_volume(codes, codes, 3, -1, layout='hwd', out=np.empty((5, 6, 4), np.uint8))
    with pytest.raises(InputError, match='layout'):
        hamming_cost_volume(codes, codes, 3, -1, layout='whd')


@pytest.mark.parametrize(
    ('other_shape', 'depth', 'step', 'message'),
    [
        ((5, 5), 2, -1, 'same shape'),  # narrower: the kernel read past the row's end
        ((4, 6), 2, 1, 'same shape'),
        ((5, 6), 0, -1, 'depth'),
        ((5, 6), 2, 0, 'step'),
    ],
)
def test_hamming_volume_refuses_codes_of_other_shapes_and_bad_arguments(
    other_shape: tuple[int, int], depth: int, step: int, message: str
) -> None:
    rng = np.random.default_rng(4)
    codes = census_transform(rng.integers(0, 256, (5, 6), dtype=np.uint8))
    other = census_transform(rng.integers(0, 256, other_shape, dtype=np.uint8))
    with pytest.raises(InputError, match=message):
        hamming_cost_volume(codes, other, depth, step)

"""Review 31 of the hand-crafted measures and of winner-takes-all / left-right check: options
that are real numbers numpy cannot test (a Fraction, an int beyond float64) and a numpy
complex tolerance."""

from __future__ import annotations

from fractions import Fraction
import warnings

import numpy as np
import pytest

from cva_confidence_ros.confidence import CONFIDENCE_METHODS, ConfidenceInputs
from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.matching import left_right_check

# D = 2, H = 1, W = 2: pixel 0 a clear match at d = 0, pixel 1 an ambiguous one.
VOLUME = np.array([[[0.0, 0.5]], [[1.0, 0.6]]], np.float32)
HUGE = 10**400  # a Python int, a real number, beyond float64


def _inputs() -> ConfidenceInputs:
    return ConfidenceInputs(
        cost_volume=VOLUME,
        disparity=VOLUME.argmin(axis=0).astype(np.float32),
        image=np.zeros(VOLUME.shape[1:], np.uint8),
        cost_volume_right=VOLUME,
    )


@pytest.mark.parametrize(
    ('name', 'option', 'value'),
    [
        ('pkrn', 'eps', HUGE),
        ('lrd', 'eps', HUGE),
        ('mlm', 'sigma', HUGE),
        ('mlm', 'sigma', -HUGE),
        ('pkrn', 'eps', Fraction(-1, 1000)),
        ('mlm', 'sigma', Fraction(0)),
    ],
    ids=['pkrn-huge', 'lrd-huge', 'mlm-huge', 'mlm-minus-huge', 'pkrn-fraction', 'mlm-fraction'],
)
def test_options_numpy_cannot_test_are_refused_by_name(
    name: str, option: str, value: object
) -> None:
    # np.isfinite takes neither: a bare TypeError ("ufunc 'isfinite' not supported").
    with pytest.raises(ConfigError, match=f'{option} must be a finite number > 0'):
        CONFIDENCE_METHODS.get(name)(**{option: value})


@pytest.mark.parametrize(
    ('name', 'option', 'value', 'same'),
    [('pkrn', 'eps', Fraction(1, 1000), 1e-3), ('mlm', 'sigma', Fraction(1, 10), 0.1)],
)
def test_fraction_options_work_like_their_float(
    name: str, option: str, value: Fraction, same: float
) -> None:
    factory = CONFIDENCE_METHODS.get(name)
    np.testing.assert_array_equal(
        factory(**{option: value})(_inputs()), factory(**{option: same})(_inputs())
    )


def test_left_right_check_refuses_a_complex_tolerance() -> None:
    # A numpy complex is an np.number: 1 + 5j was read as 1 (ComplexWarning) and accepted.
    left = np.zeros((1, 2), np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        with pytest.raises(ConfigError, match='max_diff must be a real number; got complex128'):
            left_right_check(left, left, max_diff=np.complex128(1 + 5j))  # type: ignore[arg-type]


def test_left_right_check_refuses_an_int_beyond_float64() -> None:
    left = np.zeros((1, 2), np.float32)
    with pytest.raises(ConfigError, match='max_diff must be finite'):  # was an OverflowError
        left_right_check(left, left, max_diff=HUGE)


def test_left_right_check_takes_a_fraction_tolerance() -> None:
    # A Fraction is a real number: it was refused as "must be a number; got Fraction".
    left = np.array([[0.0, 2.0, 1.0]], np.float32)
    right = np.array([[0.5, 0.25, 0.0]], np.float32)  # partners: x = 0, outside, 1
    np.testing.assert_array_equal(
        left_right_check(left, right, max_diff=Fraction(1, 2)), [[True, False, False]]
    )

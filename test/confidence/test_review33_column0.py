"""Review 33 of the hand-crafted measures: column 0, where a matcher has one candidate."""

from __future__ import annotations

import numpy as np
import pytest

from cva_confidence_ros.confidence import CONFIDENCE_METHODS, ConfidenceInputs
from cva_confidence_ros.errors import InputError
from cva_confidence_ros.matching import compute_cost_volume

D = 16
SHIFT = 6


def _inputs(matcher: str) -> ConfidenceInputs:
    # A random texture seen SHIFT px apart: column 0's true disparity is 6, which its single
    # candidate (d = 0) cannot be; every other candidate there is the matcher's filler (1.0).
    rng = np.random.default_rng(3)
    texture = rng.integers(0, 256, (24, 64 + SHIFT), dtype=np.uint8)
    left, right = texture[:, :64].copy(), texture[:, SHIFT:].copy()
    volume = compute_cost_volume(left, right, matcher, D)
    right_volume = compute_cost_volume(left, right, matcher, D, view='right')
    return ConfidenceInputs(
        cost_volume=volume,
        disparity=volume.argmin(axis=0).astype(np.float32),
        image=left,
        cost_volume_right=right_volume,
    )


@pytest.mark.parametrize('matcher', ['census_bm', 'census_sgm'])
@pytest.mark.parametrize('name', ['pkrn', 'mlm', 'lrd', 'score'])
def test_column_0_gets_the_lowest_confidence(matcher: str, name: str) -> None:
    # With the filler as every other candidate's cost, column 0 had the most distinct minimum:
    # PKRN (1 + eps) / (c1 + eps), MLM ≈ 1, LRD (1 - c1) / ..., all above the median of the
    # map although its disparity (0) is wrong in every row.
    inputs = _inputs(matcher)
    method = CONFIDENCE_METHODS.get(name)()
    confidence = method(inputs)
    assert np.all(confidence[:, 0] == confidence.min())
    assert np.all(confidence[:, 0] < np.median(confidence[:, SHIFT:]))
    unit = method.to_unit_interval(confidence)
    assert np.all(unit[:, 0] == unit.min())


def test_lowest_values_per_measure() -> None:
    inputs = _inputs('census_bm')
    lowest = {'pkrn': 1.0, 'mlm': 1.0 / D, 'lrd': 0.0, 'score': -1.0}
    for name, value in lowest.items():
        column = CONFIDENCE_METHODS.get(name)()(inputs)[:, 0]
        np.testing.assert_array_equal(column, np.float32(value), err_msg=name)


@pytest.mark.parametrize('name', ['pkrn', 'mlm', 'lrd', 'score'])
def test_a_crop_further_right_keeps_its_first_column(name: str) -> None:
    # A window cut from columns 20: of the image (the fast benchmark's develop windows) has
    # every candidate in its column 0: the values there are those of the whole image.
    inputs = _inputs('census_bm')
    whole = CONFIDENCE_METHODS.get(name)()(inputs)
    crop = ConfidenceInputs(
        cost_volume=inputs.cost_volume[:, :, 20:],
        disparity=inputs.disparity[:, 20:],
        image=inputs.image[:, 20:],
        cost_volume_right=inputs.cost_volume_right[:, :, 20:],  # type: ignore[index]
        first_column=20,
    )
    part = CONFIDENCE_METHODS.get(name)()(crop)
    if name == 'lrd':  # the right pixels left of the crop are not in it: x - d1 < 0 reads 0
        np.testing.assert_array_equal(part[:, D:], whole[:, 20 + D:])
    else:
        np.testing.assert_array_equal(part, whole[:, 20:])


@pytest.mark.parametrize('value', [-1, 1.5, '3', None])
def test_first_column_must_be_an_integer_at_least_0(value: object) -> None:
    inputs = _inputs('census_bm')
    with pytest.raises(InputError, match='first_column must be an integer ≥ 0'):
        ConfidenceInputs(inputs.cost_volume, inputs.disparity, inputs.image,
                         first_column=value)  # type: ignore[arg-type]

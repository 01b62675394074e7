"""Bad inputs and options of the confidence methods fail early with our own errors."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from cva_confidence_ros.confidence import CONFIDENCE_METHODS, ConfidenceInputs
from cva_confidence_ros.errors import ConfigError, InputError

SHAPE = (2, 3)


def _volume() -> np.ndarray:
    return np.linspace(0.0, 1.0, 4 * 6, dtype=np.float32).reshape(4, *SHAPE)


def _build(**overrides: Any) -> ConfidenceInputs:
    fields = {
        'cost_volume': _volume(),
        'disparity': np.zeros(SHAPE, np.float32),
        'image': np.zeros(SHAPE, np.uint8),
    }
    fields.update(overrides)
    return ConfidenceInputs(**fields)


@pytest.mark.parametrize('bad', [np.nan, np.inf, -np.inf, 100.0, 1.01, -0.5])
@pytest.mark.parametrize('field', ['cost_volume', 'cost_volume_right'])
def test_volume_must_hold_finite_costs_in_unit_interval(field: str, bad: float) -> None:
    volume = _volume()
    volume[1, 1, 2] = bad
    with pytest.raises(InputError, match=rf'{field} must hold finite costs in \[0, 1\]'):
        _build(**{field: volume})


def test_volume_rounding_slack_is_accepted() -> None:
    volume = _volume()
    volume[0, 0, 0] = -1e-6
    volume[-1, -1, -1] = 1.0 + 1e-6
    inputs = _build(cost_volume=volume, cost_volume_right=np.ones((4, *SHAPE), np.uint8))
    assert inputs.cost_volume.dtype == np.float32
    assert inputs.cost_volume_right is not None and inputs.cost_volume_right.dtype == np.float32


@pytest.mark.parametrize(
    'volume',
    [
        np.full((4, *SHAPE), '0.5'),
        np.zeros((4, *SHAPE), np.complex64),
        np.zeros((4, *SHAPE), bool),
        np.zeros((4, *SHAPE), object),
    ],
    ids=['str', 'complex', 'bool', 'object'],
)
def test_volume_must_be_real(volume: np.ndarray) -> None:
    with pytest.raises(InputError, match=f'cost_volume must hold real numbers.*{volume.dtype}'):
        _build(cost_volume=volume)


@pytest.mark.parametrize('field', ['disparity', 'disparity_right'])
def test_disparity_must_be_real(field: str) -> None:
    with pytest.raises(InputError, match=f'{field} must hold real numbers.*complex128'):
        _build(**{field: np.zeros(SHAPE, complex)})


@pytest.mark.parametrize(
    'image',
    [np.full(SHAPE, 255000.0), np.zeros(SHAPE, np.uint16), np.zeros((*SHAPE, 3), np.float32)],
    ids=['float64', 'uint16', 'float32-rgb'],
)
def test_image_must_be_uint8(image: np.ndarray) -> None:
    with pytest.raises(InputError, match=f'image must be uint8.*{image.dtype}'):
        _build(image=image)


@pytest.mark.parametrize('matcher', [None, 3, b'census_bm'])
def test_matcher_must_be_a_str(matcher: object) -> None:
    with pytest.raises(InputError, match=f'matcher must be a str.*{type(matcher).__name__}'):
        _build(matcher=matcher)


def test_valid_inputs_still_pass() -> None:
    inputs = _build(matcher='census_bm', image=np.zeros((*SHAPE, 3), np.uint8))
    assert inputs.matcher == 'census_bm' and _build().matcher == ''


@pytest.mark.parametrize(
    ('name', 'options'),
    [
        ('pkrn', {'eps': 'x'}),
        ('pkrn', {'eps': None}),
        ('pkrn', {'eps': True}),
        ('lrd', {'eps': [1e-3]}),
        ('mlm', {'sigma': None}),
        ('mlm', {'sigma': np.bool_(True)}),
        ('mlm', {'sigma': 1 + 0j}),
    ],
)
def test_options_must_be_real_numbers(name: str, options: dict[str, Any]) -> None:
    with pytest.raises(ConfigError, match='must be a real number'):
        CONFIDENCE_METHODS.get(name)(**options)


@pytest.mark.parametrize('sigma', [1e-30, 1e-200])
def test_mlm_refuses_a_sigma_that_overflows_float32(sigma: float) -> None:
    with pytest.raises(ConfigError, match='finite in float32'):
        CONFIDENCE_METHODS.get('mlm')(sigma=sigma)


@pytest.mark.parametrize(
    ('sigma', 'expected'),
    [(1e-19, 0.5), (1e200, 0.25), (np.int64(1), 1 / (2 + 2 * np.exp(-0.5)))],
)
def test_mlm_extreme_but_valid_sigma_gives_finite_maps(sigma: float, expected: float) -> None:
    # Costs 0, 1, 0, 1 at every pixel: two equal minima.
    volume = np.stack([np.zeros(SHAPE), np.ones(SHAPE)] * 2).astype(np.float32)
    result = CONFIDENCE_METHODS.get('mlm')(sigma=sigma)(_build(cost_volume=volume))
    np.testing.assert_allclose(result[:, 1:], np.full((SHAPE[0], SHAPE[1] - 1), expected),
                               rtol=1e-6)
    np.testing.assert_array_equal(result[:, 0], 0.25)  # column 0: one candidate, 1/D


@pytest.mark.parametrize('name', ['ccnn', 'lfn', 'lgc_net'])
@pytest.mark.parametrize('depth', [None, '64', 64.5, True, 0])
def test_baselines_refuse_a_max_disparity_that_is_no_integer(name: str, depth: object) -> None:
    # int() used to take '64' and 64.5 (as 64), True (as 1, then a missing-weights error) and
    # raise a bare TypeError for None; cva_net has always refused them.
    with pytest.raises(ConfigError, match='max_disparity must be an integer ≥ 1'):
        CONFIDENCE_METHODS.get(name)(max_disparity=depth)
    assert CONFIDENCE_METHODS.get(name)(max_disparity=np.int64(64)).max_disparity == 64

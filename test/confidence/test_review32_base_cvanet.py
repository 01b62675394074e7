"""Review 32: ConfidenceInputs bounds, the unit-interval map, is_probabilistic, the registry."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any
import warnings

import numpy as np
import pytest

from cva_confidence_ros.confidence import (
    CONFIDENCE_METHODS,
    ConfidenceInputs,
    ConfidenceMethod,
    is_probabilistic,
)
from cva_confidence_ros.confidence.handcrafted import MaximumLikelihood
from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.registry import Registry

SHAPE = (2, 3)


def _inputs(volume: np.ndarray) -> ConfidenceInputs:
    return ConfidenceInputs(
        cost_volume=volume,
        disparity=np.zeros(SHAPE, np.float32),
        image=np.zeros(SHAPE, np.uint8),
    )


def _volume(value: float, dtype: Any) -> np.ndarray:
    volume = np.full((4, *SHAPE), 0.5, dtype=dtype)
    volume[1, 0, 2] = value
    return volume


@pytest.mark.parametrize('dtype', [np.float32, np.float64])
def test_cost_slack_bounds_are_inclusive_and_tight(dtype: Any) -> None:
    # 1 + 1e-4 is 1.00010001659 in float32, above the float64 bound it was compared with.
    for value in [1.0 + 1e-4, -1e-4]:
        inputs = _inputs(_volume(value, dtype))
        assert inputs.cost_volume.dtype == np.float32
        assert inputs.cost_volume[1, 0, 2] == np.float32(value)
    for value in [1.0 + 1e-4 + 1e-6, -1e-4 - 1e-6]:
        with pytest.raises(InputError, match=r'cost_volume must hold finite costs in \[0, 1\]'):
            _inputs(_volume(value, dtype))


@pytest.mark.parametrize('field', ['cost_volume', 'cost_volume_right'])
def test_a_float64_cost_beyond_float32_is_reported_as_given(field: str) -> None:
    volume = _volume(1e300, np.float64)
    fields: dict[str, Any] = {
        'cost_volume': np.zeros((4, *SHAPE), np.float32),
        'disparity': np.zeros(SHAPE, np.float32),
        'image': np.zeros(SHAPE, np.uint8),
        field: volume,
    }
    with warnings.catch_warnings():
        warnings.simplefilter('error')  # no "overflow encountered in cast" on the way
        match = rf'{field} must hold .* got values in \[0\.5, 1e\+300\]'
        with pytest.raises(InputError, match=match):
            ConfidenceInputs(**fields)


@dataclass(frozen=True)
class _Unbounded(ConfidenceMethod):
    """A method that keeps the base class's map into [0, 1]."""

    def __call__(self, inputs: ConfidenceInputs) -> np.ndarray:
        return inputs.cost_volume[0]


@pytest.mark.parametrize('method', [_Unbounded(), MaximumLikelihood()], ids=['base', 'mlm'])
def test_default_unit_interval_map_is_increasing_up_to_inf(method: ConfidenceMethod) -> None:
    values = np.array([-np.inf, -1.0, 0.0, 0.25, 1.0, 2.0, 1e30, np.inf], np.float32)
    unit = method.to_unit_interval(values)
    np.testing.assert_array_equal(unit, [0, 0, 0, 0.25, 1, 1, 1, 1])
    assert unit.dtype == np.float32
    assert method.to_unit_interval(np.array([np.nan], np.float32))[0] == 0.0


@pytest.mark.parametrize('name', ['score', 'pkrn', 'mlm', 'lrd', 'lrc'])
def test_is_probabilistic_reads_the_class_behind_a_from_options_factory(
    name: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    factory = CONFIDENCE_METHODS.get(name)
    owner = factory.__self__  # type: ignore[attr-defined]
    assert is_probabilistic(name) is False
    monkeypatch.setattr(owner, 'probabilistic', True)
    assert factory().probabilistic is True
    assert is_probabilistic(name) is True


@pytest.mark.parametrize('name', [5, None, '', b'pkrn', ('a',)])
def test_registry_refuses_a_name_that_is_no_non_empty_str(name: object) -> None:
    registry: Registry[int] = Registry('thing')
    registry.add('a', 1)
    with pytest.raises(ConfigError, match=r'thing name must be a non-empty str; got'):
        registry.add(name, 2)  # type: ignore[arg-type]
    # The registry is left usable: its names sort and an unknown name lists them.
    assert registry.names() == ['a']
    with pytest.raises(ConfigError, match=r"unknown thing 'b'; expected one of \['a'\]"):
        registry.get('b')

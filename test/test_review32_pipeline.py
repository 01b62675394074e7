"""Review 32: the pipeline with numpy float16 / float32 options and with a configuration that
is no PipelineConfig."""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest

from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.pipeline import PipelineConfig, StereoPipeline, output_region


def _pair(height: int = 40, width: int = 64, shift: int = 3) -> tuple[np.ndarray, np.ndarray]:
    texture = np.random.default_rng(32).integers(0, 256, (height, width + shift), np.uint8)
    return (np.ascontiguousarray(texture[:, shift:]),
            np.ascontiguousarray(texture[:, :width]))


def _config(**changes: object) -> PipelineConfig:
    return PipelineConfig(confidence_method='pkrn', max_disparity=16, device='cpu').replace(
        **changes
    )


def test_float16_region_of_interest_shares_give_the_rows_of_python_floats() -> None:
    # round(np.float16(0.25) * 40, 9) overflowed float16 to NaN: the config was taken, and then
    # every frame, the warm-up and output_region failed with "cannot convert float NaN to
    # integer" (a ValueError, not an InputError the node counts as a bad frame).
    config = _config(roi_top=np.float16(0.25), roi_bottom=np.float16(0.75), speckle_size=0)
    assert config.roi_rows(40) == (10, 30)
    left, right = _pair()
    pipeline = StereoPipeline(config)
    pipeline.warm_up()
    result = pipeline.process(left, right)
    assert result.rows == (10, 30)
    expected = StereoPipeline(_config(roi_top=0.25, roi_bottom=0.75, speckle_size=0)).process(
        left, right
    )
    np.testing.assert_array_equal(result.disparity, expected.disparity)
    np.testing.assert_array_equal(result.valid, expected.valid)
    region = output_region(config, result.disparity.shape)
    assert region is not None and region[10:30].all() and not region[:10].any()


def test_real_options_are_kept_as_python_floats() -> None:
    config = _config(confidence_threshold=np.float32(0.7), speckle_range=np.float16(0.5),
                     tile_budget_mb=np.float32(64), cva_cascade_fraction=Fraction(1, 2),
                     roi_top=np.float16(0.25), roi_bottom=Fraction(3, 4))
    names = ('confidence_threshold', 'speckle_range', 'tile_budget_mb', 'cva_cascade_fraction',
             'roi_top', 'roi_bottom')
    assert [type(getattr(config, name)) for name in names] == [float] * len(names)
    assert (config.speckle_range, config.tile_budget_mb, config.cva_cascade_fraction,
            config.roi_top, config.roi_bottom) == (0.5, 64.0, 0.5, 0.25, 0.75)
    # The threshold still compares in float32: the stored confidence float32(0.7) is kept.
    assert np.float32(config.confidence_threshold) == np.float32(0.7)
    assert config == _config(confidence_threshold=float(np.float32(0.7)), speckle_range=0.5,
                             tile_budget_mb=64.0, cva_cascade_fraction=0.5, roi_top=0.25,
                             roi_bottom=0.75)


@pytest.mark.parametrize('config', [{'matcher': 'census_bm'}, 'census_bm', None])
def test_a_configuration_that_is_no_pipeline_config_is_named(config: object) -> None:
    # A dict of the fields or a matcher name failed with "'dict' object has no attribute
    # 'device'" (an AttributeError, which the node's parameter callback logs as a fault).
    name = type(config).__name__
    with pytest.raises(ConfigError, match=f'config must be a PipelineConfig; got {name}'):
        StereoPipeline(config)  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match=f'config must be a PipelineConfig; got {name}'):
        output_region(config, (40, 64))  # type: ignore[arg-type]
    if isinstance(config, dict):
        with pytest.raises(ConfigError, match=r'pass PipelineConfig\(\*\*fields\)'):
            StereoPipeline(config)  # type: ignore[arg-type]

"""Review 30 of ros/params.py: NodeConfig's type checks and the values that crashed later."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from rclpy.parameter import Parameter

from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.ros.params import PARAMETERS, NodeConfig, build_configs

DEFAULTS = {spec.name: spec.default for spec in PARAMETERS}


@pytest.mark.parametrize('name', ['queue_size', 'overlay_jpeg_quality',
                                  'compressed_depth_png_level'])
@pytest.mark.parametrize('value', [2.5, 3.0, True, '10'])
def test_node_config_counts_take_integers_only(name: str, value: object) -> None:
    # Were accepted (queue_size=2.5, a png level True) or a TypeError ('<' between str and int).
    got = re.escape(repr(value))
    with pytest.raises(ConfigError, match=rf'^{name} must be an integer; got {got}$'):
        NodeConfig(**{name: value})
    assert getattr(NodeConfig(**{name: np.int64(5)}), name) == 5


@pytest.mark.parametrize('name', ['approximate_sync_tolerance_seconds', 'max_rate_hz',
                                  'min_kept_fraction', 'max_expected_kept_error',
                                  'compressed_depth_max', 'diagnostics_period_seconds'])
@pytest.mark.parametrize('value', [True, '0.5', None])
def test_node_config_numbers_take_numbers_only(name: str, value: object) -> None:
    # True passed as 1 (min_kept_fraction, max_rate_hz); '0.5' was a TypeError.
    got = re.escape(repr(value))
    with pytest.raises(ConfigError, match=rf'^{name} must be a number; got {got}$'):
        NodeConfig(**{name: value})
    assert getattr(NodeConfig(**{name: 1}), name) == 1


def test_infinite_tolerance_and_diagnostics_period_are_refused() -> None:
    # inf was accepted; tolerance_ns then raised OverflowError on the first message.
    with pytest.raises(ConfigError, match=r'^approximate_sync_tolerance_seconds must be a '
                                          r'finite number >= 0; got inf$'):
        NodeConfig(approximate_sync_tolerance_seconds=math.inf)
    with pytest.raises(ConfigError, match=r'^diagnostics_period_seconds must be a finite '
                                          r'number > 0; got inf$'):
        NodeConfig(diagnostics_period_seconds=math.inf)
    assert NodeConfig(approximate_sync_tolerance_seconds=2.5).tolerance_ns == 2_500_000_000


@pytest.mark.parametrize('rate', [1e-300, 5e-324])
def test_a_rate_limit_whose_period_overflows_is_refused(rate: float) -> None:
    # Inside the declared range [0, 1000], so rclpy and double_value let it through; the
    # node's min_period_ns then raised OverflowError (0.98e9 / rate is inf) on the first set.
    with pytest.raises(ConfigError, match=r'^max_rate_hz must be 0 \(no limit\) or at least '
                                          r'1\.06e-10 Hz'):
        build_configs(DEFAULTS, [Parameter('max_rate_hz', value=rate)])
    _, node = build_configs(DEFAULTS, [Parameter('max_rate_hz', value=1e-9)])
    assert node.min_period_ns == 980_000_000_000_000_000 < 2**63


def test_scan_frame_id_must_be_a_frame_tf2_takes() -> None:
    # A 5 was accepted (a later assertion in the message); '/base_link' was published as the
    # scan's frame, which tf2 refuses ("frame_ids cannot start with a '/'").
    with pytest.raises(ConfigError, match=r'^scan_frame_id must be a string; got 5$'):
        NodeConfig(scan_frame_id=5)
    with pytest.raises(ConfigError, match=r"^scan_frame_id must not start with '/' .*"
                                          r"got '/base_link'$"):
        build_configs(DEFAULTS, [Parameter('scan_frame_id', value='/base_link')])
    _, node = build_configs(DEFAULTS, [Parameter('scan_frame_id', value='base_link')])
    assert node.scan_frame_id == 'base_link'

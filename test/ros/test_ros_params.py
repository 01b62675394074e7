"""Tests of the node's parameter declarations, configs, parameter file and launch file."""

from __future__ import annotations

import ast
from collections.abc import Callable
from dataclasses import fields
from pathlib import Path

import pytest
from rcl_interfaces.msg import ParameterType
from rclpy.parameter import Parameter
import yaml

from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.pipeline import PipelineConfig
from cva_confidence_ros.ros.params import (
    NODE_PARAMETERS,
    PARAMETERS,
    PIPELINE_PARAMETERS,
    NodeConfig,
    build_configs,
)

ROOT = Path(__file__).resolve().parents[2]
DEFAULTS = {spec.name: spec.default for spec in PARAMETERS}


def test_parameters_map_one_to_one_onto_the_configs() -> None:
    assert [s.name for s in PIPELINE_PARAMETERS] == [f.name for f in fields(PipelineConfig)]
    assert [s.name for s in NODE_PARAMETERS] == [f.name for f in fields(NodeConfig)]
    assert len(set(DEFAULTS)) == len(PARAMETERS)
    pipeline, node = build_configs(DEFAULTS)
    assert pipeline == PipelineConfig()
    assert node == NodeConfig()


def test_descriptors_have_types_descriptions_and_ranges() -> None:
    by_name = {spec.name: spec.descriptor() for spec in PARAMETERS}
    assert all(d.description for d in by_name.values())
    assert by_name['matcher'].type == ParameterType.PARAMETER_STRING
    assert by_name['publish_points'].type == ParameterType.PARAMETER_BOOL
    assert by_name['max_disparity'].type == ParameterType.PARAMETER_INTEGER
    (ints,) = by_name['max_disparity'].integer_range
    assert (ints.from_value, ints.to_value, ints.step) == (1, 1024, 1)
    assert by_name['confidence_threshold'].type == ParameterType.PARAMETER_DOUBLE
    (floats,) = by_name['confidence_threshold'].floating_point_range
    assert (floats.from_value, floats.to_value) == (0.0, 1.0)
    assert not by_name['lr_check'].integer_range and not by_name['lr_check'].floating_point_range
    assert by_name['input_qos'].read_only and by_name['output_qos'].read_only
    assert not by_name['matcher'].read_only
    assert 'census_sgm' in by_name['matcher'].additional_constraints


def test_doubles_take_integer_literals_and_are_checked_here() -> None:
    # -p max_rate_hz:=2 or a YAML 2 arrive typed as integers; the doubles are declared with
    # dynamic typing so that rclpy lets them through, and build_configs converts and checks.
    by_name = {spec.name: spec.descriptor() for spec in PARAMETERS}
    doubles = {name for name, d in by_name.items() if d.type == ParameterType.PARAMETER_DOUBLE}
    assert {'confidence_threshold', 'max_rate_hz', 'speckle_range'} <= doubles
    assert all(by_name[name].dynamic_typing for name in doubles)
    assert not any(d.dynamic_typing for name, d in by_name.items() if name not in doubles)
    changes = [Parameter('max_rate_hz', value=2), Parameter('confidence_threshold', value=1)]
    pipeline, node = build_configs(DEFAULTS, changes)
    assert type(node.max_rate_hz) is float and node.max_rate_hz == 2.0
    assert type(pipeline.confidence_threshold) is float and pipeline.confidence_threshold == 1.0
    # What rclpy no longer checks for them: the type and the declared range.
    for name, value, match in (
        ('confidence_threshold', 'high', "confidence_threshold must be a number; got 'high'"),
        ('confidence_threshold', True, 'confidence_threshold must be a number; got True'),
        ('confidence_threshold', 2, r'confidence_threshold must be a number in \[0, 1\]; got 2'),
        ('tile_budget_mb', 0.5, r'tile_budget_mb must be a number in \[1, 1.04858e\+06\]'),
        ('max_rate_hz', float('nan'), 'max_rate_hz must be a number in'),
        ('speckle_range', [1.0], 'speckle_range must be a number'),
    ):
        with pytest.raises(ConfigError, match=match):
            build_configs(DEFAULTS, [Parameter(name, value=value)])


def test_build_configs_applies_changes() -> None:
    changes = [Parameter('max_disparity', value=128), Parameter('approximate_sync', value=True)]
    pipeline, node = build_configs(DEFAULTS, changes)
    assert pipeline.max_disparity == 128
    assert node.approximate_sync is True
    assert node.tolerance_ns == 10_000_000


@pytest.mark.parametrize(
    ('name', 'value', 'match'),
    [
        ('matcher', 'sad', 'unknown matcher'),
        ('confidence_method', 'magic', 'confidence_method'),
        ('downsample', 3, 'downsample'),
        ('device', 'tpu', 'device'),
        ('input_qos', 'fast', 'input_qos'),
        ('queue_size', 0, 'queue_size'),
        ('approximate_sync_tolerance_seconds', -0.1, 'tolerance'),
        ('no_such_parameter', 1, 'unknown parameter'),
        ('cva_stride', 3, 'cva_stride'),
        ('cva_cascade', 'mlm', 'cva_cascade'),
        ('cva_cascade_fraction', 0.0, 'cva_cascade_fraction'),
        ('cva_precision', 'int8', 'cva_precision'),
        ('min_kept_fraction', 1.5, 'min_kept_fraction'),
        ('max_expected_kept_error', 1.2, 'max_expected_kept_error'),
    ],
)
def test_build_configs_rejects(name: str, value: object, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        build_configs(DEFAULTS, [Parameter(name, value=value)])


def test_parameter_file_lists_exactly_the_declared_parameters() -> None:
    document = yaml.safe_load((ROOT / 'config' / 'cva_confidence.yaml').read_text())
    (node_key,) = document
    values = document[node_key]['ros__parameters']
    assert set(values) == set(DEFAULTS)
    for name, value in values.items():
        # The file documents the defaults, with the declared types (1.0 for a double, though
        # the node would take 1 too).
        assert type(value) is type(DEFAULTS[name]), name
        assert value == DEFAULTS[name], name


def test_launch_file_overrides_declared_parameters() -> None:
    source = (ROOT / 'launch' / 'cva_confidence.launch.py').read_text()
    tree = ast.parse(source)
    compile(tree, 'cva_confidence.launch.py', 'exec')
    (overrides,) = [
        node.value
        for node in ast.walk(tree)
        if isinstance(node, ast.AnnAssign) and getattr(node.target, 'id', '') == 'OVERRIDES'
    ]
    names = [key.value for key in overrides.keys]
    assert names and set(names) <= set(DEFAULTS)
    kinds = {
        key.value: value.id for key, value in zip(overrides.keys, overrides.values, strict=True)
    }
    for name, kind in kinds.items():
        assert kind == type(DEFAULTS[name]).__name__, name


class _Config:
    """Stand-in for ``launch.substitutions.LaunchConfiguration``: values from a dict."""

    values: dict[str, str] = {}

    def __init__(self, name: str) -> None:
        self.name = name

    def perform(self, context: object) -> str:
        return self.values[self.name]


class _Action:
    """Stand-in for launch actions: keeps the keyword arguments it was built with."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        self.args, self.kwargs = args, kwargs


class _LifecycleAction(_Action):
    """Stand-in for ``launch_ros.actions.LifecycleNode``."""


def _launch_module(monkeypatch: pytest.MonkeyPatch) -> object:
    """Import the launch file with stand-ins for the ROS launch packages (not on the index)."""
    import importlib.util
    import sys
    import types

    fakes = {
        'ament_index_python': {},
        'ament_index_python.packages': {'get_package_share_directory': lambda name: '/share'},
        'launch': {'LaunchContext': object, 'LaunchDescription': _Action},
        'launch.actions': {'DeclareLaunchArgument': _Action, 'OpaqueFunction': _Action},
        'launch.substitutions': {'LaunchConfiguration': _Config},
        'launch_ros': {},
        'launch_ros.actions': {'Node': _Action, 'LifecycleNode': _LifecycleAction},
    }
    for name, attributes in fakes.items():
        module = types.ModuleType(name)
        module.__dict__.update(attributes)
        monkeypatch.setitem(sys.modules, name, module)
    path = ROOT / 'launch' / 'cva_confidence.launch.py'
    spec = importlib.util.spec_from_file_location('cva_confidence_launch', path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _launched(
    monkeypatch: pytest.MonkeyPatch, declares: set[str]
) -> tuple[object, Callable[..., list[_Action]]]:
    """The launch module (checked to declare ``declares``) and ``start(**arguments)``: its
    actions for those launch arguments, every other one at its default."""
    launch = _launch_module(monkeypatch)
    description = launch.generate_launch_description()
    arguments = {
        (a.args[0] if a.args else a.kwargs['name']): a.kwargs.get('default_value', '')
        for a in description.args[0][:-1]
    }
    assert declares <= set(arguments)
    defaults = {**arguments, 'stereo_namespace': '/stereo', 'params_file': 'p.yaml'}

    def start(**values: str) -> list[_Action]:
        monkeypatch.setattr(_Config, 'values', {**defaults, **values})
        return launch._node(None)

    return launch, start


def test_launch_file_starts_the_cloud_filter_on_request(monkeypatch: pytest.MonkeyPatch) -> None:
    _, start = _launched(monkeypatch, {'cloud_filter_threshold'})
    (entry_points,) = [
        ast.literal_eval(node.value)
        for node in ast.walk(ast.parse((ROOT / 'setup.py').read_text()))
        if isinstance(node, ast.Assign) and getattr(node.targets[0], 'id', '') == 'ENTRY_POINTS'
    ]
    ros_names = {ros_name for ros_name, _, _ in entry_points}  # what colcon installs

    (alone,) = start(use_sim_time='true')
    assert alone.kwargs['executable'] == 'node'
    assert not isinstance(alone, _LifecycleAction)
    assert 'points_confidence' not in alone.kwargs['parameters'][2]

    node, cloud_filter = start(use_sim_time='true', cloud_filter_threshold='0.8',
                               matcher='census_sgm')
    assert node.kwargs['parameters'][2] == {'matcher': 'census_sgm', 'points_confidence': True}
    assert cloud_filter.kwargs['executable'] == 'cloud_filter'
    assert {'node', 'cloud_filter'} <= ros_names
    assert cloud_filter.kwargs['parameters'] == [{'threshold': 0.8, 'use_sim_time': True}]
    assert cloud_filter.kwargs['namespace'] is node.kwargs['namespace']


def test_launch_file_starts_the_managed_node_on_request(monkeypatch: pytest.MonkeyPatch) -> None:
    _, start = _launched(monkeypatch, {'lifecycle', 'autostart'})
    (node,) = start(lifecycle='true', autostart='true')
    assert isinstance(node, _LifecycleAction)
    assert node.kwargs['executable'] == 'lifecycle_node'
    assert node.kwargs['name'] == 'cva_confidence'
    assert node.kwargs['parameters'][2] == {'autostart': True}
    (node,) = start(lifecycle='true', autostart='false')
    assert node.kwargs['parameters'][2] == {'autostart': False}

def test_launch_file_starts_rviz_with_the_shipped_layout_on_request(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    _, start = _launched(monkeypatch, {'rviz', 'rviz_fixed_frame'})
    assert len(start()) == 1  # rviz:=false by default
    node, rviz = start(rviz='true', use_sim_time='true')
    layout = '/share/config/cva_confidence.rviz'  # the installed copy of config/
    assert (ROOT / 'config' / Path(layout).name).is_file()
    assert (rviz.kwargs['package'], rviz.kwargs['executable']) == ('rviz2', 'rviz2')
    assert rviz.kwargs['arguments'] == ['-d', layout]
    # In the node's namespace: the layout's relative topics are the node's topics.
    assert rviz.kwargs['namespace'] is node.kwargs['namespace']
    assert rviz.kwargs['parameters'] == [{'use_sim_time': True}]
    _, rviz = start(rviz='True', rviz_fixed_frame='base_link')
    assert rviz.kwargs['arguments'] == ['-d', layout, '-f', 'base_link']

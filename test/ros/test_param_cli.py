"""``cva-param``, the stand-in for ``ros2 param``: values read as ``ros2 param set`` reads them,
and the installed command against a real node over DDS (list, get, set, describe, dump)."""

from __future__ import annotations

import math
import os
from pathlib import Path
import subprocess
import sys

from node_test_utils import Spinner, localhost_context, spare_domain_id
import pytest
from rcl_interfaces.msg import ParameterType
from rclpy.parameter import Parameter, parameter_dict_from_yaml_file, parameter_value_to_python
import yaml

from cva_confidence_ros.ros.cloud_filter_node import NODE_NAME, CloudFilterNode
from cva_confidence_ros.ros.param_cli import parse_value, yaml_scalar

pytestmark = pytest.mark.timeout(240)

CVA_PARAM = Path(sys.executable).parent / 'cva-param'


@pytest.mark.parametrize(
    ('text', 'declared', 'kind', 'value'),
    [
        ('0.8', 0, ParameterType.PARAMETER_DOUBLE, 0.8),
        ('1', 0, ParameterType.PARAMETER_INTEGER, 1),
        # A whole number for a declared double is that double (ros2 param sends an integer,
        # which a node with static typing refuses).
        ('1', ParameterType.PARAMETER_DOUBLE, ParameterType.PARAMETER_DOUBLE, 1.0),
        ('true', ParameterType.PARAMETER_DOUBLE, ParameterType.PARAMETER_BOOL, True),
        ('census_sgm', 0, ParameterType.PARAMETER_STRING, 'census_sgm'),
        ("''", 0, ParameterType.PARAMETER_STRING, ''),
        ('[1, 2]', 0, ParameterType.PARAMETER_INTEGER_ARRAY, [1, 2]),
        ('[1, 2.5]', 0, ParameterType.PARAMETER_DOUBLE_ARRAY, [1.0, 2.5]),
        ('[1, 2]', ParameterType.PARAMETER_DOUBLE_ARRAY, ParameterType.PARAMETER_DOUBLE_ARRAY,
         [1.0, 2.0]),
        ('[a, b]', 0, ParameterType.PARAMETER_STRING_ARRAY, ['a', 'b']),
        ('[true, false]', 0, ParameterType.PARAMETER_BOOL_ARRAY, [True, False]),
        # Not a parameter type, or not YAML at all (ros2 param set raises on the latter): text.
        ('[1, a]', 0, ParameterType.PARAMETER_STRING, '[1, a]'),
        ('a: b', 0, ParameterType.PARAMETER_STRING, 'a: b'),
        ('a: b: c', 0, ParameterType.PARAMETER_STRING, 'a: b: c'),
    ],
)
def test_values_are_read_as_yaml(text: str, declared: int, kind: int, value: object) -> None:
    parsed = parse_value(text, declared)
    assert parsed.type == kind
    assert parameter_value_to_python(parsed) == value


@pytest.mark.parametrize(
    'value',
    [0.1, 1.0, 1e-12, 3, -2, True, False, '', 'census_sgm', 'true', '0.5', 'a: b', "it's",
     [1, 2], [0.5, 2.0], ['x', 'true'], [], math.inf, -math.inf],
)
def test_dumped_values_read_back_unchanged(value: object) -> None:
    assert yaml.safe_load(yaml_scalar(value)) == value
    assert math.isnan(yaml.safe_load(yaml_scalar(math.nan)))


def _cva_param(domain: int, *args: str) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    return subprocess.run(
        [str(CVA_PARAM), '--timeout', '20', *args],
        capture_output=True, text=True, timeout=90, env=env,
    )  # fmt: skip


def test_cva_param_reads_and_sets_a_running_nodes_parameters(tmp_path: Path) -> None:
    if not CVA_PARAM.exists():
        pytest.skip(f'{CVA_PARAM.name} is not installed next to the interpreter')
    domain = spare_domain_id()
    target = f'/{NODE_NAME}'
    with localhost_context(domain) as context:
        node = CloudFilterNode(context=context,
                               parameter_overrides=[Parameter('threshold', value=0.25)])
        spinner = Spinner(context, node)
        try:
            listed = _cva_param(domain, 'list', NODE_NAME)
            assert listed.returncode == 0, listed
            names = [line.strip() for line in listed.stdout.splitlines()]
            assert {'threshold', 'organized', 'use_sim_time'} <= set(names)
            assert names == sorted(names)

            got = _cva_param(domain, 'get', target, 'threshold')
            assert (got.returncode, got.stdout) == (0, 'Double value is: 0.25\n'), got

            done = _cva_param(domain, 'set', target, 'threshold', '1')
            assert (done.returncode, done.stdout) == (0, 'Set parameter successful\n'), done
            assert node.get_parameter('threshold').value == 1.0

            refused = _cva_param(domain, 'set', target, 'threshold', '7')
            assert refused.returncode == 1, refused
            assert refused.stderr.startswith('Setting parameter failed: ')
            assert '7' in refused.stderr
            assert node.get_parameter('threshold').value == 1.0

            unknown = _cva_param(domain, 'set', target, 'treshold', '0.5')
            assert unknown.returncode == 1
            assert f"{target} has no parameter 'treshold'" in unknown.stderr

            described = _cva_param(domain, 'describe', target, 'threshold')
            assert described.returncode == 0, described
            assert '  Type: Double\n' in described.stdout
            assert '  Range: [0.0, 1.0' in described.stdout

            dumped = _cva_param(domain, 'dump', target)
            assert dumped.returncode == 0, dumped
            params = tmp_path / 'params.yaml'
            params.write_text(dumped.stdout)
            # rclpy reads it as a --params-file, nested names (qos_overrides.…) included.
            read = parameter_dict_from_yaml_file(str(params), target_nodes=[target])
            values = {name: parameter_value_to_python(p.value) for name, p in read.items()}
            assert values['threshold'] == 1.0
            assert values['organized'] is node.get_parameter('organized').value
            for name, value in values.items():
                assert node.get_parameter(name).value == value, name
            assert any(name.startswith('qos_overrides.') for name in values)
        finally:
            spinner.stop()
            node.destroy_node()
    missing = _cva_param(domain, '--timeout', '1', 'get', '/no_such_node', 'threshold')
    assert missing.returncode == 2
    assert "/no_such_node's parameter services" in missing.stderr

"""Review 32 of the node parameters and ``cva-param``: a dump that rcl reads back with the
types it was dumped with, and the doubles described as doubles after a refused atomic change."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

from node_test_utils import SMALL_MLM, Spinner, localhost_context, spare_domain_id
import pytest
from rcl_interfaces.msg import ParameterType
import rclpy
from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter
import yaml

from cva_confidence_ros.node import ConfidenceNode
from cva_confidence_ros.ros import lifecycle_cli, param_cli
from cva_confidence_ros.ros.cloud_filter_node import CloudFilterNode
from cva_confidence_ros.ros.param_cli import yaml_scalar
from cva_confidence_ros.ros.params import parameter_values

pytestmark = pytest.mark.timeout(120)

NAMESPACE = 'review32'


def _read_params_file(path: Path, name: str, namespace: str = '') -> dict[str, Parameter]:
    """The start-up values rcl reads from the parameter file ``path`` for node ``name``."""
    context = Context()
    rclpy.init(context=context, args=['--ros-args', '--params-file', str(path)],
               domain_id=spare_domain_id())
    try:
        node = Node(name, namespace=namespace, context=context, start_parameter_services=False)
        try:
            return dict(node._parameter_overrides)
        finally:
            node.destroy_node()
    finally:
        rclpy.shutdown(context=context)


@pytest.mark.parametrize(
    'value', ['y', 'N', '1e-3', '5E2', 'inf', '-Infinity', 'nan', '08', '0x1p3',
              ['y', 'n'], ['1e3', 'a']],
)
def test_dumped_strings_read_back_as_strings_by_rcl(value: object, tmp_path: Path) -> None:
    # PyYAML (YAML 1.1) wrote these plain; rcl read y/N as booleans, 1e-3, inf, nan, 08 as
    # doubles, and refused the whole file for [y, n] ("Sequence should be of same type").
    path = tmp_path / 'params.yaml'
    path.write_text(f'/probe:\n  ros__parameters:\n    text: {yaml_scalar(value)}\n')
    read = _read_params_file(path, 'probe')['text']
    kind = Parameter.Type.STRING_ARRAY if isinstance(value, list) else Parameter.Type.STRING
    assert read.type_ == kind
    assert (list(read.value) if isinstance(value, list) else read.value) == value
    assert yaml.safe_load(yaml_scalar(value)) == value


def test_cva_param_dump_of_the_node_starts_it_again(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    # A model_path '1e-3' came back as the double 0.001, a scan frame named 'n' as the boolean
    # false: the node refused its own dump ("Trying to set parameter 'model_path' to '0.001'
    # of type 'DOUBLE', expecting type 'STRING'").
    domain = spare_domain_id()
    overrides = [*SMALL_MLM, Parameter('scan_frame_id', value='n'),
                 Parameter('model_path', value='1e-3')]
    with localhost_context(domain) as context:
        node = ConfidenceNode(context=context, namespace=NAMESPACE,
                              parameter_overrides=overrides)
        spinner = Spinner(context, node)
        try:
            monkeypatch.setenv('ROS_DOMAIN_ID', str(domain))
            monkeypatch.setattr(lifecycle_cli, 'ATTEMPT_S', 0.5)
            code = param_cli.main(['--timeout', '20', 'dump', f'/{NAMESPACE}/cva_confidence'])
            dumped, err = capsys.readouterr()
            assert code == 0, err
            values = parameter_values(node)
        finally:
            spinner.stop()
            node.destroy_node()
    # Quoted where rcl needs it, plain elsewhere.
    assert "    scan_frame_id: 'n'\n" in dumped and "    model_path: '1e-3'\n" in dumped
    assert '    matcher: census_bm\n' in dumped
    path = tmp_path / 'dump.yaml'
    path.write_text(dumped)
    context = Context()
    rclpy.init(context=context, args=['--ros-args', '--params-file', str(path)],
               domain_id=domain)
    try:
        again = ConfidenceNode(context=context, namespace=NAMESPACE)
        try:
            assert parameter_values(again) == values
            assert again.get_parameter('scan_frame_id').value == 'n'
            assert again.get_parameter('model_path').value == '1e-3'
        finally:
            again.destroy_node()
    finally:
        rclpy.shutdown(context=context)


@pytest.fixture(params=['confidence', 'cloud_filter'])
def node_and_double(request: pytest.FixtureRequest) -> Iterator[tuple[Node, str]]:
    with localhost_context(spare_domain_id()) as context:
        if request.param == 'confidence':
            node = ConfidenceNode(context=context, namespace=NAMESPACE,
                                  parameter_overrides=list(SMALL_MLM))
            double = 'max_rate_hz'
        else:
            node = CloudFilterNode(context=context, namespace=NAMESPACE)
            double = 'threshold'
        try:
            yield node, double
        finally:
            node.destroy_node()


def test_a_refused_atomic_change_leaves_the_doubles_described_as_doubles(
    node_and_double: tuple[Node, str],
) -> None:
    # rclpy retyped the dynamically typed double to the string offered, then refused the
    # read-only / out-of-range / wrongly typed parameter after it, before any callback could
    # restore the type: `ros2 param describe` said "string" for a double holding 0.0, and
    # `cva-param set NODE max_rate_hz 1e-3` then sent the string '1e-3'.
    node, double = node_and_double
    before = node.get_parameter(double).value
    refusals = [Parameter('input_qos', value='reliable')]
    if node.has_parameter('queue_size'):
        refusals += [Parameter('queue_size', value=0), Parameter('queue_size', value=2.5)]
    for refused in refusals:
        result = node.set_parameters_atomically([Parameter(double, value='abc'), refused])
        assert not result.successful
        assert node.get_parameter(double).value == before, refused
        assert node.describe_parameter(double).type == ParameterType.PARAMETER_DOUBLE, refused
    # Two settable doubles offered as strings at once: refused by the node, both restored.
    other = 'min_kept_fraction' if node.has_parameter('min_kept_fraction') else None
    if other is not None:
        result = node.set_parameters_atomically(
            [Parameter(double, value='abc'), Parameter(other, value='x')]
        )
        assert not result.successful and 'must be a number' in result.reason
        for name in (double, other):
            assert node.describe_parameter(name).type == ParameterType.PARAMETER_DOUBLE, name
    # A whole number is still taken as the double it stands for.
    assert node.set_parameters_atomically([Parameter(double, value=1)]).successful
    assert node.get_parameter(double).type_ == Parameter.Type.DOUBLE
    assert node.get_parameter(double).value == 1.0

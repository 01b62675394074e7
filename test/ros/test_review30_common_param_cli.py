"""Review of ``ros/common.py`` (QoS overrides, the spin helper) and ``cva-param``: regressions.

The ``cva-param`` cases run its ``main`` in this process against a node of this module's own,
with every kind of parameter, over real DDS (a localhost domain of their own).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
import threading
import time

from node_test_utils import Spinner, localhost_context, spare_domain_id
import pytest
from rcl_interfaces.msg import ParameterDescriptor, ParameterType
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.lifecycle import TransitionCallbackReturn
from rclpy.node import Node
from rclpy.parameter import Parameter, parameter_value_to_python
from std_msgs.msg import String

from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.ros import lifecycle_cli, param_cli
from cva_confidence_ros.ros.common import (
    QOS_OVERRIDES,
    qos_override_errors,
    qos_profile,
    spin_until_shutdown,
)
from cva_confidence_ros.ros.param_cli import parse_value

pytestmark = pytest.mark.timeout(120)

NAMESPACE = '/review30'
NODE = 'param_probe'
TARGET = f'{NAMESPACE}/{NODE}'


# common.py ----------------------------------------------------------------------------------


def _subscribe_with_override(context: Context, policy: str, value: object) -> None:
    name = f'qos_overrides./chatter.subscription.{policy}'
    node = Node('qos_probe', context=context, parameter_overrides=[Parameter(name, value=value)])
    try:
        with qos_override_errors('chatter'):
            node.create_subscription(String, 'chatter', lambda msg: None,
                                     qos_profile('sensor_data'),
                                     qos_overriding_options=QOS_OVERRIDES)
    finally:
        node.destroy_node()


@pytest.mark.parametrize(('policy', 'value'), [('reliability', 1), ('depth', 'five'),
                                               ('history', True)])
def test_a_qos_override_of_the_wrong_type_is_a_config_error(policy: str, value: object) -> None:
    # Was rclpy's InvalidParameterTypeException, past qos_override_errors: the managed node then
    # failed its activation with ERROR and dropped to unconfigured without a word in its log.
    with localhost_context(spare_domain_id()) as context:
        with pytest.raises(ConfigError, match=rf'QoS override of chatter: .*{policy}.*expected'):
            _subscribe_with_override(context, policy, value)


@pytest.mark.parametrize('policy', ['reliability', 'history'])
def test_the_unknown_qos_policy_is_refused_by_name(policy: str) -> None:
    # Was rmw's "RCLError: Failed to create subscription: invalid allocator" (a traceback and
    # exit 1 from cva-cloud-filter) for reliability:=unknown, a name rclpy's enums accept.
    with localhost_context(spare_domain_id()) as context:
        with pytest.raises(ConfigError, match=rf'{policy} unknown is not one rmw takes'):
            _subscribe_with_override(context, policy, 'unknown')


def test_a_misspelt_qos_preset_is_refused() -> None:
    # Was a reliable profile for any name but sensor_data.
    with pytest.raises(ConfigError, match="got 'best_effort'"):
        qos_profile('best_effort')
    assert qos_profile('reliable').depth == 10


def test_the_managed_node_stays_inactive_after_an_input_override_of_the_wrong_type() -> None:
    from cva_confidence_ros.ros.lifecycle_node import ManagedConfidenceNode

    overrides = [
        Parameter('matcher', value='census_bm'),
        Parameter('max_disparity', value=16),
        Parameter('confidence_method', value='mlm'),
        Parameter('qos_overrides./right/camera_info.subscription.depth', value='five'),
    ]
    with localhost_context(spare_domain_id()) as context:
        node = ManagedConfidenceNode(context=context, parameter_overrides=overrides)
        try:
            assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
            # Was ERROR: back to unconfigured, the pipeline released, nothing logged.
            assert node.trigger_activate() == TransitionCallbackReturn.FAILURE
            assert node.configured
            assert not [s for s in node.subscriptions if s.topic_name == '/left/image_rect']
        finally:
            node.destroy_node()


def test_spin_until_shutdown_ends_when_its_executor_is_shut_down() -> None:
    # Was a hot loop (spin_once returns at once on a shut-down executor) until the context
    # went too: ~160 000 spin_once calls a second on one core.
    with localhost_context(spare_domain_id()) as context:
        node = Node('spin_probe', context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        thread = threading.Thread(target=spin_until_shutdown, args=(executor,), daemon=True)
        thread.start()
        try:
            time.sleep(0.1)
            executor.shutdown()
            thread.join(1.0)
            assert not thread.is_alive()
        finally:
            node.destroy_node()
    thread.join(2.0)


# cva-param: values --------------------------------------------------------------------------


@pytest.mark.parametrize(
    ('text', 'declared', 'kind', 'value'),
    [
        # YAML 1.1 (PyYAML) reads these as strings; --params-file and -p read them as doubles.
        ('1e-3', ParameterType.PARAMETER_DOUBLE, ParameterType.PARAMETER_DOUBLE, 0.001),
        ('1.5E3', ParameterType.PARAMETER_DOUBLE, ParameterType.PARAMETER_DOUBLE, 1500.0),
        ('-2e+4', ParameterType.PARAMETER_DOUBLE, ParameterType.PARAMETER_DOUBLE, -20000.0),
        ('[1e-3, 2]', ParameterType.PARAMETER_DOUBLE_ARRAY,
         ParameterType.PARAMETER_DOUBLE_ARRAY, [0.001, 2.0]),
        # An empty list takes the declared array type (was an integer array: refused).
        ('[]', ParameterType.PARAMETER_STRING_ARRAY, ParameterType.PARAMETER_STRING_ARRAY, []),
        ('[]', ParameterType.PARAMETER_BOOL_ARRAY, ParameterType.PARAMETER_BOOL_ARRAY, []),
    ],
)
def test_values_take_the_declared_type(text: str, declared: int, kind: int, value: object) -> None:
    parsed = parse_value(text, declared)
    assert parsed.type == kind
    assert parameter_value_to_python(parsed) == value
    # Where no such type is declared, as ros2 param set reads them: a string, an integer array.
    undeclared = parse_value(text)
    assert undeclared.type in (ParameterType.PARAMETER_STRING,
                               ParameterType.PARAMETER_INTEGER_ARRAY)


@pytest.mark.parametrize('text', ['99999999999999999999', '-9223372036854775809',
                                  '[1, 99999999999999999999]'])
def test_an_integer_outside_64_bits_is_refused(text: str) -> None:
    # Was accepted into the message (then a SystemError on sending), or an OverflowError.
    with pytest.raises(ConfigError, match='integer out of the 64-bit range of a parameter'):
        parse_value(text, ParameterType.PARAMETER_INTEGER)
    # The extremes themselves, and a big whole number for a double, are fine.
    assert parse_value('9223372036854775807').integer_value == 2**63 - 1
    assert parse_value('-9223372036854775808').integer_value == -(2**63)
    doubles = (ParameterType.PARAMETER_DOUBLE_ARRAY if text.startswith('[')
               else ParameterType.PARAMETER_DOUBLE)
    assert parse_value(text, doubles).type == doubles


# cva-param: names and options, answered before anything is asked ----------------------------


@pytest.mark.parametrize(('name', 'why'), [
    ('/ns/probe/', 'node name must not be empty'),
    ('bad name', "other than alphanumerics or '_'"),
    ('/bad ns/probe', 'Invalid namespace'),
])
def test_a_node_name_that_is_none_is_refused_with_exit_2(
    name: str, why: str, capsys: pytest.CaptureFixture[str]
) -> None:
    # Was rclpy's InvalidServiceNameException with a traceback.
    assert param_cli.main(['get', name, 'threshold']) == 2
    err = capsys.readouterr().err
    assert f'cva-param: {name!r} is not a node name (' in err and why in err


def test_a_nan_timeout_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    # Was "no answer ... within nan s" without asking at all.
    assert param_cli.main(['--timeout', 'nan', 'list', '/x']) == 2
    assert '--timeout must be > 0 s; got nan' in capsys.readouterr().err


# cva-param against a running node -----------------------------------------------------------


@pytest.fixture(scope='module')
def probe() -> Iterator[tuple[int, Node]]:
    domain = spare_domain_id()
    with localhost_context(domain) as context:
        node = Node(NODE, namespace=NAMESPACE, context=context)
        node.declare_parameter('ints', [1, 2])
        node.declare_parameter('names', ['a', 'b'])
        node.declare_parameter('empty', [''])
        node.declare_parameter('gain', 0.5)
        node.declare_parameter('gain.limit', 2)  # a parameter under another one's name
        node.declare_parameter('count', 1)
        node.declare_parameter('label', 'x: y')
        # Declared, no value: dynamic typing, and a static type only.
        node.declare_parameter('anything', None, ParameterDescriptor(dynamic_typing=True))
        node.declare_parameter('typed_only', Parameter.Type.DOUBLE)
        node.set_parameters([Parameter('empty', Parameter.Type.STRING_ARRAY, [])])
        spinner = Spinner(context, node)
        try:
            yield domain, node
        finally:
            spinner.stop()
            node.destroy_node()


def _cva_param(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], domain: int,
               *args: str) -> tuple[int, str, str]:
    monkeypatch.setenv('ROS_DOMAIN_ID', str(domain))
    monkeypatch.setattr(lifecycle_cli, 'ATTEMPT_S', 0.5)  # a lost reply costs less waiting
    code = param_cli.main(['--timeout', '20', *args])
    out, err = capsys.readouterr()
    return code, out, err


def test_get_of_arrays_and_of_parameters_without_a_value(probe, monkeypatch, capsys) -> None:
    domain, _ = probe
    # ros2 param get's words (was "Integer values value is: [1, 2]").
    assert _cva_param(monkeypatch, capsys, domain, 'get', TARGET, 'ints') == (
        0, 'Integer values are: [1, 2]\n', '')
    # Was "has no parameter 'anything'" (exit 1) and a ValueError traceback for typed_only.
    for name in ('anything', 'typed_only'):
        assert _cva_param(monkeypatch, capsys, domain, 'get', TARGET, name) == (
            0, 'Parameter not set.\n', ''), name
    code, out, _ = _cva_param(monkeypatch, capsys, domain, 'describe', TARGET, 'anything')
    assert code == 0 and '  Type: not set (any type)\n' in out
    code, _, err = _cva_param(monkeypatch, capsys, domain, 'get', TARGET, 'no_such')
    assert code == 1 and f"{TARGET} has no parameter 'no_such'" in err


def test_set_takes_the_declared_type(probe, monkeypatch, capsys) -> None:
    domain, node = probe
    ok = (0, 'Set parameter successful\n', '')
    assert _cva_param(monkeypatch, capsys, domain, 'set', TARGET, 'names', '[]') == ok
    assert list(node.get_parameter('names').value) == []
    assert _cva_param(monkeypatch, capsys, domain, 'set', TARGET, 'gain', '1e-3') == ok
    assert node.get_parameter('gain').value == pytest.approx(0.001)
    assert _cva_param(monkeypatch, capsys, domain, 'set', TARGET, 'anything', '3') == ok
    assert node.get_parameter('anything').value == 3
    code, out, err = _cva_param(monkeypatch, capsys, domain, 'set', TARGET, 'count',
                                '99999999999999999999')
    assert (code, out) == (2, '')
    assert 'cva-param: integer out of the 64-bit range of a parameter: 9999' in err
    assert node.get_parameter('count').value == 1


def test_dump_reads_back_as_a_parameter_file(probe, monkeypatch, capsys, tmp_path: Path) -> None:
    domain, node = probe
    node.set_parameters([Parameter('names', value=['a', 'b']), Parameter('gain', value=0.5)])
    # Was a ValueError (zip) for typed_only, a TypeError for gain and gain.limit.
    code, out, err = _cva_param(monkeypatch, capsys, domain, 'dump', TARGET)
    assert code == 0, err
    assert out.startswith(f'{TARGET}:\n  ros__parameters:\n')
    assert '# left out (empty or byte arrays, which a parameter file cannot hold): empty' in out
    params = tmp_path / 'dump.yaml'
    params.write_text(out)
    # Read back by rcl, as --params-file reads it (was "empty: []": an unset parameter).
    context = Context()
    rclpy.init(context=context, args=['--ros-args', '--params-file', str(params)],
               domain_id=domain)
    try:
        reader = Node(NODE, namespace=NAMESPACE, context=context,
                      start_parameter_services=False)
        try:
            read = {name: p.value for name, p in reader._parameter_overrides.items()}
        finally:
            reader.destroy_node()
    finally:
        rclpy.shutdown(context=context)
    assert 'empty' not in read and 'typed_only' not in read
    assert read['gain'] == 0.5 and read['gain.limit'] == 2
    assert list(read['ints']) == [1, 2] and list(read['names']) == ['a', 'b']
    assert read['label'] == 'x: y'
    for name, value in read.items():
        got = node.get_parameter(name).value
        assert (list(got) if isinstance(got, (list, tuple)) else got) == (
            list(value) if isinstance(value, (list, tuple)) else value), name

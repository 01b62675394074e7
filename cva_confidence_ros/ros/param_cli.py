"""``cva-param``: the part of ``ros2 param`` a running node needs, for installs without ros2cli
(the pip wheels of ROS 2 do not have it).

    cva-param list /cva_confidence                             # its parameters, by name
    cva-param get /cva_confidence confidence_threshold         # Double value is: 0.5
    cva-param set /cva_confidence confidence_threshold 0.8     # Set parameter successful
    cva-param describe /cva_confidence confidence_threshold    # type, range, description
    cva-param dump /cva_confidence > params.yaml               # a --params-file of its values

It calls the node's standard ``rcl_interfaces`` parameter services, as ``ros2 param`` does, so
it works with any node. A value is read as YAML, as ``ros2 param set`` reads it (``0.8`` a
double, ``true`` a bool, ``[1, 2]`` an integer array, anything else a string), with one
courtesy: a whole number given for a parameter the node declares as a double is sent as that
double (``confidence_threshold 1``). Exit status: 0 on success, 1 when the node refused the
value or has no such parameter, 2 for bad arguments or a node that does not answer in
``--timeout``.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
import os
import sys
import time
from typing import Any

from cva_confidence_ros.ros.lifecycle_cli import call, node_name

__all__ = ['main', 'parse_value', 'yaml_scalar']

EXIT_REFUSED = 1
EXIT_NO_ANSWER = 2

#: ``ros2 param get``'s words for the parameter types, by ``ParameterType`` value.
TYPE_NAMES = {
    1: 'Boolean',
    2: 'Integer',
    3: 'Double',
    4: 'String',
    5: 'Byte values',
    6: 'Boolean values',
    7: 'Integer values',
    8: 'Double values',
    9: 'String values',
}


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='cva-param',
        description="List, get, set, describe or dump a running ROS 2 node's parameters, as "
        '`ros2 param` does.',
    )
    parser.add_argument('--timeout', type=float, default=10.0,
                        help='seconds to wait for the node and its answer (default 10)')
    commands = parser.add_subparsers(dest='command', required=True)
    listing = commands.add_parser('list', help="print the names of the node's parameters")
    listing.add_argument('node', help='node name, e.g. /cva_confidence')
    get = commands.add_parser('get', help="print a parameter's value")
    get.add_argument('node')
    get.add_argument('name')
    change = commands.add_parser('set', help='set a parameter (the node checks the value)')
    change.add_argument('node')
    change.add_argument('name')
    change.add_argument('value', help='read as YAML: 0.8, true, census_sgm, [1, 2]')
    describe = commands.add_parser('describe', help="print a parameter's type and limits")
    describe.add_argument('node')
    describe.add_argument('name')
    dump = commands.add_parser('dump', help='print every value as a --params-file YAML')
    dump.add_argument('node')
    return parser


def parse_value(text: str, declared_type: int = 0) -> Any:
    """``text`` as a ``rcl_interfaces/ParameterValue``, read as YAML as ``ros2 param set`` does.

    Args:
        text: The value as typed on the command line.
        declared_type: The ``ParameterType`` the node declares for the parameter (0 = unknown);
            a whole number for a double (or a list of them for a double array) becomes that.
    """
    from rcl_interfaces.msg import ParameterType, ParameterValue
    import yaml

    try:
        loaded = yaml.safe_load(text)
    except yaml.YAMLError:
        loaded = text
    value = ParameterValue()
    if isinstance(loaded, bool):
        value.type, value.bool_value = ParameterType.PARAMETER_BOOL, loaded
    elif isinstance(loaded, int) and declared_type == ParameterType.PARAMETER_DOUBLE:
        value.type, value.double_value = ParameterType.PARAMETER_DOUBLE, float(loaded)
    elif isinstance(loaded, int):
        value.type, value.integer_value = ParameterType.PARAMETER_INTEGER, loaded
    elif isinstance(loaded, float):
        value.type, value.double_value = ParameterType.PARAMETER_DOUBLE, loaded
    elif isinstance(loaded, list) and loaded and all(isinstance(v, bool) for v in loaded):
        value.type, value.bool_array_value = ParameterType.PARAMETER_BOOL_ARRAY, loaded
    elif isinstance(loaded, list) and all(
        isinstance(v, (int, float)) and not isinstance(v, bool) for v in loaded
    ) and (
        any(isinstance(v, float) for v in loaded)
        or declared_type == ParameterType.PARAMETER_DOUBLE_ARRAY
    ):
        value.type = ParameterType.PARAMETER_DOUBLE_ARRAY
        value.double_array_value = [float(v) for v in loaded]
    elif isinstance(loaded, list) and all(
        isinstance(v, int) and not isinstance(v, bool) for v in loaded
    ):
        value.type, value.integer_array_value = ParameterType.PARAMETER_INTEGER_ARRAY, loaded
    elif isinstance(loaded, list) and all(isinstance(v, str) for v in loaded):
        value.type, value.string_array_value = ParameterType.PARAMETER_STRING_ARRAY, loaded
    else:
        # A string, or YAML that is none of the types above (a mapping, a mixed list): the text.
        value.type = ParameterType.PARAMETER_STRING
        value.string_value = loaded if isinstance(loaded, str) else text
    return value


def yaml_scalar(value: Any) -> str:
    """``value`` (a Python parameter value) written so that YAML reads it back unchanged."""
    import yaml

    text = yaml.safe_dump(value, default_flow_style=True, width=10**6)
    return text.removesuffix('\n').removesuffix('\n...')


def _describe(node: Any, target: str, names: list[str], deadline: float) -> list[Any] | None:
    from rcl_interfaces.srv import DescribeParameters

    answer = call(node, DescribeParameters, f'{target}/describe_parameters',
                   DescribeParameters.Request(names=names), deadline)
    return None if answer is None else list(answer.descriptors)


def _limits(descriptor: Any) -> str:
    ranges = list(descriptor.floating_point_range) + list(descriptor.integer_range)
    if not ranges:
        return ''
    low, high = ranges[0].from_value, ranges[0].to_value
    step = f', step {ranges[0].step}' if ranges[0].step else ''
    return f'[{low}, {high}{step}]'


def _run(node: Any, args: argparse.Namespace, target: str, deadline: float) -> tuple[int, str]:
    """Do the command; ``(exit status, text)``, the text for stdout when the status is 0."""
    from rcl_interfaces.msg import Parameter, ParameterType
    from rcl_interfaces.srv import GetParameters, ListParameters, SetParameters
    from rclpy.parameter import parameter_value_to_python

    no_answer = (EXIT_NO_ANSWER, '')
    if args.command in ('list', 'dump'):
        listed = call(node, ListParameters, f'{target}/list_parameters',
                       ListParameters.Request(), deadline)
        if listed is None:
            return no_answer
        names = sorted(listed.result.names)
        if args.command == 'list':
            return 0, ''.join(f'  {name}\n' for name in names)
        got = call(node, GetParameters, f'{target}/get_parameters',
                    GetParameters.Request(names=names), deadline)
        if got is None:
            return no_answer
        lines = [f'{target}:', '  ros__parameters:']
        tree: dict[str, Any] = {}
        for name, value in zip(names, got.values, strict=True):
            if value.type == ParameterType.PARAMETER_NOT_SET:
                continue
            branch = tree
            *path, leaf = name.split('.')
            for part in path:
                branch = branch.setdefault(part, {})
            branch[leaf] = parameter_value_to_python(value)
        _dump_tree(tree, 4, lines)
        return 0, '\n'.join(lines) + '\n'
    descriptors = _describe(node, target, [args.name], deadline)
    if descriptors is None:
        return no_answer
    declared = descriptors[0].type if descriptors else ParameterType.PARAMETER_NOT_SET
    if declared == ParameterType.PARAMETER_NOT_SET:
        return EXIT_REFUSED, f'{target} has no parameter {args.name!r}'
    if args.command == 'describe':
        descriptor = descriptors[0]
        lines = [f'Parameter name: {args.name}',
                 f'  Type: {TYPE_NAMES.get(descriptor.type, descriptor.type)}']
        if descriptor.description:
            lines.append(f'  Description: {descriptor.description}')
        if descriptor.additional_constraints:
            lines.append(f'  Constraints: {descriptor.additional_constraints}')
        if limits := _limits(descriptor):
            lines.append(f'  Range: {limits}')
        lines.append(f'  Read only: {str(descriptor.read_only).lower()}')
        return 0, '\n'.join(lines) + '\n'
    if args.command == 'get':
        got = call(node, GetParameters, f'{target}/get_parameters',
                    GetParameters.Request(names=[args.name]), deadline)
        if got is None:
            return no_answer
        (value,) = got.values
        python = parameter_value_to_python(value)
        return 0, f'{TYPE_NAMES.get(value.type, value.type)} value is: {python}\n'
    parameter = Parameter(name=args.name, value=parse_value(args.value, declared))
    done = call(node, SetParameters, f'{target}/set_parameters',
                 SetParameters.Request(parameters=[parameter]), deadline)
    if done is None:
        return no_answer
    (result,) = done.results
    if not result.successful:
        return EXIT_REFUSED, f'Setting parameter failed: {result.reason or "(no reason given)"}'
    return 0, 'Set parameter successful\n'


def _dump_tree(tree: dict[str, Any], indent: int, lines: list[str]) -> None:
    for key, value in tree.items():
        if isinstance(value, dict):
            lines.append(f'{" " * indent}{key}:')
            _dump_tree(value, indent + 2, lines)
        else:
            lines.append(f'{" " * indent}{key}: {yaml_scalar(value)}')


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit status."""
    args = _parser().parse_args(list(sys.argv[1:] if argv is None else argv))
    if args.timeout <= 0:
        print(f'cva-param: --timeout must be > 0 s; got {args.timeout:g}', file=sys.stderr)
        return EXIT_NO_ANSWER
    import rclpy

    target = node_name(args.node)
    deadline = time.monotonic() + args.timeout
    rclpy.init(args=['cva-param'])  # the command line is argparse's, not rclpy's
    try:
        node = rclpy.create_node(f'cva_param_{os.getpid()}',
                                 start_parameter_services=False)
        try:
            code, text = _run(node, args, target, deadline)
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown()
    if code == EXIT_NO_ANSWER:
        print(f"cva-param: no answer from {target}'s parameter services within "
              f'{args.timeout:g} s (is it running and in this ROS_DOMAIN_ID?)', file=sys.stderr)
    elif code:
        print(text, file=sys.stderr)
    else:
        sys.stdout.write(text)
    return code


if __name__ == '__main__':
    sys.exit(main())

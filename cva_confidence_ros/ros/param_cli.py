"""``cva-param``: the part of ``ros2 param`` a running node needs, for installs without ros2cli
(the pip wheels of ROS 2 do not have it).

    cva-param list /cva_confidence                             # its parameters, by name
    cva-param get /cva_confidence confidence_threshold         # Double value is: 0.5
    cva-param set /cva_confidence confidence_threshold 0.8     # Set parameter successful
    cva-param describe /cva_confidence confidence_threshold    # type, range, description
    cva-param dump /cva_confidence > params.yaml               # a --params-file of its values

It calls the node's standard ``rcl_interfaces`` parameter services, as ``ros2 param`` does, so
it works with any node. A value is read as YAML, as ``ros2 param set`` reads it (``0.8`` a
double, ``true`` a bool, ``[1, 2]`` an integer array, anything else a string), with
courtesies for a parameter whose type the node declares: a whole number given for a double is
sent as that double (``confidence_threshold 1``), so is a number in exponent form (``1e-3``,
which YAML 1.1 reads as a string but ``--params-file`` and ``-p`` read as a double), and ``[]``
is an empty array of the declared array type. Exit status: 0 on success, 1 when the node refused
the value or has no such parameter, 2 for bad arguments (a node name that is none, an integer
outside 64 bits) or a node that does not answer in ``--timeout``.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
import os
import sys
import time
from typing import Any

from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.ros.lifecycle_cli import (
    ask,
    bad_node_name,
    call,
    init_rclpy,
    interruptible,
    node_name,
)

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
#: A number in exponent form without a dot (``1e-3``, ``5E+2``): a string to YAML 1.1 (PyYAML),
#: a double to YAML 1.2 and to rcl's parameter files.
_EXPONENT_FLOAT = r'^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$'
_INT64 = (-(2**63), 2**63 - 1)
#: The plain (unquoted) words rcl's parameter files read as booleans; PyYAML writes y, Y, n and
#: N plain, which YAML 1.1 reads as strings.
_RCL_BOOLS = frozenset(
    spelling
    for word in ('y', 'yes', 'true', 'on', 'n', 'no', 'false', 'off')
    for spelling in (word, word.capitalize(), word.upper())
)
#: The start of a plain scalar that rcl may read as a number (it takes whatever ``strtod``
#: reads whole: ``1e-3``, ``08``, ``inf``, ``nan``, ``0x1p3``), where PyYAML writes it plain.
_RCL_NUMBER_START = r'\s*[-+]?(?:[0-9.]|inf|nan)'


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='cva-param',
        description="List, get, set, describe or dump a running ROS 2 node's parameters, as "
        '`ros2 param` does.',
        epilog='Exit codes: 0 done, 1 the node refused the value or has no such parameter, 2 '
        'bad arguments or no answer within --timeout, 130 stopped by Ctrl-C, 143 by SIGTERM.',
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
            a whole number or one in exponent form for a double (or a list of them for a double
            array) becomes that, and ``[]`` an empty array of the declared array type.

    Raises:
        ConfigError: For an integer outside 64 bits (a parameter's integers are int64).
    """
    from rcl_interfaces.msg import ParameterType, ParameterValue
    import yaml

    doubles = declared_type in (ParameterType.PARAMETER_DOUBLE,
                                ParameterType.PARAMETER_DOUBLE_ARRAY)
    try:
        loaded = yaml.load(text, Loader=_double_loader() if doubles else yaml.SafeLoader)
    except yaml.YAMLError:
        loaded = text
    value = ParameterValue()
    if loaded == [] and declared_type in (
        ParameterType.PARAMETER_BOOL_ARRAY, ParameterType.PARAMETER_STRING_ARRAY,
        ParameterType.PARAMETER_DOUBLE_ARRAY, ParameterType.PARAMETER_INTEGER_ARRAY,
    ):
        # An empty list has no type of its own: the declared one (else an integer array).
        value.type = declared_type
    elif isinstance(loaded, bool):
        value.type, value.bool_value = ParameterType.PARAMETER_BOOL, loaded
    elif isinstance(loaded, int) and declared_type == ParameterType.PARAMETER_DOUBLE:
        value.type, value.double_value = ParameterType.PARAMETER_DOUBLE, float(loaded)
    elif isinstance(loaded, int):
        (whole,) = _int64([loaded], text)
        value.type, value.integer_value = ParameterType.PARAMETER_INTEGER, whole
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
        value.type = ParameterType.PARAMETER_INTEGER_ARRAY
        value.integer_array_value = _int64(loaded, text)
    elif isinstance(loaded, list) and all(isinstance(v, str) for v in loaded):
        value.type, value.string_array_value = ParameterType.PARAMETER_STRING_ARRAY, loaded
    else:
        # A string, or YAML that is none of the types above (a mapping, a mixed list): the text.
        value.type = ParameterType.PARAMETER_STRING
        value.string_value = loaded if isinstance(loaded, str) else text
    return value


def _int64(values: list[int], text: str) -> list[int]:
    """``values``, each checked to fit a parameter's integers (int64)."""
    if any(not _INT64[0] <= v <= _INT64[1] for v in values):
        raise ConfigError(f'integer out of the 64-bit range of a parameter: {text}')
    return values


def _double_loader() -> type:
    """PyYAML's safe loader that also reads a number in exponent form as a double."""
    import re

    import yaml

    class DoubleLoader(yaml.SafeLoader):
        pass

    DoubleLoader.add_implicit_resolver(
        'tag:yaml.org,2002:float', re.compile(_EXPONENT_FLOAT), list('-+0123456789.')
    )
    return DoubleLoader


def yaml_scalar(value: Any) -> str:
    """``value`` (a Python parameter value) written so that YAML, and rcl reading a parameter
    file, read it back unchanged: a string that rcl would take for a bool or a number (``y``,
    ``1e-3``, ``inf``, which YAML 1.1 leaves strings) is quoted."""
    import re

    import yaml

    class RclDumper(yaml.SafeDumper):
        pass

    def represent_str(dumper: yaml.SafeDumper, text: str) -> Any:
        other = text in _RCL_BOOLS or re.match(_RCL_NUMBER_START, text, re.IGNORECASE)
        return dumper.represent_scalar('tag:yaml.org,2002:str', text, style="'" if other else None)

    RclDumper.add_representer(str, represent_str)
    text = yaml.dump(value, Dumper=RclDumper, default_flow_style=True, width=10**6)
    return text.removesuffix('\n').removesuffix('\n...')


def _describe(node: Any, target: str, names: list[str], deadline: float) -> list[Any] | None:
    from rcl_interfaces.srv import DescribeParameters

    answer = call(node, DescribeParameters, f'{target}/describe_parameters',
                   DescribeParameters.Request(names=names), deadline)
    return None if answer is None else list(answer.descriptors)


def _values(node: Any, target: str, names: list[str], deadline: float) -> list[Any] | None:
    """The values of ``names`` (type "not set" for one without a value), or None: no answer.

    rclpy answers a request with no value at all when one of its names has none (a parameter
    declared by its type only, or one undeclared since it was listed): then one by one.
    """
    from rcl_interfaces.msg import ParameterValue
    from rcl_interfaces.srv import GetParameters

    got = call(node, GetParameters, f'{target}/get_parameters',
               GetParameters.Request(names=names), deadline)
    if got is None or len(got.values) == len(names):
        return None if got is None else list(got.values)
    client = node.create_client(GetParameters, f'{target}/get_parameters')
    try:
        values = []
        for name in names:
            one = ask(node, client, GetParameters.Request(names=[name]), deadline)
            if one is None:
                return None
            values.append(one.values[0] if one.values else ParameterValue())
        return values
    finally:
        node.destroy_client(client)


def _place(tree: dict[str, Any], name: str, value: Any) -> None:
    """Put ``value`` into ``tree`` under the parts of the dotted ``name``; where a part is
    already a value (``a`` and ``a.b`` both parameters), the rest of the name stays one key
    (rcl reads ``a.b: 1`` in a parameter file as ``a.b`` too)."""
    *path, leaf = name.split('.')
    for index, part in enumerate(path):
        if not isinstance(tree.setdefault(part, {}), dict):
            tree['.'.join(path[index:] + [leaf])] = value
            return
        tree = tree[part]
    if isinstance(tree.get(leaf), dict):
        # ``a.b`` placed before ``a`` (names out of sorted order): that branch goes flat.
        for key, nested in tree.pop(leaf).items():
            tree[f'{leaf}.{key}'] = nested
    tree[leaf] = value


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
        values = _values(node, target, names, deadline)
        if values is None:
            return no_answer
        lines = [f'{target}:', '  ros__parameters:']
        tree: dict[str, Any] = {}
        left_out = []
        for name, value in zip(names, values, strict=True):
            if value.type == ParameterType.PARAMETER_NOT_SET:
                continue
            python = parameter_value_to_python(value)
            if value.type == ParameterType.PARAMETER_BYTE_ARRAY or python == []:
                # rcl reads ``[]`` back as "not set" (the parameter then has no value at all)
                # and has no byte arrays: such values cannot go into a parameter file.
                left_out.append(name)
                continue
            _place(tree, name, python)
        _dump_tree(tree, 4, lines)
        if left_out:
            lines.append(f'    # left out (empty or byte arrays, which a parameter file cannot '
                         f'hold): {", ".join(left_out)}')
        return 0, '\n'.join(lines) + '\n'
    descriptors = _describe(node, target, [args.name], deadline)
    if descriptors is None:
        return no_answer
    if not descriptors:
        # rclpy and rclcpp answer an undeclared name with no descriptor at all; a declared
        # parameter without a value (dynamic typing) has one of type "not set".
        return EXIT_REFUSED, f'{target} has no parameter {args.name!r}'
    declared = descriptors[0].type
    if args.command == 'describe':
        descriptor = descriptors[0]
        kind = TYPE_NAMES.get(descriptor.type, 'not set (any type)')
        lines = [f'Parameter name: {args.name}', f'  Type: {kind}']
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
        # rclpy answers a declared parameter without a value with no value at all.
        if not got.values or got.values[0].type == ParameterType.PARAMETER_NOT_SET:
            return 0, 'Parameter not set.\n'
        (value,) = got.values
        python = parameter_value_to_python(value)
        # ros2 param get's words: "Double value is: 0.5", "Integer values are: [1, 2]".
        label = TYPE_NAMES.get(value.type, str(value.type))
        label += ' are:' if value.type >= ParameterType.PARAMETER_BYTE_ARRAY else ' value is:'
        return 0, f'{label} {python}\n'
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
    """Run the command line; returns the exit status (130 / 143 after Ctrl-C / SIGTERM)."""
    args = _parser().parse_args(list(sys.argv[1:] if argv is None else argv))
    return interruptible('cva-param', lambda: _main(args))


def _main(args: argparse.Namespace) -> int:
    if not args.timeout > 0:  # nan too
        print(f'cva-param: --timeout must be > 0 s; got {args.timeout:g}', file=sys.stderr)
        return EXIT_NO_ANSWER
    import rclpy

    target = node_name(args.node)
    why = bad_node_name(target)
    if why is not None:
        print(f'cva-param: {args.node!r} is not a node name ({why})', file=sys.stderr)
        return EXIT_NO_ANSWER
    deadline = time.monotonic() + args.timeout
    init_rclpy('cva-param')
    try:
        node = rclpy.create_node(f'cva_param_{os.getpid()}',
                                 start_parameter_services=False)
        try:
            code, text = _run(node, args, target, deadline)
        except ConfigError as error:  # a value no parameter can take
            code, text = EXIT_NO_ANSWER, f'cva-param: {error}'
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown()
    if code == EXIT_NO_ANSWER and text:
        print(text, file=sys.stderr)
    elif code == EXIT_NO_ANSWER:
        print(f"cva-param: no answer from {target}'s parameter services within "
              f'{args.timeout:g} s (is it running and in this ROS_DOMAIN_ID?)', file=sys.stderr)
    elif code:
        print(text, file=sys.stderr)
    else:
        sys.stdout.write(text)
    return code


if __name__ == '__main__':
    sys.exit(main())

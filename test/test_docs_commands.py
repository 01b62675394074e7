"""The commands the documentation shows are ones the tools accept.

Every ``cva-*`` command line in the README, the model cards and ``docs/`` (fenced blocks and
inline code) is read for its ``--options``; each must be one that tool's ``--help`` lists (for
``cva-benchmark``, that of the ``--suite`` the line names). Every ``name:=value`` in the README
must name a node or cloud-filter parameter, a launch argument or a topic of the nodes (a
remap). A renamed option otherwise lives on in a model card's "exact command" until a user
pastes it.
"""

from __future__ import annotations

import ast
from collections import defaultdict
import contextlib
import importlib
import io
from pathlib import Path
import re

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCUMENTS = [ROOT / 'README.md', *sorted((ROOT / 'models').glob('*.md')),
             *sorted((ROOT / 'docs').glob('*.md'))]
FENCED = re.compile(r'```[a-z]*\n(.*?)```', re.S)
COMMAND = re.compile(r'(?:^|[\s=(\[])(cva-[a-z0-9-]+)(\s.*)?$')
OPTION = re.compile(r'(?<![\w-])(--[a-z][a-z0-9-]*)')
# The ROS node's own arguments are ROS's (``--ros-args -p …``), tested in test_node_arguments.
NOT_ARGPARSE = {'cva-node', 'cva-lifecycle-node'}


def _entry_points() -> dict[str, str]:
    """pip console-script name → 'module:function', from setup.py's table."""
    tree = ast.parse((ROOT / 'setup.py').read_text(encoding='utf-8'))
    (table,) = [
        ast.literal_eval(node.value) for node in ast.walk(tree)
        if isinstance(node, ast.Assign) and getattr(node.targets[0], 'id', '') == 'ENTRY_POINTS'
    ]
    return {pip_name: target for _, pip_name, target in table}


def _code(text: str) -> list[str]:
    """The lines of fenced blocks (continuations joined) and the inline code spans."""
    lines = []
    for block in FENCED.findall(text):
        lines += block.replace('\\\n', ' ').splitlines()
    lines += [span.replace('\n', ' ') for span in re.findall(r'`([^`]+)`', FENCED.sub('', text))]
    return lines


def _documented_options() -> dict[tuple[str, str | None], dict[str, set[str]]]:
    """(tool, suite or None) → option → documents that use it with that tool."""
    found: dict[tuple[str, str | None], dict[str, set[str]]] = defaultdict(
        lambda: defaultdict(set)
    )
    for path in DOCUMENTS:
        for line in _code(path.read_text(encoding='utf-8')):
            for command in re.split(r'[|;&]', line):
                match = COMMAND.search(command)
                if match is None:
                    continue
                tool, args = match.group(1), (match.group(2) or '').split(' # ')[0]
                suite = re.search(r'--suite[ =](\w+)', args)
                options = found[(tool, suite.group(1) if suite else None)]
                for option in OPTION.findall(args):
                    options[option].add(path.relative_to(ROOT).as_posix())
    return found


def _help(tool: str, suite: str | None) -> str:
    module, function = _entry_points()[tool].split(':')
    main = getattr(importlib.import_module(module), function)
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit) as exited:
        main([*(['--suite', suite] if suite else []), '--help'])
    assert exited.value.code == 0
    return out.getvalue()


DOCUMENTED = _documented_options()


def test_the_documents_show_commands_of_most_tools() -> None:
    # The scan itself works: a regex that found nothing would pass everything below.
    tools = {tool for tool, _ in DOCUMENTED}
    assert tools >= {'cva-train', 'cva-evaluate', 'cva-bag-replay', 'cva-benchmark', 'cva-mask'}
    assert {'--weights', '--json', '--data-root'} <= set(DOCUMENTED[('cva-evaluate', None)])
    assert all(tool in _entry_points() for tool in tools), tools - set(_entry_points())


@pytest.mark.parametrize(
    ('tool', 'suite'),
    sorted((key for key in DOCUMENTED if key[0] not in NOT_ARGPARSE), key=str),
    ids=lambda value: value or '',
)
def test_documented_options_are_accepted(tool: str, suite: str | None) -> None:
    text = _help(tool, suite)
    unknown = {
        option: sorted(where) for option, where in DOCUMENTED[(tool, suite)].items()
        if option != '--help' and not re.search(rf'(?<![\w-]){option}(?![\w-])', text)
    }
    assert not unknown, f'{tool} {suite or ""}: options not in its --help: {unknown}'


def _launch_arguments() -> set[str]:
    source = (ROOT / 'launch' / 'cva_confidence.launch.py').read_text(encoding='utf-8')
    return set(re.findall(r"DeclareLaunchArgument\(\s*'(\w+)'", source))


def test_readme_ros_assignments_name_real_parameters() -> None:
    from cva_confidence_ros.ros.cloud_filter_node import PARAMETER_DESCRIPTIONS
    from cva_confidence_ros.ros.confidence_node import _OUTPUTS, _TOPICS
    from cva_confidence_ros.ros.params import PARAMETERS

    launch = _launch_arguments()
    assert {'lifecycle', 'autostart', 'cloud_filter_threshold'} <= launch
    known = {spec.name for spec in PARAMETERS} | set(PARAMETER_DESCRIPTIONS) | launch
    known |= {*_TOPICS.values(), *(topic for _, topic in _OUTPUTS), 'points2_filtered'}
    known |= {'use_sim_time', '__ns', '__node'}
    text = (ROOT / 'README.md').read_text(encoding='utf-8')
    names = set()
    for line in _code(text):
        # not qos_overrides.<topic>.publisher.depth:=…, whose form the node checks itself
        names |= set(re.findall(r'(?<![\w/.])([a-z_][\w/]*):=', line))
    assert {'left/image_rect', 'max_rate_hz', 'points2'} <= names
    assert not names - known, f'README sets unknown parameters: {sorted(names - known)}'

"""The command line of ``cva-node`` and ``cva-cloud-filter`` outside ``--ros-args``.

``-h``/``--help`` prints the usage (topics, parameters with defaults) and exits 0 without
starting the node; any other argument there is refused with one line and exit status 2, as a
forgotten ``--ros-args`` must not start a node with its default parameters. What ``ros2 run``
and ``ros2 launch`` pass (``--ros-args -r __node:=… -r __ns:=… --params-file …``) still starts
it.
"""

from __future__ import annotations

from dataclasses import fields
import os
from pathlib import Path
import signal
import subprocess
import sys
import time

from node_test_utils import spare_domain_id
import pytest

from cva_confidence_ros.ros.cloud_filter_node import CloudFilterConfig
from cva_confidence_ros.ros.common import EXIT_BAD_START, check_arguments, params_file_problems
from cva_confidence_ros.ros.params import PARAMETERS

pytestmark = pytest.mark.timeout(180)

BIN = Path(sys.executable).parent
#: script → (its parameter names, a ``name:=value`` of its own for the hint)
SCRIPTS = {
    'cva-node': ([spec.name for spec in PARAMETERS], 'confidence_threshold:=0.8'),
    'cva-lifecycle-node': (
        ['autostart', *(spec.name for spec in PARAMETERS)], 'confidence_threshold:=0.8'
    ),
    'cva-cloud-filter': ([spec.name for spec in fields(CloudFilterConfig)], 'threshold:=0.8'),
}


def _env() -> dict[str, str]:
    return dict(
        os.environ,
        ROS_DOMAIN_ID=str(spare_domain_id()),
        ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
        PYTHONUNBUFFERED='1',
        OMP_NUM_THREADS='1',
    )


def _script(name: str) -> Path:
    path = BIN / name
    if not path.exists():
        pytest.skip(f'{name} is not installed next to the interpreter (make setup)')
    return path


def _call(name: str, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(_script(name)), *args], capture_output=True, text=True, timeout=60, env=_env()
    )


@pytest.mark.parametrize('script', sorted(SCRIPTS))
@pytest.mark.parametrize(
    'args',
    [
        ('--help',),
        ('-h',),
        # After the ROS arguments, as ``ros2 run pkg exe --ros-args … -- --help`` gives it.
        ('--ros-args', '-r', '__ns:=/help_test', '--', '--help'),
    ],
    ids=['help', 'h', 'after-ros-args'],
)
def test_help_prints_the_usage_and_starts_nothing(script: str, args: tuple[str, ...]) -> None:
    started = time.monotonic()
    done = _call(script, *args)
    elapsed = time.monotonic() - started
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stderr == ''
    assert done.stdout.startswith(f'usage: {script} [-h] [--ros-args')
    assert '--params-file FILE' in done.stdout and '-p NAME:=VALUE' in done.stdout
    names, _ = SCRIPTS[script]
    for name in names:
        assert f'\n  {name}:=' in done.stdout, name
    assert 'points2' in done.stdout and '/diagnostics' in done.stdout
    assert '.subscription.reliability:=reliable' in done.stdout  # the per-topic QoS overrides
    assert 'ready' not in done.stdout
    # Nothing heavy behind it: no node, no pipeline (generous for a loaded test machine).
    assert elapsed < 30.0


def test_help_shows_defaults_and_imports_neither_torch_nor_the_node() -> None:
    probe = (
        'import contextlib, io, sys\n'
        'from cva_confidence_ros.node import main\n'
        'out = io.StringIO()\n'
        'with contextlib.redirect_stdout(out):\n'
        "    code = main(['cva-node', '--help'])\n"
        "heavy = [m for m in ('torch', 'numba', 'cva_confidence_ros.ros.confidence_node')\n"
        '         if m in sys.modules]\n'
        'print(code, heavy)\n'
        'print(out.getvalue())\n'
    )
    done = subprocess.run(
        [sys.executable, '-c', probe], capture_output=True, text=True, timeout=60, env=_env()
    )
    assert done.returncode == 0, done.stderr
    first, _, text = done.stdout.partition('\n')
    assert first == '0 []'
    # Defaults as they are written after -p, descriptions below them.
    assert '\n  confidence_threshold:=0.5  [0.0, 1.0]\n' in text
    assert "\n  model_path:=''\n" in text
    assert '\n  publish_points:=true\n' in text
    assert '\n  input_qos:=sensor_data  (start-up only)\n' in text
    assert 'Allowed: one of census_bm, census_sgm, mccnn_fast.' in text


@pytest.mark.parametrize('script', sorted(SCRIPTS))
@pytest.mark.parametrize(
    ('args', 'shown', 'hint'),
    [
        (('--bogus-flag',), '--bogus-flag', 'e.g. --ros-args -p {example}'),
        # A forgotten --ros-args: the hint is the line as it should have been.
        (('-p', 'threshold:=0.8'), '-p threshold:=0.8', ': --ros-args -p threshold:=0.8'),
        (('--params-file', 'p.yaml'), '--params-file p.yaml', ': --ros-args --params-file p.yaml'),
        (('--ros-args', '-p', 'threshold:=0.8', '--', 'x', 'y'), 'x y', 'e.g.'),
    ],
    ids=['bogus-flag', 'missing-ros-args', 'params-file-outside', 'after-double-dash'],
)
def test_unrecognised_arguments_are_refused(
    script: str, args: tuple[str, ...], shown: str, hint: str
) -> None:
    _, example = SCRIPTS[script]
    done = _call(script, *args)
    assert done.returncode == EXIT_BAD_START, done.stdout + done.stderr
    assert done.stdout == ''
    (line,) = done.stderr.splitlines()
    assert line.startswith(
        f'{script}: error: unrecognised argument(s): {shown} (ROS arguments go after --ros-args'
    ), line
    assert hint.format(example=example) in line and line.endswith(')'), line


def test_bad_ros_arguments_are_still_reported_by_rcl() -> None:
    # Left to rclpy.init, whose message names the fault (test_node_process for cva-node).
    assert check_arguments(['cva-node', '--ros-args', '-p']) is None
    assert check_arguments(['cva-node', '--ros-args', '--no-such-flag', '--', '--bogus']) is None
    done = _call('cva-cloud-filter', '--ros-args', '--no-such-flag')
    assert done.returncode == EXIT_BAD_START
    assert 'cannot start' in done.stderr and '--no-such-flag' in done.stderr
    assert 'unrecognised argument' not in done.stderr


def test_ros_arguments_alone_are_not_checked_further() -> None:
    assert check_arguments(['cva-node']) is None
    assert check_arguments([]) is None
    assert check_arguments(['node', '--ros-args', '-r', '__node:=x', '-p', 'a:=1', '--']) is None


def _run_until_ready(script: str, *ros_args: str) -> str:
    """Start ``script --ros-args ros_args``, wait for its ready line, stop it with Ctrl-C
    (exit status 0); its output."""
    proc = subprocess.Popen(
        [str(_script(script)), '--ros-args', *ros_args],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=_env(),
    )  # fmt: skip
    lines: list[str] = []
    try:
        assert proc.stdout is not None
        deadline = time.monotonic() + 120.0
        while not any('ready:' in line for line in lines):
            assert time.monotonic() < deadline and proc.poll() is None, ''.join(lines)
            lines.append(proc.stdout.readline())
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=30) == 0, ''.join(lines)
        lines.extend(proc.stdout.readlines())
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    return ''.join(lines)


@pytest.mark.parametrize(
    ('script', 'parameters', 'ready'),
    [
        ('cva-cloud-filter', 'threshold: 0.65', 'threshold=0.65'),
        # Integers for doubles, as people write them (-p x:=2, a YAML 2): taken as numbers.
        ('cva-cloud-filter', 'threshold: 1', 'threshold=1.0'),
        (
            'cva-node',
            'confidence_method: mlm\n    max_disparity: 16\n    max_rate_hz: 2\n'
            '    confidence_threshold: 0',
            'confidence_method=mlm',
        ),
    ],
)
def test_launch_style_ros_arguments_start_the_node(
    script: str, parameters: str, ready: str, tmp_path: Path
) -> None:
    # What ros2 launch passes: node name and namespace remapped, a parameter file.
    params = tmp_path / 'params.yaml'
    params.write_text(f'/**:\n  ros__parameters:\n    {parameters}\n')
    name = f'argtest_{script.replace("-", "_")}'
    output = _run_until_ready(
        script, '-r', f'__node:={name}', '-r', f'__ns:=/argtest_{os.getpid()}',
        '--params-file', str(params),
    )  # fmt: skip
    lines = output.splitlines()
    (line,) = [line for line in lines if 'ready:' in line]
    # The logger is named <namespace>.<node name>.
    assert f'.{name}]: ready:' in line and ready in line, output
    assert 'Traceback' not in output and 'unrecognised' not in output, output


@pytest.mark.parametrize(
    ('script', 'typo', 'meant'),
    [
        ('cva-cloud-filter', 'treshold', 'threshold'),
        ('cva-lifecycle-node', 'confidence_treshold', 'confidence_threshold'),
    ],
)
def test_a_misspelt_parameter_is_a_warning_with_the_name_meant(
    script: str, typo: str, meant: str, tmp_path: Path
) -> None:
    # Was ignored without a word: the node ran with the default. A warning, not a refusal: a
    # parameter file's /** section is for every node (other_nodes_gain, no suggestion).
    params = tmp_path / 'params.yaml'
    params.write_text('/**:\n  ros__parameters:\n    other_nodes_gain: 3\n')
    output = _run_until_ready(script, '-p', f'{typo}:=0.8', '--params-file', str(params))
    (line,) = [line for line in output.splitlines() if 'does not have' in line]
    assert '[WARN]' in line, output
    assert f'{typo} (did you mean {meant}?)' in line and 'other_nodes_gain' in line, output
    assert 'other_nodes_gain (did' not in line and 'qos_overrides' not in line, output
    # Declared names (use_sim_time is rclpy's own) draw no warning.
    output = _run_until_ready(script, '-p', f'{meant}:=0.8', '-p', 'use_sim_time:=false')
    assert 'does not have' not in output, output


def test_a_bad_qos_override_stops_the_start_with_one_line() -> None:
    # ROS 2's per-topic QoS overrides (test_qos_overrides): a value rclpy cannot use is named
    # with its topic, exit status 2, no traceback.
    done = _call('cva-cloud-filter', '--ros-args',
                 '-p', 'qos_overrides./points2.subscription.reliability:=sometimes')
    assert done.returncode == EXIT_BAD_START, done.stdout + done.stderr
    assert 'cannot start: QoS override of /points2' in done.stderr
    assert 'sometimes' in done.stderr and 'Traceback' not in done.stderr


def test_params_files_that_cannot_be_opened_are_named(tmp_path: Path) -> None:
    good = tmp_path / 'good.yaml'
    good.write_text('/**:\n  ros__parameters:\n    max_disparity: 64\n')
    missing = tmp_path / 'missing.yaml'
    locked = tmp_path / 'locked.yaml'
    locked.write_text('{}\n')
    locked.chmod(0)
    args = ['node', '--ros-args', '--params-file', str(good), '--params-file', str(missing),
            '--params-file', str(tmp_path), '--params-file', str(locked)]
    problems = params_file_problems(args)
    expected = [f'--params-file {missing}: no such file',
                f'--params-file {tmp_path}: is a folder, not a YAML file']
    if not os.access(locked, os.R_OK):  # root reads anything
        expected.append(f'--params-file {locked}: not readable (permission denied)')
    assert problems == expected
    # Outside --ros-args the words are not ROS arguments (check_arguments refuses them).
    assert params_file_problems(['node', '--params-file', str(missing)]) == []
    assert params_file_problems(['node', '--ros-args', '--', '--params-file', str(missing)]) == []
    assert params_file_problems(['node', '--ros-args', '--params-file', str(good)]) == []

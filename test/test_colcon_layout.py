"""The package builds with colcon into the layout ``ros2 run`` uses, and pip gets cva-* names.

``ros2 run cva_confidence_ros node`` looks up the package in the ament index and runs
``<prefix>/lib/cva_confidence_ros/node``. ros2cli is not installable here, so this test checks
that layout after a real ``colcon build`` of a copy of the sources in ``tmp_path`` and starts
the installed executable as ``ros2 run`` would (with the environment ``install/setup.sh``
gives). The same sources built as a wheel must not put a plain ``node`` on ``PATH``.
"""

from __future__ import annotations

import ast
import os
from pathlib import Path
import shutil
import signal
import subprocess
import sys
import threading
import time
import zipfile

import pytest

PACKAGE = 'cva_confidence_ros'
ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
_SKIP_DIRS = {'.venv', '.git', 'build', 'install', 'log', 'out', 'runs', '__pycache__', 'dist'}


def _copy_sources(target: Path) -> None:
    """Copy the package sources (not the venv or build outputs) to ``target``."""

    def ignore(directory: str, names: list[str]) -> set[str]:
        return {
            name
            for name in names
            if name in _SKIP_DIRS or name.endswith(('.egg-info', '.pyc')) or name.startswith('.')
        }

    shutil.copytree(ROOT, target, ignore=ignore)


def _site_packages(prefix: Path) -> Path:
    return (
        prefix
        / 'lib'
        / f'python{sys.version_info.major}.{sys.version_info.minor}'
        / ('site-packages')
    )


@pytest.fixture(scope='module')
def workspace(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A colcon workspace with the package built into ``install/`` (built once per module)."""
    colcon = BIN / 'colcon'
    if not colcon.exists():
        pytest.skip('colcon is not installed in this environment (make setup installs it)')
    ws = tmp_path_factory.mktemp('colcon_ws')
    _copy_sources(ws / 'src' / PACKAGE)
    env = dict(os.environ, COLCON_HOME=str(ws / 'colcon_home'))
    env.pop('COLCON_PREFIX_PATH', None)
    done = subprocess.run(
        [str(colcon), '--log-base', 'log', 'build', '--base-paths', 'src'],
        cwd=ws,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, f'colcon build failed:\n{done.stdout}\n{done.stderr}'
    return ws


@pytest.fixture(scope='module')
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A wheel of the package built by pip from a copy of the sources."""
    tmp = tmp_path_factory.mktemp('wheel')
    _copy_sources(tmp / 'src')
    done = subprocess.run(
        [
            sys.executable,
            '-m',
            'pip',
            'wheel',
            '-q',
            '--no-deps',
            '--no-build-isolation',
            '-w',
            str(tmp / 'dist'),
            str(tmp / 'src'),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, f'pip wheel failed:\n{done.stdout}\n{done.stderr}'
    (path,) = (tmp / 'dist').glob('*.whl')
    return path


def test_colcon_install_layout(workspace: Path) -> None:
    prefix = workspace / 'install' / PACKAGE
    executable = prefix / 'lib' / PACKAGE / 'node'
    assert executable.is_file()
    assert os.access(executable, os.X_OK)
    scripts = {path.name for path in (prefix / 'lib' / PACKAGE).iterdir()}
    assert {'node', 'lifecycle_node', 'lifecycle', 'cloud_filter', 'train', 'evaluate', 'table1',
            'benchmark', 'demo', 'bag_replay', 'mask'} <= scripts
    assert not any(name.startswith('cva-') for name in scripts)
    assert not (prefix / 'bin').exists()
    marker = prefix / 'share' / 'ament_index' / 'resource_index' / 'packages' / PACKAGE
    assert marker.is_file()
    share = prefix / 'share' / PACKAGE
    assert (share / 'package.xml').read_text() == (ROOT / 'package.xml').read_text()
    assert (share / 'launch' / 'cva_confidence.launch.py').is_file()
    assert (share / 'config' / 'cva_confidence.yaml').is_file()
    assert (share / 'config' / 'cva_confidence.rviz').is_file()
    assert (_site_packages(prefix) / PACKAGE / 'node.py').is_file()
    assert (_site_packages(prefix) / PACKAGE / 'py.typed').is_file()


def test_launch_file_is_valid_python_that_runs_node(workspace: Path) -> None:
    path = workspace / 'install' / PACKAGE / 'share' / PACKAGE / 'launch'
    source = (path / 'cva_confidence.launch.py').read_text()
    tree = ast.parse(source)
    compile(tree, 'cva_confidence.launch.py', 'exec')
    functions = {node.name for node in ast.walk(tree) if isinstance(node, ast.FunctionDef)}
    assert 'generate_launch_description' in functions
    strings = {n.value for n in ast.walk(tree) if isinstance(n, ast.Constant)}
    assert {PACKAGE, 'node', 'lifecycle_node', 'cva_confidence.yaml', 'config'} <= strings
    assert {'rviz', 'rviz_fixed_frame', 'rviz2', 'cva_confidence.rviz'} <= strings


def _ros2_run_env(prefix: Path) -> dict[str, str]:
    env = dict(os.environ)
    # What sourcing install/setup.sh does for this package.
    env['PYTHONPATH'] = os.pathsep.join(
        p for p in (str(_site_packages(prefix)), env.get('PYTHONPATH', '')) if p
    )
    env['AMENT_PREFIX_PATH'] = os.pathsep.join(
        p for p in (str(prefix), env.get('AMENT_PREFIX_PATH', '')) if p
    )
    # The node tests' scheme (test/ros/node_test_utils.domain_id) with offset 3.
    env['ROS_DOMAIN_ID'] = str(101 + (os.getpid() % 30) * 4 + 3)
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env['PYTHONUNBUFFERED'] = '1'
    return env


def test_ros2_run_executable_comes_up_and_stops_on_sigint(workspace: Path) -> None:
    prefix = workspace / 'install' / PACKAGE
    env = _ros2_run_env(prefix)
    # With the install's environment the installed copy is imported, not the source tree.
    where = subprocess.run(
        [sys.executable, '-c', 'import cva_confidence_ros.node as m; print(m.__file__)'],
        env=env,
        cwd=workspace,
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    assert Path(where.stdout.strip()).is_relative_to(prefix)
    command = [
        str(prefix / 'lib' / PACKAGE / 'node'),
        '--ros-args',
        '--params-file',
        str(prefix / 'share' / PACKAGE / 'config' / 'cva_confidence.yaml'),
        '-p',
        'confidence_method:=mlm',
        '-p',
        'max_disparity:=16',
    ]
    process = subprocess.Popen(
        command,
        env=env,
        cwd=workspace,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    lines: list[str] = []
    ready = threading.Event()

    def read() -> None:
        assert process.stdout is not None
        for line in process.stdout:
            lines.append(line)
            if 'ready:' in line:
                ready.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        deadline = time.monotonic() + 90
        while not ready.wait(0.2):
            if process.poll() is not None or time.monotonic() > deadline:
                pytest.fail('no ready line; output:\n' + ''.join(lines))
        time.sleep(0.5)
        process.send_signal(signal.SIGINT)
        code = process.wait(30)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait(10)
    reader.join(10)
    output = ''.join(lines)
    assert code == 0, output
    assert 'Traceback' not in output, output
    assert 'matcher=census_bm max_disparity=16 confidence_method=mlm' in output


def test_pip_wheel_has_only_cva_prefixed_scripts(wheel: Path) -> None:
    with zipfile.ZipFile(wheel) as archive:
        (entry_points,) = [n for n in archive.namelist() if n.endswith('entry_points.txt')]
        text = archive.read(entry_points).decode()
        names = set(archive.namelist())
    scripts = [line.split('=')[0].strip() for line in text.splitlines() if '=' in line]
    assert 'cva-node' in scripts
    assert all(name.startswith('cva-') for name in scripts), scripts
    assert not any(n.rsplit('/', 1)[-1] == 'node' and '/scripts/' in n for n in names)
    data = f'{PACKAGE}-0.1.0.data/data/share'
    assert f'{data}/ament_index/resource_index/packages/{PACKAGE}' in names
    assert f'{data}/{PACKAGE}/config/cva_confidence.yaml' in names
    assert f'{data}/{PACKAGE}/config/cva_confidence.rviz' in names


def test_installed_environment_has_cva_node_and_no_plain_node() -> None:
    from importlib import metadata

    try:
        distribution = metadata.distribution(PACKAGE)
    except metadata.PackageNotFoundError:
        pytest.skip('the package is not pip-installed here (make setup installs it)')
    scripts = [ep.name for ep in distribution.entry_points if ep.group == 'console_scripts']
    if 'node' in scripts:
        pytest.skip('this environment runs from a colcon install, which uses ROS names')
    assert 'cva-node' in scripts
    assert (BIN / 'cva-node').is_file()
    assert not (BIN / 'node').exists()

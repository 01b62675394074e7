"""Deployment on robots: a read-only install, no writable home, a CPU quota (review 35).

Root ignores permission bits, so "not writable" is made here by a regular file where a folder
should be (``__pycache__``, ``$HOME``): no one can create a folder inside a file.
"""

from __future__ import annotations

import os
from pathlib import Path
import shutil
import subprocess
import sys
import types

import numpy as np
import pytest

import cva_confidence_ros
from cva_confidence_ros import node
from cva_confidence_ros.ros import confidence_node

PACKAGE = Path(cva_confidence_ros.__file__).resolve().parent


def _read_only_install(tmp_path: Path) -> tuple[Path, dict[str, str]]:
    """A copy of the package whose ``__pycache__`` folders cannot be made, and an environment
    whose home and cache folders cannot be made either."""
    site = tmp_path / 'site'
    shutil.copytree(
        PACKAGE, site / PACKAGE.name, ignore=shutil.ignore_patterns('__pycache__', '*.nb*')
    )
    for init in (site / PACKAGE.name).rglob('__init__.py'):
        (init.parent / '__pycache__').write_text('not a folder')
    blocker = tmp_path / 'blocker'
    blocker.write_text('a file')
    env = {k: v for k, v in os.environ.items() if k not in ('NUMBA_CACHE_DIR', 'PYTHONPATH')}
    env.update(
        PYTHONPATH=str(site),
        PYTHONDONTWRITEBYTECODE='1',
        HOME=str(blocker / 'home'),
        XDG_CACHE_HOME=str(blocker / 'cache'),
        TMPDIR=str(tmp_path / 'tmp'),
        ROS_LOG_DIR=str(tmp_path / 'log'),
    )
    (tmp_path / 'tmp').mkdir()
    return site, env


def test_jit_cache_moves_to_the_temp_folder_when_package_and_home_are_read_only(
    tmp_path: Path,
) -> None:
    # Before, numba refused to define the kernels: RuntimeError: cannot cache function ...
    _, env = _read_only_install(tmp_path)
    script = (
        # The package's import sets it, before any kernel module (the library's and every
        # program's imports failed alike).
        'import os, cva_confidence_ros; folder = os.environ["NUMBA_CACHE_DIR"]; '
        'import cva_confidence_ros._scan_kernel as k; import numba; '
        'print(folder); print(numba.config.CACHE_DIR); print(k.__file__)'
    )
    done = subprocess.run(
        [sys.executable, '-c', script], env=env, cwd=tmp_path, capture_output=True, text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    folder, numba_dir, kernel_file = done.stdout.split()
    assert Path(folder).parent == tmp_path / 'tmp'
    assert numba_dir == folder
    assert Path(kernel_file).is_relative_to(tmp_path / 'site')
    assert (Path(folder).stat().st_mode & 0o077) == 0  # numba's cache files are pickles


def test_node_without_any_writable_cache_folder_says_so(tmp_path: Path) -> None:
    # Before: a RuntimeError traceback from numba deep in the node's imports.
    _, env = _read_only_install(tmp_path)
    script = (
        'import sys, tempfile; tempfile.tempdir = sys.argv[1]\n'
        'from cva_confidence_ros import node\n'
        'sys.exit(node.main(["cva-node"]))'
    )
    done = subprocess.run(
        [sys.executable, '-c', script, str(tmp_path / 'blocker' / 'tmp')],
        env=env, cwd=tmp_path, capture_output=True, text=True, timeout=120,
    )
    assert done.returncode == 2, done.stderr
    assert 'Traceback' not in done.stderr
    assert 'cannot start: no writable folder for the compiled numba kernels' in done.stderr
    assert 'NUMBA_CACHE_DIR' in done.stderr


def test_jit_cache_leaves_a_user_choice_and_a_writable_package_alone(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setenv('NUMBA_CACHE_DIR', str(tmp_path))
    assert node.ensure_jit_cache() is None
    monkeypatch.delenv('NUMBA_CACHE_DIR')
    assert node.ensure_jit_cache() is None  # the checkout's own __pycache__ is writable
    assert 'NUMBA_CACHE_DIR' not in os.environ


def _cgroup_v2(tmp_path: Path, cpu_max: str, parent: str = 'max') -> tuple[Path, Path]:
    root = tmp_path / 'cgroup'
    (root / 'robot' / 'node').mkdir(parents=True)
    (root / 'cpu.max').write_text('max 100000\n')
    (root / 'robot' / 'cpu.max').write_text(f'{parent}\n')
    (root / 'robot' / 'node' / 'cpu.max').write_text(f'{cpu_max}\n')
    proc = tmp_path / 'proc_cgroup'
    proc.write_text('0::/robot/node\n')
    return root, proc


@pytest.fixture
def eight_cpus(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(os, 'sched_getaffinity', lambda pid: set(range(8)))
    for name in node.THREAD_VARIABLES:
        monkeypatch.delenv(name, raising=False)


@pytest.mark.usefixtures('eight_cpus')
def test_threads_follow_a_cgroup_v2_quota(tmp_path: Path) -> None:
    # docker run --cpus 2.5 on an 8-core host: torch and numba ran 8 threads each.
    root, proc = _cgroup_v2(tmp_path, '250000 100000')
    assert node.cpu_quota(root, proc) == 2.5
    assert node.match_threads_to_cpu_quota(root, proc) == 2
    assert os.environ['OMP_NUM_THREADS'] == os.environ['NUMBA_NUM_THREADS'] == '2'


@pytest.mark.usefixtures('eight_cpus')
def test_threads_follow_the_smallest_quota_and_keep_a_user_setting(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    root, proc = _cgroup_v2(tmp_path, 'max 100000', parent='50000 100000')
    monkeypatch.setenv('OMP_NUM_THREADS', '3')
    assert node.match_threads_to_cpu_quota(root, proc) == 1  # half a CPU: one thread
    assert os.environ['OMP_NUM_THREADS'] == '3'
    assert os.environ['NUMBA_NUM_THREADS'] == '1'


@pytest.mark.usefixtures('eight_cpus')
def test_threads_follow_a_cgroup_v1_quota_and_not_a_larger_one(tmp_path: Path) -> None:
    root = tmp_path / 'cgroup'
    folder = root / 'cpu,cpuacct' / 'docker' / 'abc'
    folder.mkdir(parents=True)
    (folder / 'cpu.cfs_quota_us').write_text('300000\n')
    (folder / 'cpu.cfs_period_us').write_text('100000\n')
    proc = tmp_path / 'proc_cgroup'
    proc.write_text('4:memory:/docker/abc\n2:cpu,cpuacct:/docker/abc\n')
    assert node.match_threads_to_cpu_quota(root, proc) == 3
    for name in node.THREAD_VARIABLES:
        del os.environ[name]
    (folder / 'cpu.cfs_quota_us').write_text('1600000\n')  # 16 CPUs of quota, 8 cores
    assert node.match_threads_to_cpu_quota(root, proc) is None
    (folder / 'cpu.cfs_quota_us').write_text('-1\n')
    assert node.cpu_quota(root, proc) is None
    assert 'OMP_NUM_THREADS' not in os.environ


def test_run_entry_sets_cache_and_threads_before_importing_the_node(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    calls: list[str] = []
    monkeypatch.setattr(node, 'ensure_jit_cache', lambda: calls.append('cache'))
    monkeypatch.setattr(node, 'match_threads_to_cpu_quota', lambda: calls.append('threads'))
    fake = types.ModuleType('review35_fake_node')
    fake.run = lambda argv: calls.append('run') or 0  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, fake.__name__, fake)
    assert node.run_entry(fake.__name__, ['cva-node']) == 0
    assert calls == ['cache', 'threads', 'run']


def test_node_start_up_compiles_the_scan_kernel(monkeypatch: pytest.MonkeyPatch) -> None:
    # The scan kernel was left to the first frame a scan subscriber got (≈ 0.3 s, cold cache).
    import rclpy
    from rclpy.context import Context
    from rclpy.parameter import Parameter

    from cva_confidence_ros._scan_kernel import scan_kernel
    from cva_confidence_ros.pointcloud import StereoGeometry
    from cva_confidence_ros.scan import disparity_to_scan

    warmed: list[bool] = []
    real = confidence_node._warm_up_scan
    monkeypatch.setattr(confidence_node, '_warm_up_scan', lambda: warmed.append(True) or real())
    context = Context()
    rclpy.init(context=context, domain_id=221 + os.getpid() % 10)
    try:
        made = confidence_node.ConfidenceNode(
            context=context,
            parameter_overrides=[
                Parameter('max_disparity', value=16),
                Parameter('confidence_method', value='pkrn'),
            ],
        )
        made.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
    assert warmed == [True]
    # What a frame then passes (float32 disparity, a bool mask, float32 confidence) is the
    # signature the warm-up compiled: nothing new to compile.
    compiled = len(scan_kernel.signatures)
    disparity = np.full((6, 8), 2.0, np.float32)
    geometry = StereoGeometry(fx=4.0, fy=4.0, cx=4.0, cy=3.0, cx_right=4.0, baseline=0.1)
    disparity_to_scan(disparity, geometry, disparity > 1, np.ones_like(disparity))
    assert len(scan_kernel.signatures) == compiled


@pytest.mark.parametrize('layout', ['target', 'prefix'])
def test_shipped_weights_are_found_beside_a_target_or_prefix_install(
    tmp_path: Path, layout: str
) -> None:
    # pip install --target DIR puts the models in DIR/share/..., --user / --prefix in
    # <prefix>/share/...; both were searched only under sys.prefix ('no shipped ... weights').
    site = tmp_path / 'target' if layout == 'target' else tmp_path / 'lib/python3/site-packages'
    shutil.copytree(
        PACKAGE, site / PACKAGE.name, ignore=shutil.ignore_patterns('__pycache__', '*.nb*')
    )
    share = (site if layout == 'target' else tmp_path) / 'share' / PACKAGE.name / 'models'
    share.mkdir(parents=True)
    (share / 'cvanet_fast_census_bm_d64.pt').write_bytes(b'stand-in')
    env = {k: v for k, v in os.environ.items() if k != 'PYTHONPATH'}
    env.update(PYTHONPATH=str(site), PYTHONDONTWRITEBYTECODE='1')
    script = (
        'from cva_confidence_ros.model.weights import default_weights_path; '
        "print(default_weights_path('census_bm', 64, 'cvanet_fast'))"
    )
    done = subprocess.run(
        [sys.executable, '-c', script], env=env, cwd=tmp_path, capture_output=True, text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    assert Path(done.stdout.strip()) == share / 'cvanet_fast_census_bm_d64.pt'

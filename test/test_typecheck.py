"""The package type-checks (mypy over what ``setup.cfg`` names: the package and msg_tools) and
passes ruff, as ``make lint`` checks."""

from __future__ import annotations

import configparser
from pathlib import Path
import shutil
import subprocess
import sys

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_package_passes_mypy(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    api = pytest.importorskip('mypy.api')
    config = configparser.ConfigParser()
    config.read(ROOT / 'setup.cfg')
    files = [f.strip() for f in config['mypy']['files'].split(',') if f.strip()]
    assert files == ['cva_confidence_ros', 'msg_tools']
    monkeypatch.chdir(ROOT)
    out, err, code = api.run(['--cache-dir', str(tmp_path / 'cache')])
    assert code == 0, out + err
    assert 'Success: no issues found' in out


def test_sources_pass_ruff() -> None:
    # What `make lint` checks, so that a long line cannot land between two lint runs.
    ruff = Path(sys.executable).parent / 'ruff'
    command = str(ruff) if ruff.exists() else shutil.which('ruff')
    if command is None:
        pytest.skip('ruff is not installed (make setup installs it)')
    done = subprocess.run(
        [command, 'check', 'cva_confidence_ros', 'msg_tools', 'test'],
        cwd=ROOT, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr

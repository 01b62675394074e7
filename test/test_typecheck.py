"""The package type-checks: mypy over what ``setup.cfg`` names (the package and msg_tools)."""

from __future__ import annotations

import configparser
from pathlib import Path

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

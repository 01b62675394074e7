"""The core type-checks: mypy over the files ``setup.cfg`` names (no rclpy among them)."""

from __future__ import annotations

import configparser
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_core_passes_mypy(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    api = pytest.importorskip('mypy.api')
    config = configparser.ConfigParser()
    config.read(ROOT / 'setup.cfg')
    files = [f.strip() for f in config['mypy']['files'].split(',') if f.strip()]
    assert 'cva_confidence_ros/model' in files and 'cva_confidence_ros/pipeline.py' in files
    monkeypatch.chdir(ROOT)
    out, err, code = api.run(['--cache-dir', str(tmp_path / 'cache')])
    assert code == 0, out + err
    assert 'Success: no issues found' in out

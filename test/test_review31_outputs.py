"""Review 31: an empty output folder (an unset shell variable) is refused, not taken as the
current folder."""

from __future__ import annotations

from pathlib import Path

import pytest

from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.outputs import check_output_dir


def test_an_empty_output_folder_is_refused(tmp_path: Path,
                                           monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ConfigError, match=r"^--out is empty; give a folder \('\.' for the "
                                          r"current one\)$"):
        check_output_dir('', '--out')
    assert check_output_dir('.', '--out') == Path('.')
    assert list(tmp_path.iterdir()) == []


def test_cva_demo_refuses_an_empty_out(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from cva_confidence_ros.demo import main

    monkeypatch.chdir(tmp_path)

    # Before: the demo wrote its bags, reports and PNGs into the current folder.
    with pytest.raises(SystemExit) as stopped:
        main(['--out', ''])
    assert stopped.value.code == 2
    assert "cva-demo: error: --out is empty; give a folder ('.' for" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []

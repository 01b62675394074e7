"""Output paths are tried before a job starts: a path that cannot be written fails at once."""

from __future__ import annotations

from pathlib import Path

import pytest

from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.outputs import check_output_dir, check_output_file

# procfs refuses new entries to every user, root included, whom os.access would let through.
UNWRITABLE = Path('/proc/cva-confidence-ros-probe')


def test_folders_are_made_and_left_without_probe_files(tmp_path: Path) -> None:
    out = check_output_dir(tmp_path / 'a' / 'b', '--out')
    assert out.is_dir() and list(out.iterdir()) == []
    target = check_output_file(tmp_path / 'c' / 'records.json', '--json')
    assert target.parent.is_dir() and not target.exists()
    assert list(target.parent.iterdir()) == []


@pytest.mark.skipif(not Path('/proc/self').exists(), reason='needs procfs')
def test_a_place_that_cannot_be_written_fails_before_any_work() -> None:
    with pytest.raises(ConfigError, match=f'^--out {UNWRITABLE}: cannot write in {UNWRITABLE}'):
        check_output_dir(UNWRITABLE, '--out')
    with pytest.raises(ConfigError, match='^--json .*records.json: cannot write in'):
        check_output_file(UNWRITABLE / 'records.json', '--json')
    with pytest.raises(ConfigError, match='^--weights-out /proc/w.pt: cannot write in /proc'):
        check_output_file('/proc/w.pt', '--weights-out')


def test_files_and_folders_in_the_way_are_named(tmp_path: Path) -> None:
    afile = tmp_path / 'afile'
    afile.write_text('x')
    with pytest.raises(ConfigError, match='is a file; expected a folder'):
        check_output_dir(afile, '--out')
    with pytest.raises(ConfigError, match=f'{afile} is a file, not a folder'):
        check_output_dir(afile / 'sub', '--out')
    with pytest.raises(ConfigError, match='is a folder; expected a file path'):
        check_output_file(tmp_path, '--json')

"""Review 32 of the ``cva-bag-replay`` command line: options checked as the node checks them,
and one-line errors when ROS 2's Python packages are missing."""

from __future__ import annotations

import importlib.abc
from pathlib import Path
import sys

from msg_test_utils import MAX_DISPARITY, write_stereo_bag
import pytest

from msg_tools.bag_replay import main


def _argv(bag: Path, tmp_path: Path, *extra: str) -> list[str]:
    return [
        str(bag), '--out', str(tmp_path / 'out'), '--report', str(tmp_path / 'report'),
        '--matcher', 'census_bm', '--confidence-method', 'pkrn', '--device', 'cpu',
        '--max-disparity', str(MAX_DISPARITY), *extra,
    ]


def test_scan_frame_id_with_leading_slash_is_refused_before_any_output(tmp_path, capsys):
    # The node refuses scan_frame_id '/base' (tf2 takes no such frame); offline mode wrote a
    # scan with it and exited 0.
    bag = write_stereo_bag(tmp_path / 'bag', [{}])
    code = main(_argv(bag, tmp_path, '--scan', '--scan-frame-id', '/base_link'))
    err = capsys.readouterr().err
    assert code == 2
    assert "--scan-frame-id must not start with '/'" in err and "'/base_link'" in err
    assert len(err.strip().splitlines()) == 1
    assert not (tmp_path / 'out').exists() and not (tmp_path / 'report').exists()


class _NoRclpy(importlib.abc.MetaPathFinder):
    """A Python without rclpy: importing it fails as in a shell where ROS 2 is not sourced."""

    def find_spec(self, name, path=None, target=None):
        if name == 'rclpy' or name.startswith('rclpy.'):
            raise ModuleNotFoundError(f'No module named {name!r}', name=name)
        return None


@pytest.mark.parametrize('mode', ['offline', 'live'])
def test_missing_rclpy_is_one_line_exit_2_and_keeps_the_old_report(
    tmp_path, capsys, monkeypatch, mode
):
    bag = write_stereo_bag(tmp_path / 'bag', [{}])
    report = tmp_path / 'report'
    report.mkdir()
    (report / 'report.json').write_text('{}')  # an earlier report, for --overwrite
    for name in [n for n in sys.modules if n == 'rclpy' or n.startswith('rclpy.')]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.delitem(sys.modules, 'cva_confidence_ros.ros.params', raising=False)
    monkeypatch.setattr(sys, 'meta_path', [_NoRclpy(), *sys.meta_path])
    code = main(_argv(bag, tmp_path, '--mode', mode, '--overwrite'))
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith('cva-bag-replay: error: ROS 2 Python package missing')
    assert "'rclpy" in err and 'Traceback' not in err
    assert len(err.strip().splitlines()) == 1
    assert (report / 'report.json').read_text() == '{}'
    assert not (tmp_path / 'out').exists()


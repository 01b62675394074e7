"""Review 30: a live replay refuses options the node it starts would refuse, before the old
report goes."""

from __future__ import annotations

from pathlib import Path

from msg_test_utils import MAX_DISPARITY, write_stereo_bag
import pytest

from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.ros.params import check_declared_ranges
from msg_tools.bag_replay import main
from msg_tools.live import node_arguments
from msg_tools.replay import ReplayOptions


def test_node_arguments_refuse_values_outside_the_nodes_declared_ranges(tmp_path: Path) -> None:
    # The replay took any tolerance up to the int64 span and any queue size; the node it
    # starts declares [0, 10] s and [1, 1000] and ended its start-up on them.
    common = dict(bag=tmp_path / 'in', out=tmp_path / 'out', report=tmp_path / 'report',
                  mode='live')
    options = ReplayOptions(**common, approximate_sync=True, sync_tolerance_s=60.0)
    with pytest.raises(ConfigError, match=r'^approximate_sync_tolerance_seconds must be in '
                       r'\[0, 10\] \(the range the node declares\); got 60\.0'):
        node_arguments(options, 'replayed')
    with pytest.raises(ConfigError, match=r'^queue_size must be in \[1, 1000\].*got 5000'):
        node_arguments(ReplayOptions(**common, queue_size=5000), 'replayed')
    assert node_arguments(ReplayOptions(**common, queue_size=1000), 'replayed')
    check_declared_ranges({'queue_size': 10, 'max_disparity': 64, 'publish_points': True})


def test_a_live_replay_refuses_them_before_the_old_report_goes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = write_stereo_bag(tmp_path / 'in', [{}, {}])
    report = tmp_path / 'report'
    report.mkdir()
    (report / 'report.json').write_text('{"old": true}')
    code = main([
        str(bag), '--mode', 'live', '--out', str(tmp_path / 'out'), '--report', str(report),
        '--max-disparity', str(MAX_DISPARITY), '--confidence-method', 'pkrn',
        '--queue-size', '5000', '--overwrite',
    ])
    err = capsys.readouterr().err
    assert code == 2, err
    assert 'queue_size must be in [1, 1000]' in err
    assert 'Traceback' not in err
    assert (report / 'report.json').read_text() == '{"old": true}'
    assert not (tmp_path / 'out').exists()

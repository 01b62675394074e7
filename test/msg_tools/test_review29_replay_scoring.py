"""Review fixes of the replay engine: two inputs (or an input and the ground truth) on one
topic are refused by name; a full disk that keeps the output bag from being finished still
leaves the report of the frames done; a report folder that cannot be written stops the run
with its reason, recorded in the report, instead of a traceback."""

from __future__ import annotations

from collections.abc import Callable
import json
from pathlib import Path
from typing import Any

from msg_test_utils import MAX_DISPARITY, read_bag, textured_pair, write_stereo_bag
import pytest

from cva_confidence_ros.errors import ConfigError
from msg_tools.bag_replay import main
from msg_tools.replay import TopicNames


@pytest.mark.parametrize(('fields', 'message'), [
    ({'ground_truth': 'left/image_rect'}, 'topics left and ground_truth are both'),
    ({'right': '/left/image_rect'}, 'topics left and right are both'),
    ({'prefix': '/cam', 'left_info': 'right/camera_info'},
     "topics left_info and right_info are both '/cam/right/camera_info'"),
])
def test_inputs_on_one_topic_are_refused(fields: dict[str, str], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        TopicNames(**fields)


def test_ground_truth_on_the_left_image_topic_is_named(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = write_stereo_bag(tmp_path / 'in', [{}, {}])
    code = main([
        str(bag), '--out', str(tmp_path / 'out'), '--report', str(tmp_path / 'report'),
        '--max-disparity', str(MAX_DISPARITY), '--confidence-method', 'pkrn',
        '--gt-topic', 'left/image_rect',
    ])
    err = capsys.readouterr().err
    # Before: the left images were all read as ground truth, and the run ended with 'no stereo
    # pair matched by stamp: ... must share header stamps' and a report of nothing.
    assert code == 2
    assert err.strip().splitlines()[-1] == (
        "cva-bag-replay: error: topics left and ground_truth are both '/left/image_rect'; "
        'every input (and the ground truth) needs a topic of its own'
    )
    assert not (tmp_path / 'out').exists() and not (tmp_path / 'report').exists()


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_a_bag_that_cannot_be_finished_keeps_the_report(
    tmp_path: Path, storage: str, capsys: pytest.CaptureFixture[str],
    file_size_limit: Callable[[int], Any],
) -> None:
    frames = [dict(zip(('left', 'right'), textured_pair(60, 80, 4, i), strict=True))
              for i in range(6)]
    bag = write_stereo_bag(tmp_path / 'in', frames)
    report = tmp_path / 'report'
    with file_size_limit(150_000):  # the output bag outgrows it; the report files do not
        code = main([
            str(bag), '--out', str(tmp_path / 'out'), '--report', str(report),
            '--max-disparity', str(MAX_DISPARITY), '--confidence-method', 'pkrn',
            '--storage', storage, '--max-plots', '0',
        ])
    err = capsys.readouterr().err
    assert 'Traceback' not in err
    line = err.strip().splitlines()[-1]
    assert code == 2
    assert line.startswith('cva-bag-replay: error: ') and 'cannot finish output bag' in line
    # Before: the error came out of closing the bag before the report was written, so the
    # report folder stayed empty and the frames' scores were lost.
    document = json.loads((report / 'report.json').read_text())
    summary = document['summary']
    assert 'cannot finish output bag' in summary['error']
    assert summary['processed'] > 0 and len(document['frames']) == summary['processed']
    assert all(frame['auc'] is not None for frame in document['frames'])
    assert f"{summary['processed']} frames were done before" in line
    assert (report / 'summary.md').is_file() and (report / 'report.csv').is_file()


def test_a_full_report_folder_stops_the_run_with_its_reason(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import errno

    import cva_confidence_ros.plots as plots

    bag = write_stereo_bag(tmp_path / 'in', [{}, {}, {}])
    drawn = plots.save_confidence_map

    def full_after_one(confidence: Any, path: Path, *args: Any) -> Path:
        if Path(path).name != 'confidence_00000.png':
            raise OSError(errno.ENOSPC, 'No space left on device')
        return drawn(confidence, path, *args)

    monkeypatch.setattr(plots, 'save_confidence_map', full_after_one)
    report = tmp_path / 'report'
    code = main([
        str(bag), '--out', str(tmp_path / 'out'), '--report', str(report),
        '--max-disparity', str(MAX_DISPARITY), '--confidence-method', 'pkrn',
    ])
    err = capsys.readouterr().err
    # Before: an OSError traceback, and a report.json that said the run ended normally.
    assert 'Traceback' not in err
    assert code == 2
    message = (f'cannot write the PNGs of frame 1 into the report folder {report}: OSError: '
               '[Errno 28] No space left on device')
    assert err.strip().splitlines()[-1] == f'cva-bag-replay: error: {message}'
    summary = json.loads((report / 'report.json').read_text())['summary']
    assert summary['error'] == message and summary['processed'] == 2
    assert len(read_bag(tmp_path / 'out')['/disparity']) == 2


def test_a_report_that_cannot_be_written_is_a_config_error(tmp_path: Path) -> None:
    from msg_tools.scoring import ReplayReport, ReportWriter

    writer = ReportWriter(tmp_path / 'report')
    (tmp_path / 'report' / 'report.json').mkdir()  # in the way, as a full disk would be
    # Before: IsADirectoryError out of the replay's end.
    with pytest.raises(ConfigError, match=f'cannot write the report file '
                                          f'{tmp_path / "report" / "report.json"}: '
                                          'IsADirectoryError'):
        writer.write(ReplayReport())

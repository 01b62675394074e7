"""Review fixes of the replay's counts and report: a message that cannot be deserialised is
counted as unreadable, not as a skipped pair (pairs = processed + skipped), and a frame whose
ground truth may be one of them says so; the messages still waiting for partners when a run
stops are listed with the count; a PNG that cannot be written for a frame scored at the end
still leaves the report."""

from __future__ import annotations

import errno
import json
import os
from pathlib import Path
import signal
from typing import Any

from msg_test_utils import MAX_DISPARITY, START_NS, read_bag, write_stereo_bag
import pytest

from msg_tools.bag_replay import main
from msg_tools.bagio import InputBag, OutputBag
from msg_tools.convert import jazzy_typestore

STEP = 100_000_000  # write_stereo_bag's frame spacing, ns


def _cut(source: Path, target: Path, cut: set[tuple[str, int]]) -> Path:
    """A copy of bag ``source`` whose messages (topic, bag time) in ``cut`` are cut short."""
    with InputBag(source) as src, OutputBag(target, 'mcap', jazzy_typestore()) as dst:
        for topic, msgtype, timestamp, raw in src.messages(list(src.topics)):
            data = bytes(raw)
            dst.write(topic, msgtype, data[:10] if (topic, timestamp) in cut else data,
                      timestamp)
    return target


def _replay(tmp_path: Path, bag: Path, *extra: str) -> tuple[int, str, dict[str, Any]]:
    code = main([
        str(bag), '--out', str(tmp_path / 'out'), '--report', str(tmp_path / 'report'),
        '--max-disparity', str(MAX_DISPARITY), '--confidence-method', 'pkrn', *extra,
    ])
    report = json.loads((tmp_path / 'report' / 'report.json').read_text())
    return code, (tmp_path / 'report' / 'summary.md').read_text(), report


def test_unreadable_messages_are_not_skipped_pairs(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = _cut(write_stereo_bag(tmp_path / 'raw', [{}, {}, {}]), tmp_path / 'in', {
        ('/ground_truth/disparity', START_NS + STEP),
        ('/left/image_rect', START_NS + 2 * STEP),
    })
    code, markdown, report = _replay(tmp_path, bag, '--max-plots', '0')
    out = capsys.readouterr().out
    summary = report['summary']
    assert code == 0
    # Before: skipped 2 beside 2 of 2 pairs processed ('2 of 2 frames processed, 2 skipped').
    assert (summary['pairs'], summary['processed'], summary['skipped']) == (2, 2, 0)
    assert summary['unreadable'] == 2
    assert '2 of 2 frames processed, 0 skipped' in out and '2 unreadable messages' in out
    assert 'Unreadable messages (cannot be deserialised, skipped): 2' in markdown
    # Before: 'no ground truth with this stamp in the bag', though the bag had it, unreadable.
    assert report['frames'][1]['note'] == (
        'no ground truth with this stamp in the bag (1 ground-truth message could not be read)'
    )


def test_no_pair_of_unreadable_images_says_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = _cut(write_stereo_bag(tmp_path / 'raw', [{}, {}]), tmp_path / 'in', {
        ('/left/image_rect', START_NS), ('/left/image_rect', START_NS + STEP),
    })
    code, _, report = _replay(tmp_path, bag)
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert code == 2
    assert (report['summary']['skipped'], report['summary']['unreadable']) == (0, 2)
    # Before: only 'no stereo pair matched by stamp ... must share header stamps'.
    assert 'no stereo pair matched by stamp' in line
    assert '; 2 input messages could not be read (see the messages above)' in line


def test_messages_waiting_at_ctrl_c_are_listed_with_the_count(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from msg_tools import replay

    # Frame 1 never pairs (its right side is 1 µs off): its four messages wait when the signal
    # comes, with frame 0's ground truth logged after them.
    bag = write_stereo_bag(tmp_path / 'in', [
        {'gt_lag': STEP + STEP // 2},
        {'stamp_right': START_NS + STEP + 1000, 'no_gt': True},
        {},
    ])
    add_ground_truth = replay.ReplaySession.add_ground_truth

    def signal_on_truth(session: replay.ReplaySession, stamp: int, msg: Any) -> None:
        if stamp == START_NS:
            os.kill(os.getpid(), signal.SIGINT)  # taken by the replay's own handler
        add_ground_truth(session, stamp, msg)

    monkeypatch.setattr(replay.ReplaySession, 'add_ground_truth', signal_on_truth)
    code, markdown, report = _replay(tmp_path, bag, '--max-plots', '0')
    summary = report['summary']
    assert code == 130 and summary['interrupted'] is True and summary['processed'] == 1
    # Before: unpaired 4, but unpaired_by_topic {} and no message listed.
    assert summary['unpaired'] == sum(summary['unpaired_by_topic'].values()) == 4
    assert len(report['unpaired']) == 4
    assert {m['reason'] for m in report['unpaired']} == {
        'still waiting for its partners when the run stopped'
    }
    assert 'Unpaired input messages: 4' in markdown


def test_a_png_error_at_the_end_still_writes_the_report(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import cva_confidence_ros.plots as plots

    # The last frame has no ground truth in the bag: it is scored (and drawn) only at the end.
    bag = write_stereo_bag(tmp_path / 'in', [{}, {}, {'no_gt': True}])
    drawn = plots.save_confidence_map

    def full_at_the_last(confidence: Any, path: Path, *args: Any) -> Path:
        if Path(path).name == 'confidence_00002.png':
            raise OSError(errno.ENOSPC, 'No space left on device')
        return drawn(confidence, path, *args)

    monkeypatch.setattr(plots, 'save_confidence_map', full_at_the_last)
    report = tmp_path / 'report'
    code = main([
        str(bag), '--out', str(tmp_path / 'out'), '--report', str(report),
        '--max-disparity', str(MAX_DISPARITY), '--confidence-method', 'pkrn',
    ])
    err = capsys.readouterr().err
    message = (f'cannot write the PNGs of frame 2 into the report folder {report}: OSError: '
               '[Errno 28] No space left on device')
    assert code == 2 and 'Traceback' not in err
    assert err.strip().splitlines()[-1] == f'cva-bag-replay: error: {message}'
    # Before: no report.json, report.csv or summary.md at all (only the earlier PNGs).
    document = json.loads((report / 'report.json').read_text())
    assert document['summary']['error'] == message
    assert [frame['frame'] for frame in document['frames']] == [0, 1, 2]
    assert (report / 'summary.md').is_file() and (report / 'report.csv').is_file()
    assert len(read_bag(tmp_path / 'out')['/disparity']) == 3

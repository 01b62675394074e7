"""``cva-bag-replay`` names what it could not use: unpaired input messages (topic, stamp, why)
and frames whose ground truth is unusable, on stderr (throttled) and in the report."""

from __future__ import annotations

import json
from pathlib import Path

from msg_test_utils import MAX_DISPARITY, START_NS, write_stereo_bag
import numpy as np
import pytest

from msg_tools.bag_replay import main

FRAME_NS = 100_000_000


def _run(
    bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], *extra: str
) -> tuple[int, str, str, dict]:
    code = main([
        str(bag), '--out', str(tmp_path / 'out'), '--report', str(tmp_path / 'report'),
        '--max-disparity', str(MAX_DISPARITY), '--confidence-method', 'pkrn', *extra,
    ])
    captured = capsys.readouterr()
    assert 'Traceback' not in captured.err
    report = json.loads((tmp_path / 'report' / 'report.json').read_text())
    return code, captured.out, captured.err, report


def _lines(err: str, start: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith(f'[cva-bag-replay] {start}')]


def test_a_right_image_5_us_off_is_named(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    off = START_NS + FRAME_NS + 5_000
    bag = write_stereo_bag(tmp_path / 'in', [{}, {'stamp_right': off}, {}, {}])
    code, out, err, report = _run(bag, tmp_path, capsys)
    assert code == 0
    left = START_NS + FRAME_NS
    lines = _lines(err, 'unpaired')
    assert len(lines) == 4
    assert (f'[cva-bag-replay] unpaired right image on /right/image_rect, stamp {off} ns: no '
            f'message with this stamp on /left/image_rect (nearest 5 µs earlier), '
            f'/left/camera_info (nearest 5 µs earlier)') in lines
    assert (f'[cva-bag-replay] unpaired left image on /left/image_rect, stamp {left} ns: no '
            f'message with this stamp on /right/image_rect (nearest 5 µs later), '
            f'/right/camera_info (nearest 5 µs later)') in lines
    assert ('3 of 3 frames processed, 0 skipped, 0 dropped, 4 unpaired messages '
            '(/left/camera_info: 1, /left/image_rect: 1, /right/camera_info: 1, '
            '/right/image_rect: 1)') in out
    summary = report['summary']
    assert summary['unpaired'] == 4
    assert summary['unpaired_by_topic'] == {
        '/left/camera_info': 1, '/left/image_rect': 1, '/right/camera_info': 1,
        '/right/image_rect': 1,
    }
    listed = {(m['topic'], m['stamp_ns']) for m in report['unpaired']}
    assert listed == {('/left/image_rect', left), ('/left/camera_info', left),
                      ('/right/image_rect', off), ('/right/camera_info', off)}
    markdown = (tmp_path / 'report' / 'summary.md').read_text()
    assert 'Unpaired input messages: 4' in markdown
    assert f'| /right/image_rect | {off} | no message with this stamp' in markdown


def test_duplicate_stamps_are_named_as_such(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Frames 1 and 2 carry the same stamp: the second set pairs with nothing.
    bag = write_stereo_bag(tmp_path / 'in', [{}, {}, {'stamp': START_NS + FRAME_NS}, {}])
    code, out, err, report = _run(bag, tmp_path, capsys)
    assert code == 0
    stamp = START_NS + FRAME_NS
    lines = _lines(err, 'unpaired')
    assert len(lines) == 4
    assert (f'[cva-bag-replay] unpaired left image on /left/image_rect, stamp {stamp} ns: '
            f'duplicate stamp: an earlier message on /left/image_rect has the same stamp and '
            f'was paired') in lines
    assert all('duplicate stamp' in line for line in lines)
    assert '3 of 3 frames processed' in out and '4 unpaired messages' in out
    assert report['summary']['unpaired'] == 4
    assert {m['stamp_ns'] for m in report['unpaired']} == {stamp}
    assert {m['reason'].split(':')[0] for m in report['unpaired']} == {'duplicate stamp'}


def test_many_unpaired_messages_are_logged_a_few_times(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    frames = [{'stamp_right': START_NS + i * FRAME_NS + 2_000_000} for i in range(4)]
    bag = write_stereo_bag(tmp_path / 'in', frames)
    code, _, err, report = _run(bag, tmp_path, capsys)
    assert code == 2
    assert len(_lines(err, 'unpaired')) == 10
    assert len(_lines(err, 'more unpaired messages; only counting them')) == 1
    last = err.strip().splitlines()[-1]
    assert 'no stereo pair matched by stamp' in last and '16 messages stayed unpaired' in last
    assert '/right/image_rect: 4' in last
    assert report['summary']['unpaired'] == 16 and len(report['unpaired']) == 16
    assert sum(report['summary']['unpaired_by_topic'].values()) == 16


@pytest.mark.parametrize(
    ('gt_frame', 'reason'),
    [
        ({'gt': np.full((30, 40), np.nan, np.float32)}, 'ground truth has no known pixel'),
        ({'gt_bytes': 100}, 'bad ground truth: '),
        ({'gt': np.full((20, 40), 4.0, np.float32)},
         'ground truth is 40×20 but the output is 40×30 (downsample 1)'),
    ],
    ids=['nan-only', 'truncated', 'wrong-size'],
)
def test_unusable_ground_truth_is_said_on_the_console(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], gt_frame: dict, reason: str
) -> None:
    bag = write_stereo_bag(tmp_path / 'in', [gt_frame])
    code, out, err, report = _run(bag, tmp_path, capsys)
    assert code == 0
    [line] = _lines(err, 'frame 0')
    assert line.startswith(f'[cva-bag-replay] frame 0 (stamp {START_NS} ns) not scored: {reason}')
    assert '; 0 of 1 frames scored (ground truth unusable: ' in out
    assert reason in out.split('0 of 1 frames scored', 1)[1]
    note = report['frames'][0]['note']
    assert note.startswith(reason)
    assert report['summary']['frames_scored'] == 0
    assert report['summary']['not_scored'] == {note: 1}
    assert f'- 1 × {note}' in (tmp_path / 'report' / 'summary.md').read_text()


def test_unusable_ground_truth_is_logged_a_few_times_per_reason(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    nan = np.full((30, 40), np.nan, np.float32)
    bag = write_stereo_bag(tmp_path / 'in', [{'gt': nan}] * 5 + [{}, {'gt_bytes': 10}])
    code, out, err, report = _run(bag, tmp_path, capsys)
    assert code == 0
    assert len(_lines(err, 'frame')) == 4  # three of the first reason, one of the other
    assert len(_lines(err, 'more frames not scored for "ground truth has no known pixel"')) == 1
    assert '; 1 of 7 frames scored (ground truth unusable: ground truth has no known pixel ' \
        '(5 frames); bad ground truth: ' in out
    assert report['summary']['frames_scored'] == 1


def test_a_bag_without_ground_truth_says_nothing_per_frame(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = write_stereo_bag(tmp_path / 'in', [{}, {}], ground_truth=False)
    code, out, err, _ = _run(bag, tmp_path, capsys)
    assert code == 0
    assert not _lines(err, 'frame') and 'frames scored' not in out
    assert len(_lines(err, 'no ground-truth topic')) == 1


def test_ground_truth_logged_frames_after_its_images_is_waited_for(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # A ground-truth node with latency: each message logged 5 frames after its images, more
    # than --queue-size (the synchroniser's setting) frames.
    bag = write_stereo_bag(tmp_path / 'in', [{'gt_lag': 5 * FRAME_NS}] * 8)
    code, out, err, report = _run(bag, tmp_path, capsys, '--queue-size', '2')
    assert code == 0
    assert not _lines(err, 'frame') and 'frames scored' not in out
    assert report['summary']['frames_scored'] == 8


def test_missing_ground_truth_is_named_as_missing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Frame 1 waits until the ground truth of frame 2 is read (its own cannot come after
    # that); frame 5 until the end of the bag.
    frames = [{'gt_lag': 2 * FRAME_NS, 'no_gt': index in (1, 5)} for index in range(6)]
    bag = write_stereo_bag(tmp_path / 'in', frames)
    code, out, err, report = _run(bag, tmp_path, capsys)
    assert code == 0
    note = 'no ground truth with this stamp in the bag'
    assert [line.split(': ', 1)[1] for line in _lines(err, 'frame')] == [note, note]
    assert [f['frame'] for f in report['frames'] if f['note'] == note] == [1, 5]
    assert report['summary']['frames_scored'] == 4
    assert report['summary']['not_scored'] == {note: 2}


def test_ground_truth_later_than_a_frame_waits_is_said_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    from msg_tools import replay

    monkeypatch.setattr(replay, 'GT_WAIT_FRAMES', 2)
    bag = write_stereo_bag(tmp_path / 'in', [{'gt_lag': 4 * FRAME_NS}] * 6)
    code, out, err, report = _run(bag, tmp_path, capsys)
    assert code == 0
    note = ('no ground truth before 2 later frames came (ground truth later than that is '
            'not waited for)')
    # At most 2 frames wait: frames 0 to 3 stop waiting before their ground truth comes.
    assert [f['frame'] for f in report['frames'] if f['note'] == note] == [0, 1, 2, 3]
    assert report['summary']['frames_scored'] == 2
    [line] = _lines(err, 'the ground truth of stamp')
    assert f'stamp {START_NS} ns came 2 or more frames after its images' in line
    assert f'{note} (4 frames)' in out

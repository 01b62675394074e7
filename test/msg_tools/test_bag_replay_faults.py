"""``cva-bag-replay`` on bad input: one-line errors with exit code 2, counted skips, Ctrl-C."""

from __future__ import annotations

import json
import os
from pathlib import Path
import signal
import subprocess
import sys
import time

from msg_test_utils import (
    MAX_DISPARITY,
    break_storage,
    read_bag,
    textured_pair,
    write_stereo_bag,
    write_topics_without_messages,
)
import numpy as np
import pytest

import msg_tools
from msg_tools.bag_replay import main
from msg_tools.convert import CAMERA_INFO, IMAGE

ROOT = Path(msg_tools.__file__).resolve().parents[1]


def _run(
    bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], *extra: str
) -> tuple[int, str, dict]:
    code = main([
        str(bag), '--out', str(tmp_path / 'out'), '--report', str(tmp_path / 'report'),
        '--max-disparity', str(MAX_DISPARITY), '--confidence-method', 'pkrn', *extra,
    ])
    err = capsys.readouterr().err
    assert 'Traceback' not in err
    report = tmp_path / 'report' / 'report.json'
    return code, err, json.loads(report.read_text()) if report.exists() else {}


def _last_line(err: str) -> str:
    return err.strip().splitlines()[-1]


def test_missing_bag(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, err, _ = _run(tmp_path / 'nothing', tmp_path, capsys)
    assert code == 2
    assert err.strip() == f'cva-bag-replay: error: bag {tmp_path / "nothing"} does not exist'
    assert not (tmp_path / 'out').exists()


@pytest.mark.parametrize('damage', ['garbage', 'truncated'])
def test_corrupt_bag(tmp_path: Path, capsys: pytest.CaptureFixture[str], damage: str) -> None:
    bag = write_stereo_bag(tmp_path / 'in', [{} for _ in range(4)])
    data = bag / 'in.mcap'
    content = data.read_bytes()
    if damage == 'garbage':
        data.write_bytes(content[:8] + bytes(np.random.default_rng(0).integers(0, 256, 4000)))
    else:
        data.write_bytes(content[: int(len(content) * 0.6)])
    code, err, report = _run(bag, tmp_path, capsys)
    assert code == 2
    assert 'corrupt or truncated' in _last_line(err) or 'corrupt or truncated' in err
    if (tmp_path / 'out').exists():
        # Stopped part-way: the output holds the frames done and says why it stopped.
        assert 'corrupt or truncated' in report['summary']['error']
        assert len(read_bag(tmp_path / 'out').get('/disparity', [])) == report['summary'][
            'processed']


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_storage_that_fails_part_way(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], storage: str
) -> None:
    # Images large enough that SQLite chains overflow pages, which it reads only on iteration.
    frames = [dict(zip(('left', 'right'), textured_pair(100, 120, 4, i), strict=True))
              for i in range(6)]
    bag = write_stereo_bag(tmp_path / 'in', frames, storage=storage)
    read = break_storage(bag)
    code, err, report = _run(bag, tmp_path, capsys)
    assert code == 2
    line = _last_line(err)
    assert line.startswith(f'cva-bag-replay: error: bag {bag} is corrupt or truncated after '
                           f'{read} messages: ')
    assert ('OverflowError' if storage == 'mcap' else 'CorruptError') in line
    # The frames done before the fault are in a readable output bag and in the report.
    summary = report['summary']
    assert 'corrupt or truncated' in summary['error']
    if storage == 'sqlite3':
        assert summary['processed'] > 0
    if summary['processed']:
        assert len(read_bag(tmp_path / 'out').get('/disparity', [])) == summary['processed']
    else:  # a bag with nothing in it is not left behind
        assert not (tmp_path / 'out').exists()
        assert 'no output bag written' in line


def test_missing_topic(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag = write_stereo_bag(tmp_path / 'in', [{}], skip_topics=('right/camera_info',))
    code, err, _ = _run(bag, tmp_path, capsys)
    assert code == 2
    line = _last_line(err)
    assert "no right info topic '/right/camera_info'" in line and '/left/camera_info' in line
    assert not (tmp_path / 'out').exists()


def test_unknown_encoding_everywhere_is_an_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = write_stereo_bag(tmp_path / 'in', [{'encoding': 'yuv422'}, {'encoding': 'yuv422'}])
    code, err, report = _run(bag, tmp_path, capsys)
    assert code == 2
    assert "'yuv422'" in err  # each skip is logged with its reason
    line = _last_line(err)
    assert 'none of the 2 stereo pairs could be processed' in line
    assert report['summary']['skipped'] == 2
    # Nothing to write: no empty bag left behind that a retry would have to --overwrite.
    assert f'no output bag written (nothing to write at {tmp_path / "out"})' in line
    assert not (tmp_path / 'out').exists()


def test_single_bad_frames_are_skipped_and_counted(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    small = textured_pair(30, 36, 4, 9)
    frames = [
        {},
        {'encoding': 'yuv422'},
        {'left': textured_pair(30, 40, 4, 8)[0], 'right': small[1]},  # left/right sizes differ
        {'info_size': (20, 30)},  # camera infos for another size
        {},
    ]
    bag = write_stereo_bag(tmp_path / 'in', frames)
    code, err, report = _run(bag, tmp_path, capsys)
    assert code == 0
    summary = report['summary']
    assert (summary['pairs'], summary['processed'], summary['skipped']) == (5, 2, 3)
    assert [f['frame'] for f in report['frames']] == [0, 4]
    assert err.count('skipped frame') == 3 and 'same size' in err and '20×30' in err
    assert len(read_bag(tmp_path / 'out')['/disparity']) == 2


def test_frame_narrower_than_max_disparity_is_skipped(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    tiny = np.full((1, 1), 7, np.uint8)
    bag = write_stereo_bag(tmp_path / 'in', [{'left': tiny, 'right': tiny}, {}, {}])
    code, err, report = _run(bag, tmp_path, capsys)
    assert code == 0
    summary = report['summary']
    assert (summary['pairs'], summary['processed'], summary['skipped']) == (3, 2, 1)
    assert [f['frame'] for f in report['frames']] == [1, 2]
    assert 'skipped frame 0' in err and 'smaller than the image width 1' in err
    assert len(read_bag(tmp_path / 'out')['/disparity']) == 2


@pytest.mark.parametrize('empty', [
    ('/left/image_rect', '/right/image_rect', '/left/camera_info', '/right/camera_info'),
    ('/right/image_rect',),
])
def test_input_topics_without_messages(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], empty: tuple[str, ...]
) -> None:
    types = {'/left/image_rect': IMAGE, '/right/image_rect': IMAGE,
             '/left/camera_info': CAMERA_INFO, '/right/camera_info': CAMERA_INFO}
    if len(empty) == len(types):
        bag = write_topics_without_messages(tmp_path / 'in', types)
    else:
        bag = write_stereo_bag(tmp_path / 'in', [{}, {}], skip_topics=('right/image_rect',))
        # The topic is declared (its connection exists) but carries nothing.
        bag = _with_declared_topics(bag, tmp_path / 'in2', {'/right/image_rect': IMAGE})
    code, err, _ = _run(bag, tmp_path, capsys)
    assert code == 2
    line = _last_line(err)
    topics = ', '.join(empty)
    verb = 'hold' if len(empty) > 1 else 'holds'
    assert f'{topics} {verb} no messages in bag {bag}' in line
    assert 'matched by stamp' not in line


def _with_declared_topics(bag: Path, out: Path, extra: dict[str, str]) -> Path:
    """A copy of ``bag`` that also declares ``extra`` topics, without messages on them."""
    from rosbags.rosbag2 import Reader, Writer

    from msg_tools.convert import jazzy_typestore

    store = jazzy_typestore()
    with Reader(bag) as reader, Writer(out, version=8) as writer:
        connections = {
            conn.id: writer.add_connection(conn.topic, conn.msgtype, typestore=store)
            for conn in reader.connections
        }
        for topic, msgtype in extra.items():
            writer.add_connection(topic, msgtype, typestore=store)
        for conn, timestamp, data in reader.messages():
            writer.write(connections[conn.id], timestamp, data)
    return out


def test_a_default_ground_truth_topic_of_another_type_is_not_used(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # The bag's /ground_truth/disparity is no ground truth (a CameraInfo): not asked for, the
    # frames are processed, not scored, and the log says why; asked for, it is an error.
    bag = write_stereo_bag(tmp_path / 'in', [{}, {}], ground_truth=False)
    bag = _with_declared_topics(bag, tmp_path / 'in2', {'/ground_truth/disparity': CAMERA_INFO})
    code, err, report = _run(bag, tmp_path, capsys)
    assert code == 0
    assert (f'[cva-bag-replay] topic /ground_truth/disparity of the bag has type {CAMERA_INFO}, '
            'not a ground truth (stereo_msgs/msg/DisparityImage or sensor_msgs/msg/Image): it is '
            'not used, frames are processed, not scored (name the ground-truth topic with '
            '--gt-topic)') in err.splitlines()
    assert report['summary']['processed'] == 2
    assert [f['note'] for f in report['frames']] == ['no ground truth'] * 2
    for name in ('ground_truth/disparity', '/ground_truth/disparity'):
        code, err, _ = _run(bag, tmp_path, capsys, '--gt-topic', name, '--overwrite')
        assert code == 2
        assert _last_line(err) == (
            "cva-bag-replay: error: ground-truth topic '/ground_truth/disparity' has type "
            f"{CAMERA_INFO}; expected one of ['stereo_msgs/msg/DisparityImage', "
            f"'{IMAGE}']"
        )


def test_unpaired_stamps(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    frames = [{'stamp_right': 1_700_000_000 * 10**9 + i * 100_000_000 + 2_000_000}
              for i in range(3)]
    bag = write_stereo_bag(tmp_path / 'in', frames)
    code, err, report = _run(bag, tmp_path, capsys)
    assert code == 2
    assert 'no stereo pair matched by stamp' in _last_line(err)
    assert report['summary']['unpaired'] == 12
    # The same bag pairs up with the approximate policy and a tolerance above the 2 ms skew.
    code, _, report = _run(bag, tmp_path, capsys, '--approximate-sync', '--sync-tolerance',
                           '0.005', '--overwrite')
    assert code == 0 and report['summary']['processed'] == 3


def test_bad_options(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag = write_stereo_bag(tmp_path / 'in', [{}])
    for extra, message in (
        (('--matcher', 'nope'), "unknown matcher 'nope'"),
        (('--downsample', '3'), 'downsample must be 1, 2 or 4'),
        (('--speckle-size', '-1'), 'speckle_size must be an integer in [0, 1000000]'),
        (('--speckle-range', 'nan'), 'speckle_range must be a number in [0, 1024]'),
        (('--scan', '--scan-height', '1', '0'), 'scan_min_height must be < scan_max_height'),
        (('--scan-range', '-1', '5'), 'scan_range_min < scan_range_max'),
        (('--scan-pitch', '2'), 'scan_pitch must be in (-pi/2, pi/2)'),
        (('--rate-scale', '0'), 'rate_scale must be a finite number > 0'),
        (('--rate-scale', 'inf'), 'rate_scale must be a finite number > 0'),
        (('--approximate-sync', '--sync-tolerance', 'nan'), 'sync tolerance must be a finite'),
        (('--approximate-sync', '--sync-tolerance', 'inf'), 'sync tolerance must be a finite'),
        (('--approximate-sync', '--sync-tolerance', '1e300'), 'sync tolerance must be a finite'),
        (('--mode', 'live', '--no-start-node', '--startup-timeout', 'nan'), 'timeouts must be'),
        (('--mode', 'live', '--drain-timeout', 'inf'), 'timeouts must be'),
        (('--topic-prefix', 'a b'), 'topic prefix must be a valid ROS 2 topic name'),
        (('--left-topic', '1cam/image'), 'topic left must be a valid ROS 2 topic name'),
        (('--max-pixels', '100', '--seed', '-1'), 'seed must be an integer >= 0; got -1'),
    ):
        code, err, _ = _run(bag, tmp_path, capsys, *extra)
        assert code == 2 and message in err and len(err.strip().splitlines()) == 1
        assert not (tmp_path / 'out').exists() and not (tmp_path / 'report').exists()
    assert _run(bag, tmp_path, capsys)[0] == 0
    code, err, _ = _run(bag, tmp_path, capsys)
    assert code == 2 and 'exists already' in err


def _replay_into(bag: Path, out: Path, report: Path, *extra: str) -> int:
    return main([str(bag), '--out', str(out), '--report', str(report), '--max-disparity',
                 str(MAX_DISPARITY), '--confidence-method', 'pkrn', *extra])


def test_overwrite_never_deletes_the_input(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = write_stereo_bag(tmp_path / 'in', [{}])
    storage = bag / 'in.mcap'
    before = {p.name: p.read_bytes() for p in bag.iterdir()}
    for bag_arg, out, message in (
        (bag, bag, 'must lie outside the input bag'),
        (bag, storage, 'must lie outside the input bag'),  # --out in the input folder
        (bag, bag / 'sub' / 'out', 'must lie outside the input bag'),
        (storage, bag, 'must not contain the input bag'),  # --out holds the input file
        (storage, tmp_path, 'must not contain the input bag'),
        (tmp_path / 'link' / 'in.mcap', bag, 'must not contain the input bag'),
    ):
        if not (tmp_path / 'link').exists():
            (tmp_path / 'link').symlink_to(bag)  # the same folder under another name
        code = _replay_into(bag_arg, out, tmp_path / 'report', '--overwrite')
        err = capsys.readouterr().err
        assert code == 2 and 'Traceback' not in err
        assert message in err and len(err.strip().splitlines()) == 1
        assert {p.name: p.read_bytes() for p in bag.iterdir()} == before
    assert not (tmp_path / 'report').exists()


def test_overwrite_refuses_what_is_not_a_bag(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = write_stereo_bag(tmp_path / 'in', [{}])
    text = tmp_path / 'notes.mcap'
    text.write_text('not a bag\n')
    code = _replay_into(bag, text, tmp_path / 'report', '--overwrite')
    assert code == 2
    assert 'refusing to overwrite' in capsys.readouterr().err
    assert text.read_text() == 'not a bag\n'


@pytest.mark.parametrize('mode', ['offline', 'live'])
def test_bad_report_path(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], mode: str
) -> None:
    bag = write_stereo_bag(tmp_path / 'in', [{}])
    plain = tmp_path / 'plain.txt'
    plain.write_text('x')
    for report, message in (
        (plain, f'the report folder {plain} is a file; expected a folder'),
        (plain / 'sub', f'cannot create the report folder {plain / "sub"}: {plain} is a file'),
    ):
        code = _replay_into(bag, tmp_path / 'out', report, '--mode', mode, '--no-start-node',
                            '--startup-timeout', '1')
        err = capsys.readouterr().err
        assert code == 2 and 'Traceback' not in err
        assert err.strip() == f'cva-bag-replay: error: {message}'
        assert not (tmp_path / 'out').exists()


def test_report_and_output_must_not_overlap(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = write_stereo_bag(tmp_path / 'in', [{}])
    for report in (tmp_path / 'out', tmp_path / 'out' / 'report'):
        code = _replay_into(bag, tmp_path / 'out', report)
        err = capsys.readouterr().err
        assert code == 2 and len(err.strip().splitlines()) == 1
        assert 'the report folder must lie outside the output bag' in err
        assert not (tmp_path / 'out').exists()
    # The output bag may go inside the report folder.
    assert _replay_into(bag, tmp_path / 'run' / 'bag', tmp_path / 'run') == 0
    assert len(read_bag(tmp_path / 'run' / 'bag')['/disparity']) == 1


def test_ctrl_c_during_a_frame_still_scores_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    # The signal lands while the second frame is processed; its ground truth comes after its
    # images in the bag, so the replay reads ahead for it rather than report the frame bare.
    from msg_tools import replay

    bag = write_stereo_bag(tmp_path / 'in', [{'shift': 3}, {'shift': 4}, {'shift': 5}])
    process_pair = replay._process_pair

    def signal_during_second(session: replay.ReplaySession, *args: object) -> None:
        if session.counts['pairs'] == 2:
            os.kill(os.getpid(), signal.SIGINT)  # taken by the replay's own handler
        process_pair(session, *args)

    monkeypatch.setattr(replay, '_process_pair', signal_during_second)
    code = _replay_into(bag, tmp_path / 'out', tmp_path / 'report')
    assert code == 130, capsys.readouterr().err
    report = json.loads((tmp_path / 'report' / 'report.json').read_text())
    assert report['summary']['interrupted'] is True
    assert [frame['frame'] for frame in report['frames']] == [0, 1]
    assert all(frame['auc'] is not None and not frame['note'] for frame in report['frames'])


def test_ctrl_c_leaves_a_readable_bag(tmp_path: Path) -> None:
    # Enough frames that the run is still going when the signal comes (PNGs make each slow).
    bag = write_stereo_bag(tmp_path / 'in', [{'shift': 2 + i % 5} for i in range(150)])
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        p for p in (str(ROOT), os.environ.get('PYTHONPATH', '')) if p))
    process = subprocess.Popen(
        [sys.executable, '-m', 'msg_tools.bag_replay', str(bag), '--out', str(tmp_path / 'out'),
         '--report', str(tmp_path / 'report'), '--max-disparity', str(MAX_DISPARITY),
         '--confidence-method', 'pkrn', '--max-plots', '1000'],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
    )
    assert process.stderr is not None
    deadline = time.monotonic() + 60
    for line in process.stderr:  # the first progress line comes after the first frame
        if 'offline:' in line or time.monotonic() > deadline:
            break
    time.sleep(0.3)
    process.send_signal(signal.SIGINT)
    out, err = process.communicate(timeout=60)
    assert process.returncode == 130, err
    assert 'Traceback' not in err
    assert 'interrupted after' in err
    report = json.loads((tmp_path / 'report' / 'report.json').read_text())
    done = report['summary']['processed']
    assert report['summary']['interrupted'] is True
    assert 0 < done < 150 and len(report['frames']) == done
    outputs = read_bag(tmp_path / 'out')
    assert len(outputs['/disparity']) == len(outputs['/confidence']) == done


def test_a_fault_while_scoring_at_the_end_still_closes_the_bag(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The last frame has no ground truth, so it is scored only when the run ends.
    from msg_tools.replay import ReplaySession

    bag = write_stereo_bag(tmp_path / 'in', [{}, {}, {'no_gt': True}])
    score_now = ReplaySession._score_now

    def fail_without_ground_truth(
        session: ReplaySession, result: object, msg: object, note: str
    ) -> None:
        if msg is None:
            raise RuntimeError('scoring failed')
        score_now(session, result, msg, note)

    monkeypatch.setattr(ReplaySession, '_score_now', fail_without_ground_truth)
    with pytest.raises(RuntimeError, match='scoring failed'):
        _replay_into(bag, tmp_path / 'out', tmp_path / 'report')
    # Closed all the same: metadata and MCAP summary written, every frame readable.
    outputs = read_bag(tmp_path / 'out')
    assert len(outputs['/disparity']) == len(outputs['/confidence']) == 3

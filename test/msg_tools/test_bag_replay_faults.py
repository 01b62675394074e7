"""``cva-bag-replay`` on bad input: one-line errors with exit code 2, counted skips, Ctrl-C."""

from __future__ import annotations

import json
import os
from pathlib import Path
import signal
import subprocess
import sys
import time

from msg_test_utils import MAX_DISPARITY, read_bag, textured_pair, write_stereo_bag
import numpy as np
import pytest

import msg_tools
from msg_tools.bag_replay import main

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
    assert 'none of the 2 stereo pairs could be processed' in _last_line(err)
    assert report['summary']['skipped'] == 2
    assert read_bag(tmp_path / 'out') == {}  # closed properly, empty


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
        (('--rate-scale', '0'), 'rate_scale must be > 0'),
    ):
        code, err, _ = _run(bag, tmp_path, capsys, *extra)
        assert code == 2 and message in err and len(err.strip().splitlines()) == 1
    assert _run(bag, tmp_path, capsys)[0] == 0
    code, err, _ = _run(bag, tmp_path, capsys)
    assert code == 2 and 'exists already' in err


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

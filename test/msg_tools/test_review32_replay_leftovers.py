"""Replay leftovers: a frame not scored against its ground truth keeps what needs none; log
lines above the progress line on a terminal."""

from __future__ import annotations

import io
import json
from pathlib import Path
import sys

from msg_test_utils import MAX_DISPARITY, write_stereo_bag
import pytest

from cva_confidence_ros.errors import InputError
from msg_tools import replay
from msg_tools.bag_replay import main
from msg_tools.progress import Progress
from msg_tools.replay import log_stderr


def test_a_frame_not_scored_against_its_ground_truth_keeps_its_kept_share(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    score_frame = replay.score_frame

    def refuse_ground_truth(*args, **kwargs):
        if args[5] is not None:  # gt
            raise InputError('confidence must not be NaN at scored pixels; got 1 NaN values')
        return score_frame(*args, **kwargs)

    monkeypatch.setattr(replay, 'score_frame', refuse_ground_truth)
    bag = write_stereo_bag(tmp_path / 'in', [{}, {}])
    code = main([str(bag), '--out', str(tmp_path / 'out'), '--report', str(tmp_path / 'rep'),
                 '--max-disparity', str(MAX_DISPARITY), '--confidence-method', 'pkrn'])
    capsys.readouterr()
    assert code == 0
    frames = json.loads((tmp_path / 'rep' / 'report.json').read_text())['frames']
    assert len(frames) == 2
    for frame in frames:
        # The kept share needs no ground truth: it was lost with the failed scoring.
        assert frame['kept_fraction'] is not None and 0.0 <= frame['kept_fraction'] <= 1.0
        assert frame['auc'] is None
        assert frame['note'].startswith('not scored: confidence must not be NaN')


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_a_log_line_goes_above_a_progress_line_on_a_terminal(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # The progress line has no newline while it is rewritten in place: a log line printed
    # then was glued to its end ('...0.50 fps[cva-bag-replay] frame 3 skipped').
    terminal = _Terminal()
    monkeypatch.setattr(sys, 'stderr', terminal)
    with Progress(4, prefix='replay: ', clock=iter(range(100)).__next__) as progress:
        progress.update()
        log_stderr('frame 1 skipped: no ground truth')
        progress.update()
    lines = terminal.getvalue().split('\n')
    assert lines[0].endswith('\r\x1b[K[cva-bag-replay] frame 1 skipped: no ground truth')
    # Drawn again below it, then rewritten in place; the last one ends the line.
    assert len(lines) == 3 and lines[2] == ''
    assert lines[1].startswith('replay: 1/4 frames') and '\rreplay: 2/4 frames' in lines[1]


def test_the_progress_line_ends_when_the_run_fails(monkeypatch: pytest.MonkeyPatch) -> None:
    terminal = _Terminal()
    monkeypatch.setattr(sys, 'stderr', terminal)
    with pytest.raises(RuntimeError), Progress(4, prefix='replay: ') as progress:
        progress.update()
        raise RuntimeError('a bag fault')
    assert terminal.getvalue().endswith('\n')  # the error message starts its own line
    log_stderr('after')  # no progress line to redraw any more
    assert terminal.getvalue().endswith('\n[cva-bag-replay] after\n')

"""Review 33 of the live replay: what a Ctrl-C leaves unanswered is not all dropped."""

from __future__ import annotations

import os
from pathlib import Path
import signal
from typing import Any

from msg_test_utils import write_stereo_bag
import pytest
from test_review31_live import _play

from msg_tools import live
from msg_tools.scoring import format_summary


def _ctrl_c_after(monkeypatch: pytest.MonkeyPatch, pair: int) -> None:
    """Send SIGINT (Ctrl-C) once the replay has registered ``pair`` as published."""
    expect = live._Recorder.expect

    def ctrl_c(recorder: live._Recorder, matched: Any, frame: int, timestamp_ns: int) -> None:
        expect(recorder, matched, frame, timestamp_ns)
        if frame == pair:
            os.kill(os.getpid(), signal.SIGINT)

    monkeypatch.setattr(live._Recorder, 'expect', ctrl_c)


def test_frames_in_flight_at_a_ctrl_c_are_not_counted_dropped(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The node answers pairs 0 and 2, drops 1 and has not answered 3 yet when Ctrl-C comes
    # right after 3 went out. Pair 1 is dropped (the node answers in order and 2 came); pair 3
    # may still have been on its way: the report counted 2 dropped.
    bag = write_stereo_bag(tmp_path / 'in', [{}] * 5, ground_truth=False)
    _ctrl_c_after(monkeypatch, 3)
    outcome, _ = _play(tmp_path, bag, silent={1, 3})
    assert outcome.exit_code == 130
    counts = outcome.report.counts
    assert (counts['pairs'], counts['processed']) == (4, 2)
    assert (counts['dropped'], counts['in_flight']) == (1, 1)
    assert outcome.report.summary()['in_flight'] == 1


def test_a_run_to_its_end_counts_no_frame_in_flight(tmp_path: Path) -> None:
    # Without a Ctrl-C, what the node has not answered by the end of the drain is dropped.
    bag = write_stereo_bag(tmp_path / 'in', [{}] * 3, ground_truth=False)
    outcome, _ = _play(tmp_path, bag, '--drain-timeout', '0.5', silent={2})
    assert outcome.exit_code == 0, outcome.message
    counts = outcome.report.counts
    assert counts['dropped'] == 1 and 'in_flight' not in counts


def test_the_report_says_how_many_were_in_flight(tmp_path: Path,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    bag = write_stereo_bag(tmp_path / 'in', [{}] * 3, ground_truth=False)
    _ctrl_c_after(monkeypatch, 1)
    outcome, _ = _play(tmp_path, bag, silent={1})
    assert outcome.exit_code == 130
    assert 'interrupted after 1 frames (1 more were still on their way)' in outcome.message
    summary = format_summary(outcome.report.as_dict())
    assert '1 frames published after the last one the node answered were still' in summary

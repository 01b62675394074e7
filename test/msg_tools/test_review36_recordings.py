"""Review 36 of ``cva-bag-replay`` with robots' own recordings (``ros2 bag record``).

Ground truth from a node whose latency varies can come (in bag order) after that of the next
frame; its frame was left unscored ('no ground truth with this stamp in the bag', though it
was there). Frames now wait for theirs until ground truth ``TRUTH_JUMP_NS`` or more later
has come (or the ground truth jumps back, or ``GT_WAIT_FRAMES`` frames wait).
"""

from __future__ import annotations

from pathlib import Path

from msg_test_utils import (
    START_NS,
    replay_offline,
    session_frame,
    session_truth,
    truth_session,
    write_stereo_bag,
)
import pytest

from msg_tools.replay import TRUTH_JUMP_NS

FRAME_NS = 100_000_000


def _scored(report: dict) -> dict[int, bool]:
    return {f['frame']: f['auc'] is not None for f in report['frames']}


def test_ground_truth_after_that_of_the_next_frame_scores_its_frame(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # The ground truth of frames 0 and 3 is logged 150 ms after its images, after that of the
    # next frame; frame 1 has none. Before: frames 0 and 3 went unscored ('no ground truth
    # with this stamp in the bag'): 2 of 5 scored.
    frames: list[dict] = [{'gt_lag': 150_000_000}, {'no_gt': True}, {}, {'gt_lag': 150_000_000},
                          {}]
    bag = write_stereo_bag(tmp_path / 'in', frames)
    code, err, report = replay_offline(bag, tmp_path, capsys)
    assert code == 0
    assert _scored(report) == {0: True, 1: False, 2: True, 3: True, 4: True}
    [missing] = [f for f in report['frames'] if f['frame'] == 1]
    assert missing['note'] == 'no ground truth with this stamp in the bag'
    assert report['summary']['gt_unmatched'] == 0
    assert err.count('not scored') == 1


def test_a_frame_waits_for_its_ground_truth_only_within_the_window(tmp_path: Path) -> None:
    # Ground truth a frame later than the frame's own does not end its wait (before it did);
    # ground truth TRUTH_JUMP_NS later does, so the memory stays bounded.
    session = truth_session(tmp_path)
    session.add_result(session_frame(0, START_NS))
    session.add_result(session_frame(1, START_NS + FRAME_NS))
    session.add_ground_truth(START_NS + FRAME_NS, session_truth(START_NS + FRAME_NS))
    assert [f.frame for f in session.report.frames] == [1]
    session.add_ground_truth(START_NS, session_truth(START_NS))  # out of order
    session.add_result(session_frame(2, START_NS + 2 * FRAME_NS))  # no ground truth of its own
    session.add_ground_truth(START_NS + 3 * FRAME_NS, session_truth(START_NS + 3 * FRAME_NS))
    assert {f.frame: f.auc is not None for f in session.report.frames} == {0: True, 1: True}
    late = START_NS + 2 * FRAME_NS + TRUTH_JUMP_NS
    session.add_ground_truth(late, session_truth(late))
    scores = {f.frame: f for f in session.report.frames}
    assert scores[2].auc is None
    assert scores[2].note == 'no ground truth with this stamp in the bag'
    assert session.counts['processed'] == 3


# --- a part of a long recording: --start / --duration ------------------------------------------


def test_start_and_duration_replay_a_part_of_the_bag(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Before: no way to replay a part of a long recording (unrecognised arguments). Frame 3's
    # ground truth lies 150 ms after its images, past the part: it is read all the same.
    frames = [{'gt_lag': 150_000_000} if i == 3 else {} for i in range(6)]
    bag = write_stereo_bag(tmp_path / 'in', frames)
    code, _, report = replay_offline(bag, tmp_path, capsys, '--start', '0.15', '--duration',
                                     '0.2')
    assert code == 0
    assert [f['stamp_ns'] for f in report['frames']] == [START_NS + 2 * FRAME_NS,
                                                         START_NS + 3 * FRAME_NS]
    assert all(_scored(report).values())
    assert report['summary']['total'] == 2
    assert (report['config']['start_s'], report['config']['duration_s']) == (0.15, 0.2)


def test_a_start_past_the_end_of_the_bag_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = write_stereo_bag(tmp_path / 'in', [{}, {}])
    code, err, report = replay_offline(bag, tmp_path, capsys, '--start', '5')
    assert code == 2 and not report
    assert '--start: start 5 s lies at or past the end of bag' in err
    assert 'spans 0.100 s of bag time' in err
    assert not (tmp_path / 'out').exists()

"""Review 32 of ``ReplaySession``'s ground-truth pairing across a jump back of the stamps.

The frames and the ground truth count their jumps back (ordering epochs), and the n-th jump of
each is taken as the same one. Ground truth left over from before a jump (that of a skipped
frame, or a second message of one stamp) must not score the frame of the same stamp after the
jump (a simulator reset shows another scene at the same stamps), and ground truth after the jump
must not score a frame of the same stamp from before it.
"""

from __future__ import annotations

import json
from pathlib import Path

from msg_test_utils import (
    MAX_DISPARITY,
    START_NS,
    session_frame,
    session_truth,
    truth_session,
    write_stereo_bag,
)
import pytest

from msg_tools.bag_replay import main
from msg_tools.replay import ReplaySession

FRAME_NS = 100_000_000


def _session(tmp_path: Path) -> ReplaySession:
    return truth_session(tmp_path)


def _errors(session: ReplaySession) -> dict[int, float | None]:
    """Frame index → error rate (None: not scored)."""
    session.finish()
    return {f.frame: f.error_rate for f in session.report.frames}


def test_ground_truth_of_a_skipped_frame_is_not_used_after_a_reset(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # A simulator reset: stamps A, B, then A, B again, with another scene (disparity 8, not 4).
    # Frame 1 is skipped (bad encoding), so its ground truth stays stored. Before: frame 3, of
    # its stamp after the reset, was scored against it (error rate 0.88, EPE 4 px) and its own
    # ground truth went unused.
    frames = [
        {'stamp': START_NS, 'shift': 4},
        {'stamp': START_NS + FRAME_NS, 'shift': 4, 'encoding': 'yuv422'},
        {'stamp': START_NS, 'shift': 8},
        {'stamp': START_NS + FRAME_NS, 'shift': 8},
    ]
    bag = write_stereo_bag(
        tmp_path / 'in',
        [{**frame, 'logged': START_NS + index * FRAME_NS} for index, frame in enumerate(frames)],
    )
    code = main([
        str(bag), '--out', str(tmp_path / 'out'), '--report', str(tmp_path / 'report'),
        '--max-disparity', str(MAX_DISPARITY), '--confidence-method', 'pkrn',
        '--max-plots', '0',
    ])
    assert 'Traceback' not in capsys.readouterr().err
    assert code == 0
    report = json.loads((tmp_path / 'report' / 'report.json').read_text())
    scores = {f['frame']: f for f in report['frames']}
    assert sorted(scores) == [0, 2, 3]
    assert all(f['note'] == '' for f in scores.values())
    assert scores[3]['kept_epe'] < 0.5
    assert scores[3]['error_rate'] < 0.1


def test_a_second_ground_truth_of_one_stamp_is_not_used_after_a_reset(tmp_path: Path) -> None:
    # The ground truth of stamp 100 comes twice: the second stays stored. After the reset the
    # frame of stamp 100 (disparity 7) was scored against it (error rate 1.0), not its own.
    session = _session(tmp_path)
    session.add_result(session_frame(0, 100, 3.0))
    session.add_ground_truth(100, session_truth(100, 3.0))
    session.add_ground_truth(100, session_truth(100, 3.0))
    session.add_result(session_frame(1, 200, 3.0))
    session.add_ground_truth(200, session_truth(200, 3.0))
    # The reset: both streams start over at stamp 100, with another scene.
    session.add_result(session_frame(2, 100, 7.0))
    session.add_ground_truth(100, session_truth(100, 7.0))
    session.add_result(session_frame(3, 200, 7.0))
    session.add_ground_truth(200, session_truth(200, 7.0))
    assert _errors(session) == {0: 0.0, 1: 0.0, 2: 0.0, 3: 0.0}


def test_ground_truth_after_a_reset_does_not_score_a_frame_from_before_it(
    tmp_path: Path,
) -> None:
    # Frame 1 (stamp 100) has no ground truth and waits. After the reset the ground truth runs
    # ahead of the frames: that of stamp 100 (disparity 7) comes before frame 3. Before: it
    # scored frame 1 (disparity 3; error rate 1.0) and frame 3 was left without one.
    session = _session(tmp_path)
    session.add_result(session_frame(0, 50, 3.0))
    session.add_ground_truth(50, session_truth(50, 3.0))
    session.add_result(session_frame(1, 100, 3.0))
    session.add_ground_truth(20, session_truth(20, 7.0))
    session.add_ground_truth(100, session_truth(100, 7.0))
    session.add_result(session_frame(2, 20, 7.0))
    session.add_result(session_frame(3, 100, 7.0))
    errors = _errors(session)
    assert errors == {0: 0.0, 1: None, 2: 0.0, 3: 0.0}
    [unscored] = [f for f in session.report.frames if f.frame == 1]
    assert unscored.note == 'no ground truth with this stamp in the bag'

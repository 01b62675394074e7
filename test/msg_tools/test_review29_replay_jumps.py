"""Review fixes of the replay's ground-truth pairing and size check.

Stamps that jump back (a simulator reset, a looped recording) start a new ordering epoch:
ground truth and frames from before the jump no longer make the frames after it give up on
their ground truth, and a frame from before the jump that never got ground truth is still
reported (unscored, with the reason). Ground truth of another size than the input is refused,
naming both sizes, at every ``--downsample``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from msg_test_utils import START_NS, replay_offline, write_stereo_bag
import numpy as np
import pytest

FRAME_NS = 100_000_000
JUMP_NS = 10 * 10**9
NO_GT = 'no ground truth with this stamp in the bag'


def _bag(path: Path, frames: Sequence[dict[str, Any]]) -> Path:
    """A stereo bag (``write_stereo_bag``'s frames) whose bag times go on at 10 Hz whatever
    the header stamps do."""
    return write_stereo_bag(
        path, [{**frame, 'logged': START_NS + index * FRAME_NS}
               for index, frame in enumerate(frames)]
    )


def _notes(report: dict) -> dict[int, str | None]:
    """Frame index → None when scored, else its note."""
    return {f['frame']: (None if f['auc'] is not None else f['note']) for f in report['frames']}


def _stamps(before: int, after: int, jump_ns: int = JUMP_NS) -> list[int]:
    """``before`` frames at 10 Hz, then ``after`` more whose stamps went back ``jump_ns``."""
    return [START_NS + i * FRAME_NS - (jump_ns if i >= before else 0)
            for i in range(before + after)]


def test_ground_truth_kept_from_before_a_jump_does_not_stop_later_frames(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Frame 1 is skipped (bad encoding), so its ground truth stays stored; then the stamps go
    # back 10 s. Before: that stored ground truth, of a later stamp, made every frame after
    # the jump give up at once ('no ground truth with this stamp in the bag').
    frames = [{'stamp': stamp} for stamp in _stamps(2, 4)]
    frames[1]['encoding'] = 'yuv422'
    code, err, report = replay_offline(_bag(tmp_path / 'in', frames), tmp_path, capsys)
    assert code == 0
    assert report['summary']['processed'] == 5 and report['summary']['skipped'] == 1
    assert _notes(report) == {0: None, 2: None, 3: None, 4: None, 5: None}
    assert [f['stamp_ns'] for f in report['frames']] == [frames[0]['stamp'],
                                                         *(f['stamp'] for f in frames[2:])]
    assert 'not scored' not in err


def test_late_ground_truth_from_before_a_jump_does_not_stop_later_frames(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Ground truth logged 0.25 s after its images: that of the last frames before the jump
    # comes while frames after it wait. Before: its later stamp gave them up. Frame 1 has no
    # ground truth at all: it is still reported, unscored, with the reason, and, as before
    # the fix, as soon as the ground truth of frame 2 comes (the report is in that order).
    frames = [{'stamp': stamp, 'gt_lag': 250_000_000} for stamp in _stamps(4, 4)]
    frames[1]['no_gt'] = True
    code, err, report = replay_offline(_bag(tmp_path / 'in', frames), tmp_path, capsys)
    assert code == 0
    notes = _notes(report)
    assert sorted(notes) == list(range(8))
    assert notes == {i: (NO_GT if i == 1 else None) for i in range(8)}
    assert report['summary']['frames_scored'] == 7
    assert f'frame 1 (stamp {frames[1]["stamp"]} ns) not scored: {NO_GT}' in err
    assert err.count('not scored') == 1
    assert [f['frame'] for f in report['frames']] == list(range(8))


def test_a_jump_right_after_a_skipped_frame_is_seen(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # The only frame before the jump is skipped (bad encoding) and the ground truth lags
    # 0.25 s: the jump lies between a skipped frame and the first processed one. Before: the
    # late ground truth of the skipped frame, of a later stamp, gave up frames 1 and 2.
    frames = [{'stamp': stamp, 'gt_lag': 250_000_000} for stamp in _stamps(1, 3)]
    frames[0]['encoding'] = 'yuv422'
    code, err, report = replay_offline(_bag(tmp_path / 'in', frames), tmp_path, capsys)
    assert code == 0
    assert report['summary']['skipped'] == 1
    assert _notes(report) == {1: None, 2: None, 3: None}


def test_a_looped_bag_keeps_every_frame_in_the_report(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # A 3-frame recording played twice (the stamps go back 0.3 s, to the same stamps). Frame 2
    # of the first pass has no ground truth and still waits when frame 5 of the second pass,
    # of the same stamp, comes. Before: frame 5 took its place among the waiting frames and
    # frame 2 vanished from the report.
    frames = [{'stamp': START_NS + (i % 3) * FRAME_NS} for i in range(6)]
    frames[2]['no_gt'] = True
    code, err, report = replay_offline(_bag(tmp_path / 'in', frames), tmp_path, capsys)
    assert code == 0
    assert report['summary']['processed'] == 6
    notes = _notes(report)
    assert sorted(notes) == list(range(6))
    assert notes[2] == ('no ground truth with this stamp before the stamps jumped back and a '
                        'later frame came with the same stamp')
    assert all(notes[i] is None for i in (0, 1, 3, 4, 5))


@pytest.mark.parametrize('factor', [2, 4])
def test_ground_truth_larger_than_the_input_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], factor: int
) -> None:
    # 41×31 ground truth for 40×30 images (frame 0). Before, at --downsample 2 or 4 it passed
    # the shape // factor check and was silently cropped (--downsample 1 refuses it, as the
    # reporting tests check). Frame 1's ground truth of the input size is still scored.
    frames = [{'stamp': stamp} for stamp in _stamps(2, 0)]
    frames[0]['gt'] = np.full((31, 41), 4.0, np.float32)
    code, err, report = replay_offline(_bag(tmp_path / 'in', frames), tmp_path, capsys,
                             '--downsample', str(factor), '--max-disparity', '8')
    assert code == 0
    reason = (f'ground truth is 41×31 but the input is 40×30 (the output '
              f'{40 // factor}×{30 // factor} at downsample {factor})')
    assert _notes(report) == {0: reason, 1: None}
    assert f'frame 0 (stamp {frames[0]["stamp"]} ns) not scored: {reason}' in err
    assert report['frames'][1]['width'] == 40 // factor

"""Review 33 of ``cva-bag-replay``: ground truth that matches no frame, and errors that name
the command line's options.

Ground-truth messages whose stamp no processed frame has (ground truth stamped unlike its
images, or of images that were unpaired or skipped) were forgotten without a word: the run
just scored fewer frames. The report and the closing line now count them (and name a few
stamps). ``ReplayOptions`` and ``TopicNames`` named their dataclass fields (``rate_scale``,
``queue_size``, ``topic left``) to a user who had typed ``--rate-scale``, ``--queue-size`` or
``--left-topic``.
"""

from __future__ import annotations

import json
from pathlib import Path

from msg_test_utils import (
    MAX_DISPARITY,
    SESSION_GEOMETRY,
    START_NS,
    session_frame,
    session_truth,
    textured_pair,
    truth_session,
    write_stereo_bag,
)
import numpy as np
import pytest

from cva_confidence_ros.errors import ConfigError
from msg_tools.bag_replay import main
from msg_tools.bagio import OutputBag
from msg_tools.convert import (
    CAMERA_INFO,
    DISPARITY_IMAGE,
    IMAGE,
    camera_info_msgs,
    disparity_to_msg,
    image_to_msg,
    jazzy_typestore,
)
from msg_tools.replay import (
    ReplayOptions,
    ReplaySession,
    TopicNames,
)
from msg_tools.scoring import ReplayReport, format_summary

FRAME_NS = 100_000_000
GEOMETRY = SESSION_GEOMETRY


def _argv(bag: Path, tmp_path: Path, *extra: str) -> list[str]:
    return [
        str(bag), '--out', str(tmp_path / 'out'), '--report', str(tmp_path / 'report'),
        '--confidence-method', 'pkrn', '--max-disparity', str(MAX_DISPARITY), '--max-plots',
        '0', *extra,
    ]


def _summary(tmp_path: Path) -> dict:
    return json.loads((tmp_path / 'report' / 'report.json').read_text())['summary']


def _bag_with_truth_offset(path: Path, count: int, offset_ns: int) -> Path:
    """Images and camera infos as ``write_stereo_bag`` writes them, ground truth stamped
    ``offset_ns`` after its images (a ground-truth node that stamps with its own clock)."""
    store = jazzy_typestore()
    with OutputBag(path, 'mcap', store) as bag:
        for index in range(count):
            stamp = START_NS + index * FRAME_NS
            left, right = textured_pair(30, 40, 4, index)
            left_info, right_info = camera_info_msgs(GEOMETRY, 40, 30, stamp, ('l', 'r'), store)
            truth = np.full((30, 40), 4.0, np.float32)
            truth[:, :4] = np.nan
            for topic, kind, msg in (
                ('/left/camera_info', CAMERA_INFO, left_info),
                ('/right/camera_info', CAMERA_INFO, right_info),
                ('/left/image_rect', IMAGE, image_to_msg(left, stamp, 'l', store)),
                ('/right/image_rect', IMAGE, image_to_msg(right, stamp, 'r', store)),
                ('/ground_truth/disparity', DISPARITY_IMAGE,
                 disparity_to_msg(truth, stamp + offset_ns, 'l', GEOMETRY, typestore=store)),
            ):
                bag.write(topic, kind, msg, stamp)
    return path


def _session(tmp_path: Path, truth_window: int | None = 0) -> ReplaySession:
    return truth_session(tmp_path, truth_window=truth_window)


# --- ground truth that matches no frame -------------------------------------------------------


def test_ground_truth_stamped_unlike_its_images_is_reported(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Ground truth 1 ms after its images: before, the run said only '0 of 3 frames scored (no
    # ground truth with this stamp in the bag)', as for a bag without its ground truth.
    bag = _bag_with_truth_offset(tmp_path / 'in', 3, 1_000_000)
    code = main(_argv(bag, tmp_path))
    out = capsys.readouterr().out
    assert code == 0
    summary = _summary(tmp_path)
    assert summary['frames_scored'] == 0
    assert summary['gt_unmatched'] == 3
    first = START_NS + 1_000_000
    assert summary['gt_unmatched_stamps'] == [first, first + FRAME_NS, first + 2 * FRAME_NS]
    line = out.splitlines()[0]
    assert '3 ground-truth messages on /ground_truth/disparity matched no processed frame' in line
    assert f'stamps {first}, {first + FRAME_NS}, … ns' in line
    assert f'{first} is 1 ms later than frame stamp {START_NS}' in line
    markdown = (tmp_path / 'report' / 'summary.md').read_text()
    assert 'Ground-truth messages that matched no processed frame: 3' in markdown
    assert str(first + 2 * FRAME_NS) in markdown


def test_ground_truth_of_unpaired_and_skipped_images_is_counted(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Frame 1's right image is 1 µs off (unpaired), frame 2's images have an encoding the node
    # refuses (skipped): their ground truth went unmentioned, the other two frames scored.
    frames = [{}, {'stamp_right': START_NS + FRAME_NS + 1000}, {'encoding': 'yuv422'}, {}]
    bag = write_stereo_bag(tmp_path / 'in', frames)
    code = main(_argv(bag, tmp_path))
    out = capsys.readouterr().out
    assert code == 0
    summary = _summary(tmp_path)
    assert summary['frames_scored'] == 2 and summary['skipped'] == 1
    assert summary['gt_unmatched'] == 2
    assert summary['gt_unmatched_stamps'] == [START_NS + FRAME_NS, START_NS + 2 * FRAME_NS]
    assert '2 ground-truth messages on /ground_truth/disparity matched no processed frame' in out


def test_matching_ground_truth_counts_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = write_stereo_bag(tmp_path / 'in', [{}, {}])
    assert main(_argv(bag, tmp_path)) == 0
    assert 'matched no processed frame' not in capsys.readouterr().out
    summary = _summary(tmp_path)
    assert summary['frames_scored'] == 2
    assert summary['gt_unmatched'] == 0 and summary['gt_unmatched_stamps'] == []
    assert 'matched no processed frame' not in (tmp_path / 'report' / 'summary.md').read_text()


def test_ground_truth_waiting_at_an_early_stop_is_not_counted(tmp_path: Path) -> None:
    # Ground truth read ahead of its frames when the run stops (Ctrl-C) may be of frames
    # further on in the bag: only that which the frames have passed matched none.
    session = _session(tmp_path)
    session.add_ground_truth(100, session_truth(100))
    session.add_result(session_frame(0, 100))
    session.add_ground_truth(150, session_truth(150))  # its frame was skipped, unpaired, ...
    session.add_ground_truth(300, session_truth(300))
    session.add_ground_truth(400, session_truth(400))
    session.add_result(session_frame(1, 200))
    session.report.interrupted = True
    session.finish()
    assert session.counts['gt_unmatched'] == 1
    assert session.report.gt_unmatched_stamps == [150]
    # The same at the end of the bag: none of them can find its frame any more.
    session = _session(tmp_path)
    session.add_ground_truth(100, session_truth(100))
    session.add_result(session_frame(0, 100))
    session.add_ground_truth(300, session_truth(300))
    session.finish()
    assert session.counts['gt_unmatched'] == 1
    assert session.report.gt_unmatched_stamps == [300]


def test_looped_bag_counts_per_pass(tmp_path: Path) -> None:
    # A bag played twice: the second pass repeats the stamps. A second ground truth of one
    # stamp (the frame was scored with the first) is no unmatched one; the ground truth of a
    # frame skipped in the second pass is, although the first pass processed that stamp.
    session = _session(tmp_path)
    session.add_ground_truth(100, session_truth(100))
    session.add_ground_truth(100, session_truth(100))
    session.add_result(session_frame(0, 100))
    session.add_ground_truth(200, session_truth(200))
    session.add_result(session_frame(1, 200))
    session.add_ground_truth(100, session_truth(100, 7.0))  # second pass
    session.add_result(session_frame(2, 100, 7.0))
    session.add_ground_truth(200, session_truth(200, 7.0))
    session.frame_epoch(200)  # frame 3 was skipped
    session.finish()
    scored = {f.frame: f.error_rate for f in session.report.frames}
    assert scored == {0: 0.0, 1: 0.0, 2: 0.0}
    assert session.counts['gt_unmatched'] == 1
    assert session.report.gt_unmatched_stamps == [200]


def test_ground_truth_let_go_for_waiting_too_long_is_taken_back_when_its_frame_comes(
    tmp_path: Path,
) -> None:
    # Ground truth far ahead of its images: the oldest is let go (counted), and when its frame
    # comes after all it did match one.
    session = _session(tmp_path, truth_window=2)
    for stamp in (100, 200, 300):
        session.add_ground_truth(stamp, session_truth(stamp))
    assert session.counts['gt_unmatched'] == 1
    session.add_result(session_frame(0, 100))
    session.add_result(session_frame(1, 200))
    session.add_result(session_frame(2, 300))
    session.finish()
    assert session.counts['gt_unmatched'] == 0
    assert session.report.gt_unmatched_stamps == []
    notes = {f.frame: f.note for f in session.report.frames}
    assert 'was not kept' in notes[0] and notes[1] == notes[2] == ''


def test_unmatched_ground_truth_is_counted_with_bounded_memory(tmp_path: Path) -> None:
    session = _session(tmp_path)
    session.add_result(session_frame(0, 0))
    for index in range(1, 3001):
        session.add_ground_truth(index * 10 + 1, session_truth(index * 10 + 1))
    session.finish()
    assert session.counts['gt_unmatched'] == 3000
    assert session.report.gt_unmatched_stamps == [11, 21, 31, 41, 51]
    summary = session.report.summary()
    assert summary['gt_unmatched'] == 3000 and len(summary['gt_unmatched_stamps']) == 5
    assert '(stamps 11, 21, 31, 41, 51, … ns)' in format_summary(session.report.as_dict())


def test_report_without_the_count_still_formats() -> None:
    # A report of an older run (or one built by hand) has no gt_unmatched count.
    summary = ReplayReport().summary()
    assert summary['gt_unmatched_stamps'] == []
    assert 'matched no processed frame' not in format_summary(ReplayReport().as_dict())


# --- errors that name the option the user typed ------------------------------------------------


@pytest.mark.parametrize(('extra', 'option', 'message'), [
    (('--rate', '0'), '--rate-scale', 'rate_scale must be a finite number > 0; got 0.0'),
    (('--rate', 'nan'), '--rate-scale', 'rate_scale must be a finite number > 0; got nan'),
    (('--queue-size', '0'), '--queue-size', 'queue_size must be >= 1; got 0'),
    (('--max-pixels', '0'), '--max-pixels', 'max_pixels must be >= 1; got 0'),
    (('--max-plots', '-1'), '--max-plots', 'max_plots must be >= 0; got -1'),
    (('--seed', '-1'), '--seed', 'seed must be an integer >= 0; got -1'),
    (('--startup-timeout', '0'), '--startup-timeout', 'timeouts must be'),
    (('--drain-timeout', 'nan'), '--drain-timeout', 'timeouts must be'),
    (('--approximate-sync', '--sync-tolerance', '-1'), '--sync-tolerance',
     'sync tolerance must be a finite number'),
    (('--left-topic', ''), '--left-topic', "topic left must be a non-empty name; got ''"),
    (('--topic-prefix', 'a b'), '--topic-prefix', 'topic prefix must be a valid ROS 2 topic'),
    (('--right-info-topic', '1cam/info'), '--right-info-topic', 'topic right_info must be'),
])
def test_cli_errors_name_the_option(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], extra: tuple[str, ...], option: str,
    message: str,
) -> None:
    bag = write_stereo_bag(tmp_path / 'in', [{}])
    code = main(_argv(bag, tmp_path, '--mode', 'live', '--no-start-node', *extra))
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith(f'cva-bag-replay: error: {option}: ') and message in err, err
    assert len(err.strip().splitlines()) == 1
    assert not (tmp_path / 'out').exists() and not (tmp_path / 'report').exists()


def test_python_api_errors_keep_the_field_names(tmp_path: Path) -> None:
    common = dict(bag=tmp_path / 'in', out=tmp_path / 'out', report=tmp_path / 'report')
    with pytest.raises(ConfigError, match=r'^rate_scale must be a finite number > 0; got 0$') \
            as caught:
        ReplayOptions(**common, rate_scale=0)
    assert caught.value.fields == ('rate_scale',)
    with pytest.raises(ConfigError, match=r'^timeouts must be') as caught:
        ReplayOptions(**common, drain_timeout_s=float('inf'))
    assert caught.value.fields == ('drain_timeout_s',)
    with pytest.raises(ConfigError, match=r'^topic left must be a valid ROS 2 topic name') \
            as caught:
        TopicNames(left='1cam')
    assert caught.value.fields == ('left',)

"""``cva-bag-from-dataset``: data set → rosbag2, checked message by message."""

from __future__ import annotations

from pathlib import Path

from msg_test_utils import (
    DOFFS,
    dataset_bag,
    read_bag,
    synthetic_samples,
    write_middlebury_root,
)
import numpy as np
import pytest

from cva_confidence_ros.datasets import load_dataset
from cva_confidence_ros.errors import ConfigError
from msg_tools.bag_from_dataset import DEFAULT_START_TIME_S, MAX_STAMP_S, BagSpec, main
from msg_tools.convert import disparity_from_msg, stamp_to_ns
from msg_tools.replay import stereo_inputs

TOPICS = {
    '/left/image_rect', '/right/image_rect', '/left/camera_info', '/right/camera_info',
    '/ground_truth/disparity',
}


def test_middlebury_layout_to_mcap(tmp_path: Path) -> None:
    bag = dataset_bag(tmp_path, 'mcap', 3, '--rate', '4')
    assert 'storage_identifier: mcap' in (bag / 'metadata.yaml').read_text()
    messages = read_bag(bag)
    assert set(messages) == TOPICS
    samples = list(load_dataset('middlebury2014', tmp_path / 'data'))
    start = int(DEFAULT_START_TIME_S * 1e9)
    for topic, rows in messages.items():
        assert [t for t, _ in rows] == [start, start + 250_000_000, start + 500_000_000], topic
        assert [stamp_to_ns(m.header.stamp) for _, m in rows] == [t for t, _ in rows]
    for index, sample in enumerate(samples):
        items = {key: messages[f'/{topic}'][index][1] for key, topic in (
            ('left', 'left/image_rect'), ('right', 'right/image_rect'),
            ('left_info', 'left/camera_info'), ('right_info', 'right/camera_info'))}
        left, right, geometry = stereo_inputs(items)
        np.testing.assert_array_equal(left, sample.left)
        np.testing.assert_array_equal(right, sample.right)
        calib = sample.calib
        assert (geometry.fx, geometry.cx, geometry.cy) == (calib.fx, calib.cx, calib.cy)
        assert geometry.baseline == pytest.approx(calib.baseline)
        assert geometry.disparity_offset == pytest.approx(DOFFS)
        assert items['left'].header.frame_id == 'left_camera_optical_frame'
        assert items['right_info'].header.frame_id == 'right_camera_optical_frame'
        gt_msg = messages['/ground_truth/disparity'][index][1]
        assert gt_msg.header.frame_id == 'left_camera_optical_frame'
        assert gt_msg.f == pytest.approx(calib.fx) and gt_msg.t == pytest.approx(calib.baseline)
        # The image holds d + doffs (stereo_image_proc's convention); unknown stays NaN.
        read = disparity_from_msg(gt_msg, offset=DOFFS)
        np.testing.assert_array_equal(np.isnan(read), np.isnan(sample.disparity))
        np.testing.assert_allclose(read, sample.disparity, rtol=0, atol=1e-5)
    sizes = {messages['/left/image_rect'][i][1].width for i in range(3)}
    assert sizes == {56, 48}  # each frame carries its own size


def test_sqlite3_with_prefix_and_calibration_override(tmp_path: Path) -> None:
    bag = dataset_bag(
        tmp_path, 'sqlite3', 1, '--topic-prefix', '/stereo', '--focal', '30',
        '--baseline', '0.5', '--max-frames', '1',
    )
    assert 'storage_identifier: sqlite3' in (bag / 'metadata.yaml').read_text()
    messages = read_bag(bag)
    assert set(messages) == {f'/stereo{topic}' for topic in TOPICS}
    right_info = messages['/stereo/right/camera_info'][0][1]
    assert right_info.p[0] == 30.0 and right_info.p[3] == pytest.approx(-15.0)


def test_missing_calibration_is_assumed_and_said(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = write_middlebury_root(tmp_path / 'data', synthetic_samples(1), calib=False)
    code = main(['--data-root', str(root), '--dataset', 'middlebury2014', '--out',
                 str(tmp_path / 'bag')])
    assert code == 0
    captured = capsys.readouterr()
    assert 'has no calibration' in captured.err
    assert f'wrote 1 frames to {tmp_path / "bag"}' in captured.out
    info = read_bag(tmp_path / 'bag')['/left/camera_info'][0][1]
    assert info.p[0] == info.width == 56  # f = image width
    assert info.p[2] == pytest.approx(27.5)


def test_motorcycle_needs_no_root(tmp_path: Path) -> None:
    assert main(['--dataset', 'motorcycle', '--out', str(tmp_path / 'moto')]) == 0
    messages = read_bag(tmp_path / 'moto')
    assert set(messages) == TOPICS
    assert messages['/left/image_rect'][0][1].encoding == 'rgb8'


@pytest.mark.parametrize(
    ('args', 'message'),
    [
        # A misspelt name is named as such, not as a missing --data-root.
        (['--dataset', 'motorcyle'], "unknown data set 'motorcyle'; expected one of"),
        (['--dataset', 'kitti2015'], '--data-root'),
        (['--dataset', 'motorcycle', '--rate', '0'], 'rate'),
        (['--dataset', 'motorcycle', '--max-frames', '0'], 'max-frames'),
        # Header stamps hold int32 seconds: these would not serialise.
        (['--dataset', 'motorcycle', '--start-time', '3e9'], 'start time must be 0 to'),
        (['--dataset', 'motorcycle', '--rate', '1e-9'], 'rate 1e-09 Hz puts frame 1 at'),
        (['--dataset', 'motorcycle', '--rate', '1e12'], 'at most 1e+09'),
        # Topics ROS 2 could not play.
        (['--dataset', 'motorcycle', '--topic-prefix', 'a b'], 'topic prefix must be a valid'),
        (['--dataset', 'motorcycle', '--topic-prefix', '/1bad//x'], "got '/1bad//x'"),
        (['--dataset', 'motorcycle', '--topic-prefix', '/stereo/2'], 'start with a digit'),
        (['--dataset', 'middlebury2014', '--data-root', 'EMPTY'], 'middlebury2014'),
    ],
)
def test_bad_input_is_one_line_and_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], message: str
) -> None:
    (tmp_path / 'empty').mkdir()
    args = [str(tmp_path / 'empty') if a == 'EMPTY' else a for a in args]
    assert main([*args, '--out', str(tmp_path / 'bag')]) == 2
    err = capsys.readouterr().err
    assert message in err and 'Traceback' not in err
    assert len(err.strip().splitlines()) == 1


def test_existing_output_is_refused_unless_overwritten(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = dataset_bag(tmp_path, 'mcap', 1)
    args = ['--data-root', str(tmp_path / 'data'), '--dataset', 'middlebury2014',
            '--out', str(bag)]
    assert main(args) == 2
    assert 'exists already' in capsys.readouterr().err
    assert main([*args, '--overwrite', '--storage', 'sqlite3']) == 0
    assert 'sqlite3' in (bag / 'metadata.yaml').read_text()


@pytest.mark.parametrize('name', ['notes.mcap', 'notes.db3', 'plain_folder'])
def test_overwrite_refuses_what_is_not_a_bag(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str
) -> None:
    target = tmp_path / name
    if name == 'plain_folder':
        target.mkdir()
        (target / 'keep.txt').write_text('mine\n')
    else:
        target.write_text('mine\n')
    code = main(['--dataset', 'motorcycle', '--out', str(target), '--overwrite'])
    assert code == 2
    err = capsys.readouterr().err
    assert f'refusing to overwrite {target}' in err and len(err.strip().splitlines()) == 1
    assert (target / 'keep.txt' if target.is_dir() else target).read_text() == 'mine\n'


def test_stamps_past_int32_seconds_are_refused() -> None:
    spec = BagSpec(start_time_s=MAX_STAMP_S - 10, rate_hz=1.0)
    assert spec.stamp_ns(10) == MAX_STAMP_S * 10**9
    with pytest.raises(ConfigError, match='frame 11 would be stamped 2147483648 s'):
        spec.stamp_ns(11)
    for bad in ({'start_time_s': MAX_STAMP_S + 1}, {'start_time_s': MAX_STAMP_S, 'rate_hz': 1},
                {'rate_hz': 1e-9}, {'start_time_s': float('nan')}):
        with pytest.raises(ConfigError):
            BagSpec(**bad)


def test_topic_names_are_checked_like_ros2() -> None:
    assert BagSpec(topic_prefix='/stereo/').topic('left/image_rect') == '/stereo/left/image_rect'
    for bad in ({'topic_prefix': 'a b'}, {'topic_prefix': '/1bad//x'},
                {'gt_topic': 'ground truth'}, {'gt_topic': '/'}):
        with pytest.raises(ConfigError):
            BagSpec(**bad)

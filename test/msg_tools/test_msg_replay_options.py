"""Replay options, topic names and the report folder: what is refused before anything runs."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from cva_confidence_ros.errors import ConfigError
from msg_tools.replay import ReplayOptions, TopicNames
from msg_tools.scoring import ReportWriter


def _options(tmp_path: Path, **overrides: Any) -> ReplayOptions:
    values: dict[str, Any] = {
        'bag': tmp_path / 'in', 'out': tmp_path / 'out', 'report': tmp_path / 'report',
    }
    values.update(overrides)
    return ReplayOptions(**values)


@pytest.mark.parametrize(
    ('overrides', 'message'),
    [
        ({'sync_tolerance_s': float('nan')}, 'sync tolerance must be a finite number'),
        ({'sync_tolerance_s': float('inf')}, 'sync tolerance must be a finite number'),
        ({'sync_tolerance_s': 1e300}, 'sync tolerance must be a finite number'),
        ({'sync_tolerance_s': -0.1}, 'sync tolerance must be a finite number'),
        ({'rate_scale': float('nan')}, 'rate_scale must be a finite number > 0'),
        ({'rate_scale': float('inf')}, 'rate_scale must be a finite number > 0'),
        ({'startup_timeout_s': float('nan')}, 'timeouts must be a finite number'),
        ({'startup_timeout_s': float('inf')}, 'timeouts must be a finite number'),
        ({'drain_timeout_s': float('nan')}, 'timeouts must be a finite number'),
        ({'drain_timeout_s': 0.0}, 'timeouts must be a finite number'),
    ],
)
def test_numbers_must_be_finite(tmp_path: Path, overrides: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        _options(tmp_path, **overrides)


@pytest.mark.parametrize('seed', [-1, -(2**40)])
def test_seed_must_not_be_negative(tmp_path: Path, seed: int) -> None:
    # numpy's generators refuse it: the run would fail at its first scored frame.
    with pytest.raises(ConfigError, match=f'seed must be an integer >= 0; got {seed}'):
        _options(tmp_path, seed=seed)
    assert _options(tmp_path, seed=0).seed == 0


def test_output_bag_blocked_by_a_file(tmp_path: Path) -> None:
    plain = tmp_path / 'plain.txt'
    plain.write_text('x')
    with pytest.raises(ConfigError, match=f'cannot create output bag .*: {plain} is a file, not'):
        _options(tmp_path, out=plain / 'a' / 'out')
    assert not (tmp_path / 'report').exists()


def test_finite_numbers_are_accepted(tmp_path: Path) -> None:
    options = _options(tmp_path, approximate_sync=True, sync_tolerance_s=3600.0,
                       rate_scale=0.01, startup_timeout_s=1e6, drain_timeout_s=0.5)
    assert options.sync_tolerance_s == 3600.0


@pytest.mark.parametrize(
    ('bag', 'out', 'report', 'message'),
    [
        ('in', 'in', 'report', 'the output bag must lie outside the input bag'),
        ('in', 'in/in.mcap', 'report', 'the output bag must lie outside the input bag'),
        ('in', 'in/../in/x', 'report', 'the output bag must lie outside the input bag'),
        ('in/in.mcap', 'in', 'report', 'the output bag must not contain the input bag'),
        ('data/runs/in', 'data', 'report', 'the output bag must not contain the input bag'),
        ('in', 'out', 'out', 'the report folder must lie outside the output bag'),
        ('in', 'out', 'out/report', 'the report folder must lie outside the output bag'),
        ('in', 'out', 'in', 'the report folder must lie outside the input bag'),
        ('in', 'out', 'in/report', 'the report folder must lie outside the input bag'),
    ],
)
def test_outputs_must_not_overlap_the_input_or_each_other(
    tmp_path: Path, bag: str, out: str, report: str, message: str
) -> None:
    with pytest.raises(ConfigError, match=message):
        _options(tmp_path, bag=tmp_path / bag, out=tmp_path / out, report=tmp_path / report)


def test_separate_or_nested_outputs_are_accepted(tmp_path: Path) -> None:
    _options(tmp_path, out=tmp_path / 'run' / 'bag', report=tmp_path / 'run')
    _options(tmp_path, bag=tmp_path / 'bags' / 'in', out=tmp_path / 'bags' / 'out')
    # A relative and an absolute spelling of the same folder are the same folder.
    _options(tmp_path, bag=Path('in_relative'), out=tmp_path / 'out')
    with pytest.raises(ConfigError, match='outside the input bag'):
        _options(tmp_path, bag=Path('in_relative'), out=Path.cwd() / 'in_relative')


def test_report_folder_blocked_by_a_file(tmp_path: Path) -> None:
    plain = tmp_path / 'plain.txt'
    plain.write_text('x')
    with pytest.raises(ConfigError, match=f'the report folder {plain} is a file'):
        _options(tmp_path, report=plain)
    with pytest.raises(ConfigError, match=f'cannot create the report folder .*: {plain} is a'):
        _options(tmp_path, report=plain / 'a' / 'b')
    # The writer itself says the same when used directly.
    with pytest.raises(ConfigError, match=f'the report folder {plain} is a file'):
        ReportWriter(plain)
    with pytest.raises(ConfigError, match='cannot create the report folder .*NotADirectoryError'):
        ReportWriter(plain / 'sub')
    assert ReportWriter(tmp_path / 'new' / 'report').folder.is_dir()


@pytest.mark.parametrize(
    ('fields', 'message'),
    [
        ({'prefix': 'a b'}, "topic prefix must be a valid ROS 2 topic name .*got '/a b'"),
        ({'prefix': '/1bad//x'}, 'topic prefix must be a valid ROS 2 topic name'),
        ({'left': 'left image'}, 'topic left must be a valid ROS 2 topic name'),
        ({'right': '/cam/1/image'}, 'topic right .*start with a digit'),
        ({'ground_truth': 'gt~'}, 'topic ground_truth'),
        ({'disparity': '/'}, 'topic disparity must be a non-empty name'),
    ],
)
def test_topic_names_follow_ros2_rules(fields: dict[str, str], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        TopicNames(**fields)


def test_valid_topic_names_resolve() -> None:
    names = TopicNames(prefix='/stereo/', left='/cam0/image', right='right/image_rect/')
    assert names.inputs()['left'] == '/cam0/image'
    assert names.inputs()['right'] == '/stereo/right/image_rect'
    assert names.outputs()['points'] == '/stereo/points2'


def test_topic_plan_names_the_image_transport_and_refuses_a_mixed_pair() -> None:
    from msg_tools.convert import CAMERA_INFO, COMPRESSED_IMAGE, IMAGE
    from msg_tools.replay import TopicPlan

    inputs = {'left': '/l', 'right': '/r', 'left_info': '/li', 'right_info': '/ri'}

    def plan(left: str, right: str) -> TopicPlan:
        types = {'/l': left, '/r': right, '/li': CAMERA_INFO, '/ri': CAMERA_INFO}
        return TopicPlan(inputs=inputs, input_types=types, ground_truth=None,
                         ground_truth_type='', pairs_expected=1, input_counts={})

    assert plan(IMAGE, IMAGE).image_transport == 'raw'
    assert plan(COMPRESSED_IMAGE, COMPRESSED_IMAGE).image_transport == 'compressed'
    with pytest.raises(ConfigError, match='one image_transport'):
        _ = plan(COMPRESSED_IMAGE, IMAGE).image_transport

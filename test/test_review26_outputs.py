"""Review regressions: output paths that cannot even be looked at, and the cloud filter's
diagnostics period beyond what a ROS timer can count."""

from __future__ import annotations

from pathlib import Path

import pytest

from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.outputs import check_output_dir, check_output_file

# One path component longer than any file system's NAME_MAX (255): stat() fails with
# ENAMETOOLONG, which pathlib's is_dir()/exists() pass on instead of answering False.
LONG = 'a' * 300


def test_a_name_too_long_is_a_config_error_not_an_os_error(tmp_path: Path) -> None:
    # Used to raise OSError [Errno 36] from Path.is_dir(): a traceback from cva-benchmark
    # --json, which catches only CVAError around the check.
    too_long = r': cannot use this path \(File name too long\)'
    with pytest.raises(ConfigError, match=r'^--json .*' + too_long):
        check_output_file(tmp_path / f'{LONG}.json', '--json')
    with pytest.raises(ConfigError, match=r'^--out .*' + too_long):
        check_output_dir(tmp_path / LONG, '--out')
    # The long name in a folder above the file: the look for the first existing folder fails.
    with pytest.raises(ConfigError, match=r'^--json .*records.json: cannot use this path'):
        check_output_file(tmp_path / LONG / 'records.json', '--json')
    assert list(tmp_path.iterdir()) == []


def test_paths_that_can_be_looked_at_are_still_checked_as_before(tmp_path: Path) -> None:
    assert check_output_file(tmp_path / 'a' / 'r.json', '--json') == tmp_path / 'a' / 'r.json'
    with pytest.raises(ConfigError, match='is a folder; expected a file path'):
        check_output_file(tmp_path, '--json')
    (tmp_path / 'f').write_text('x')
    with pytest.raises(ConfigError, match='is a file; expected a folder'):
        check_output_dir(tmp_path / 'f', '--out')


@pytest.mark.parametrize('period', [1e10, 1e300, 1e-10])
def test_cloud_filter_period_must_fit_a_ros_timer(period: float) -> None:
    # rclpy's timers count whole nanoseconds in an int64: 1e300 s used to end the start with
    # an OverflowError traceback (1e10 s with a TypeError), 1e-10 s made a timer of period 0
    # that fires without pause.
    pytest.importorskip('rclpy')
    from cva_confidence_ros.ros.cloud_filter_node import CloudFilterConfig

    with pytest.raises(ConfigError, match='diagnostics_period_seconds must be in'):
        CloudFilterConfig(diagnostics_period_seconds=period)


def test_cloud_filter_node_refuses_a_period_too_long_with_a_config_error() -> None:
    rclpy = pytest.importorskip('rclpy')
    from rclpy.context import Context
    from rclpy.parameter import Parameter

    from cva_confidence_ros.ros.cloud_filter_node import CloudFilterConfig, CloudFilterNode

    assert CloudFilterConfig(diagnostics_period_seconds=9.2e9).diagnostics_period_seconds == 9.2e9
    context = Context()
    rclpy.init(context=context)
    try:
        with pytest.raises(ConfigError, match='diagnostics_period_seconds'):
            CloudFilterNode(
                context=context,
                parameter_overrides=[Parameter('diagnostics_period_seconds', value=1e300)],
            )
    finally:
        rclpy.shutdown(context=context)

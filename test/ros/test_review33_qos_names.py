"""Review 33 of the QoS override errors: the topic as the user keyed it, one line."""

from __future__ import annotations

from test_node_arguments import _call

from cva_confidence_ros.ros.common import EXIT_BAD_START


def test_a_zero_depth_in_a_namespace_is_one_line_naming_the_resolved_topic() -> None:
    # The user set qos_overrides./stereo/points2...; the error named 'points2', and rclpy's
    # two-line UserWarning about a zero depth came before the 'cannot start' line.
    done = _call('cva-cloud-filter', '--ros-args', '-r', '__ns:=/stereo',
                 '-p', 'qos_overrides./stereo/points2.subscription.depth:=0')
    assert done.returncode == EXIT_BAD_START, done.stdout + done.stderr
    assert 'cannot start: QoS override of /stereo/points2: ' in done.stderr, done.stderr
    assert 'UserWarning' not in done.stderr and 'zero depth' not in done.stderr, done.stderr

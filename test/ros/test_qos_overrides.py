"""ROS 2's per-topic QoS overrides (``qos_overrides.<topic>.<entity>.<policy>``) on the node,
the managed node and the cloud filter, over real DDS."""

from __future__ import annotations

from pathlib import Path
import time

from node_test_utils import (
    Spinner,
    StereoClient,
    localhost_context,
    spare_domain_id,
    textured_pair,
)
import pytest
from rclpy.lifecycle import TransitionCallbackReturn
from rclpy.parameter import Parameter
from rclpy.qos import HistoryPolicy, ReliabilityPolicy

from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.node import ConfidenceNode
from cva_confidence_ros.ros.cloud_filter_node import CloudFilterNode
from cva_confidence_ros.ros.lifecycle_node import ManagedConfidenceNode

pytestmark = pytest.mark.timeout(120)

BASE = [
    Parameter('matcher', value='census_bm'),
    Parameter('max_disparity', value=16),
    Parameter('confidence_method', value='mlm'),
]


def _override(topic: str, entity: str, policy: str, value: object) -> Parameter:
    return Parameter(f'qos_overrides.{topic}.{entity}.{policy}', value=value)


def _qos(node, topic: str, entity: str):
    """The profile the node's publisher or subscription of ``topic`` was made with; its
    reliability checked against what the graph (DDS discovery) shows, which carries no depth."""
    made = node.publishers if entity == 'publisher' else node.subscriptions
    (profile,) = [item.qos_profile for item in made if item.topic_name == topic]
    infos = (node.get_publishers_info_by_topic if entity == 'publisher'
             else node.get_subscriptions_info_by_topic)(topic)
    (info,) = [i for i in infos if i.node_name == node.get_name()]
    assert info.qos_profile.reliability == profile.reliability
    return profile


def test_each_topic_takes_its_own_overrides_and_the_frames_still_flow() -> None:
    overrides = [
        *BASE,
        _override('/left/image_rect', 'subscription', 'reliability', 'reliable'),
        _override('/left/image_rect', 'subscription', 'depth', 2),
        _override('/confidence', 'publisher', 'reliability', 'best_effort'),
        _override('/confidence', 'publisher', 'depth', 1),
        _override('/points2', 'publisher', 'history', 'keep_all'),
    ]
    with localhost_context(spare_domain_id()) as context:
        node = ConfidenceNode(context=context, parameter_overrides=overrides)
        client = StereoClient(context)
        spinner = Spinner(context, node, client.node)
        try:
            left = _qos(node, '/left/image_rect', 'subscription')
            assert (left.reliability, left.depth) == (ReliabilityPolicy.RELIABLE, 2)
            # The other inputs keep the sensor_data preset (the profiles are not shared).
            for topic in ('/right/image_rect', '/left/camera_info', '/right/camera_info'):
                other = _qos(node, topic, 'subscription')
                assert (other.reliability, other.depth) == (ReliabilityPolicy.BEST_EFFORT, 5)
            confidence = _qos(node, '/confidence', 'publisher')
            assert (confidence.reliability, confidence.depth) == (ReliabilityPolicy.BEST_EFFORT, 1)
            assert _qos(node, '/points2', 'publisher').history == HistoryPolicy.KEEP_ALL
            for topic in ('/disparity', '/depth', '/scan', '/camera_info'):
                output = _qos(node, topic, 'publisher')
                assert (output.reliability, output.depth) == (ReliabilityPolicy.RELIABLE, 10)
            # Declared as ROS 2 declares them: read-only, with the preset's value by default.
            name = 'qos_overrides./right/image_rect.subscription.reliability'
            assert node.get_parameter(name).value == 'best_effort'
            assert node.describe_parameter(name).read_only
            assert not node.set_parameters([Parameter(name, value='reliable')])[0].successful
            left_image, right_image = textured_pair(seed=4)
            out = client.send_until_output(left_image, right_image, 5_000_000_000,
                                           topics=('disparity', 'points2'))
            assert out['disparity'].image.height == 64
        finally:
            spinner.stop()
            node.destroy_node()
            client.node.destroy_node()


@pytest.mark.parametrize(
    ('override', 'message'),
    [
        (_override('/left/image_rect', 'subscription', 'reliability', 'sometimes'),
         'QoS override of /left/image_rect: .*reliability.*sometimes.*expected reliability'),
        (_override('/disparity', 'publisher', 'depth', 0),
         'QoS override of /disparity: .*depth must be >= 1 with history keep_last; got 0'),
    ],
)
def test_a_bad_override_stops_the_start_with_the_topic_named(override, message) -> None:
    with localhost_context(spare_domain_id()) as context:
        with pytest.raises(ConfigError, match=message):
            ConfidenceNode(context=context, parameter_overrides=[*BASE, override])


def test_the_managed_node_refuses_a_bad_override_and_keeps_nothing() -> None:
    bad_output = _override('/depth', 'publisher', 'reliability', 'never')
    with localhost_context(spare_domain_id()) as context:
        node = ManagedConfidenceNode(context=context, parameter_overrides=[*BASE, bad_output])
        try:
            assert node.trigger_configure() == TransitionCallbackReturn.FAILURE
            assert not node.configured
            # made before /depth, then dropped (the node's own list: the graph may still hold
            # a participant of an earlier test in this domain)
            assert not [pub for pub in node.publishers if pub.topic_name == '/disparity']
        finally:
            node.destroy_node()
    bad_input = _override('/right/camera_info', 'subscription', 'history', 'some')
    with localhost_context(spare_domain_id()) as context:
        node = ManagedConfidenceNode(context=context, parameter_overrides=[*BASE, bad_input])
        try:
            assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
            assert node.trigger_activate() == TransitionCallbackReturn.FAILURE  # the inputs'
            assert not [sub for sub in node.subscriptions
                        if sub.topic_name == '/left/image_rect']
            time.sleep(0.1)
            assert node.configured
        finally:
            node.destroy_node()


def test_cloud_filter_overrides_and_a_parameter_file(tmp_path: Path) -> None:
    # The nested form of a parameter file, as the ROS 2 documentation writes it (and the
    # README's flow form).
    params = tmp_path / 'filter.yaml'
    params.write_text(
        '/**:\n  ros__parameters:\n    qos_overrides:\n      /points2:\n        subscription:\n'
        '          reliability: reliable\n          depth: 3\n'
        '      /points2_filtered:\n        publisher: {reliability: best_effort, depth: 1}\n'
    )
    with localhost_context(spare_domain_id()) as context:
        node = CloudFilterNode(context=context, cli_args=['--ros-args', '--params-file',
                                                          str(params)])
        try:
            points = _qos(node, '/points2', 'subscription')
            assert (points.reliability, points.depth) == (ReliabilityPolicy.RELIABLE, 3)
            filtered = _qos(node, '/points2_filtered', 'publisher')
            assert (filtered.reliability, filtered.depth) == (ReliabilityPolicy.BEST_EFFORT, 1)
        finally:
            node.destroy_node()

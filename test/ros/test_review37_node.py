"""Review 37 of the node on a running robot: parameters changed at run time around lifecycle
transitions, camera drivers that stop and restart (regression tests of the faults found)."""

from __future__ import annotations

import time

from diagnostic_msgs.msg import DiagnosticStatus
from node_test_utils import (
    SMALL_MLM,
    StereoClient,
    first_stamp,
    image_msg,
    info_msgs,
    node_and_client,
    set_parameters_by_service,
    textured_pair,
)
import pytest
from rclpy.lifecycle import TransitionCallbackReturn
from rclpy.parameter import Parameter
from sensor_msgs.msg import Image

from cva_confidence_ros.node import ConfidenceNode, ManagedConfidenceNode
from cva_confidence_ros.ros.dds_profile import PROFILE_VARIABLES

pytestmark = pytest.mark.timeout(120)

#: No /diagnostics timer window in the way: the tests call diagnostics() themselves.
_QUIET = Parameter('diagnostics_period_seconds', value=600.0)


def _quiet_node(context: object) -> ConfidenceNode:
    return ConfidenceNode(context=context, parameter_overrides=[*SMALL_MLM, _QUIET])


def test_a_deactivate_forgets_the_image_size_parameter_changes_are_checked_against() -> None:
    # After deactivate and activate (a camera restarted at 160 px wide), max_disparity 96 was
    # refused as too wide for the 64 px images seen before the deactivate.
    with node_and_client(
        lambda context: ManagedConfidenceNode(context=context, parameter_overrides=list(SMALL_MLM))
    ) as (node, client):
        assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
        assert node.trigger_activate() == TransitionCallbackReturn.SUCCESS
        assert client.wait_connected()
        left, right = textured_pair(48, 64)
        client.send_until_output(left, right, first_stamp(), topics=('disparity',))
        # Active, with 64 px images coming: refused, naming the images it is judged by.
        (refused,) = set_parameters_by_service(client.node, max_disparity=96)
        assert not refused.successful
        assert 'image width 64; got 96' in refused.reason
        assert '64×48 px' in refused.reason
        assert node.trigger_deactivate() == TransitionCallbackReturn.SUCCESS
        assert node.trigger_activate() == TransitionCallbackReturn.SUCCESS
        (accepted,) = set_parameters_by_service(client.node, max_disparity=96)
        assert accepted.successful, accepted.reason
        assert node.pipeline_config.max_disparity == 96
        # The camera back at 160×120: processed with it.
        wide_left, wide_right = textured_pair(120, 160)
        client.send_until_output(
            wide_left, wide_right, first_stamp() + 10**10, topics=('disparity',)
        )


def _infos_only(client: StereoClient, stamp: int, count: int) -> None:
    """Publish ``count`` pairs of camera infos (no images), 50 ms apart."""
    for i in range(count):
        left_info, right_info = info_msgs(stamp + i * 10**8, 48, 64)
        client.pubs['left_info'].publish(left_info)
        client.pubs['right_info'].publish(right_info)
        time.sleep(0.05)


def _unpaired_message(node: ConfidenceNode, client: StereoClient, stamp: int) -> str:
    """The status message of a window in which only camera infos came."""
    node.diagnostics()  # a new window
    _infos_only(client, stamp, 10)
    time.sleep(0.3)
    return str(node.diagnostics().message)


@pytest.fixture
def no_dds_profile(monkeypatch: pytest.MonkeyPatch) -> None:
    """No large-message DDS profile set: the 512 kB hint is given only without one."""
    for name in PROFILE_VARIABLES:
        monkeypatch.delenv(name, raising=False)


@pytest.mark.usefixtures('no_dds_profile')
def test_images_that_stopped_while_the_camera_infos_come_are_not_called_too_large() -> None:
    # A rectifier stopped (its camera driver's infos still coming): 64×48 images had arrived,
    # and the status blamed images over 512 kB lost by Fast DDS.
    with node_and_client(_quiet_node) as (node, client):
        assert client.wait_connected()
        left, right = textured_pair(48, 64)
        stamp = first_stamp()
        client.send_until_output(left, right, stamp, topics=('disparity',))
        message = _unpaired_message(node, client, stamp + 10**10)
        assert message.startswith('messages arrive but none pair up'), message
        assert 'stopped (their publisher stopped sending, or was restarted?)' in message
        assert 'come: images over 512 kB' not in message


@pytest.mark.usefixtures('no_dds_profile')
def test_images_without_a_publisher_are_not_called_too_large() -> None:
    # No image publisher at all (the rectifier not started, a wrong topic name) and the camera
    # infos coming: the status blamed images over 512 kB lost by Fast DDS. Images that never
    # come from a publisher there is keep the hint.
    with node_and_client(_quiet_node) as (node, client):
        assert client.wait_connected()
        stamp = first_stamp()
        message = _unpaired_message(node, client, stamp)
        assert '512 kB' in message, message  # publishers there, nothing ever came
        for key in ('left', 'right'):
            client.node.destroy_publisher(client.pubs.pop(key))
        deadline = time.monotonic() + 10.0
        while node.count_publishers('left/image_rect') and time.monotonic() < deadline:
            time.sleep(0.05)
        message = _unpaired_message(node, client, stamp + 10**10)
        assert 'no publisher on left/image_rect, right/image_rect' in message, message
        assert '512 kB' not in message


def test_a_second_camera_on_the_left_topic_is_warned_about() -> None:
    # A second camera publishing on left/image_rect by mistake (3 ms apart), approximate sync:
    # most frames paired its image with the first camera's right one (wrong disparities), and
    # the status said 'processing at 10.0 Hz', level OK.
    overrides = [
        *SMALL_MLM, _QUIET, Parameter('approximate_sync', value=True),
        Parameter('approximate_sync_tolerance_seconds', value=0.02),
    ]
    with node_and_client(
        lambda context: ConfidenceNode(context=context, parameter_overrides=overrides)
    ) as (node, client):
        assert client.wait_connected()
        assert node.diagnostics().message.startswith('processing at')
        second = client.node.create_publisher(Image, 'left/image_rect', 10)
        deadline = time.monotonic() + 10.0
        while node.count_publishers('left/image_rect') < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
        left, right = textured_pair(48, 64)
        other, _ = textured_pair(120, 160, seed=5)
        stamp = first_stamp()
        for k in range(3):
            second.publish(image_msg(other, stamp + k * 10**8 + 3 * 10**6))
            client.publish_frame(left, right, stamp + k * 10**8)
            time.sleep(0.05)
        status = node.diagnostics()
        assert status.level == DiagnosticStatus.WARN
        assert status.message.startswith(
            'more than one publisher on left/image_rect (2): two cameras'
        ), status.message
        client.node.destroy_publisher(second)
        deadline = time.monotonic() + 10.0
        while node.count_publishers('left/image_rect') > 1 and time.monotonic() < deadline:
            time.sleep(0.05)
        client.publish_frame(left, right, stamp + 10**9)
        time.sleep(0.3)
        assert 'more than one publisher' not in node.diagnostics().message

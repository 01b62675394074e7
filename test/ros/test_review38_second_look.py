"""Review 38, a second look at the node's late changes under simulated time: regression tests
of the faults found (a ``/clock`` of the test's own, as ``ros2 bag play --loop --clock``)."""

from __future__ import annotations

from collections.abc import Callable
import time
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from node_test_utils import SMALL_MLM, node_and_client, wait_until
import pytest
from rclpy.lifecycle import TransitionCallbackReturn
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile
from rosgraph_msgs.msg import Clock

from cva_confidence_ros.node import ConfidenceNode, ManagedConfidenceNode
from cva_confidence_ros.ros.convert import ns_to_stamp

pytestmark = pytest.mark.timeout(120)

_PERIOD_S = 0.5
_PARAMETERS = [
    *SMALL_MLM,
    Parameter('use_sim_time', value=True),
    Parameter('diagnostics_period_seconds', value=_PERIOD_S),
]


def _plain(context: Any) -> ConfidenceNode:
    return ConfidenceNode(context=context, parameter_overrides=list(_PARAMETERS))


def _managed(context: Any) -> ManagedConfidenceNode:
    return ManagedConfidenceNode(
        context=context, parameter_overrides=[*_PARAMETERS, Parameter('autostart', value=True)]
    )


def _play_loop(clock: Any, loop_s: float, seconds: float) -> None:
    """Publish /clock as a bag of ``loop_s`` seconds played on a loop at real speed."""
    start = time.monotonic()
    while (elapsed := time.monotonic() - start) < seconds:
        clock.publish(Clock(clock=ns_to_stamp(100 * 10**9 + int((elapsed % loop_s) * 1e9))))
        time.sleep(0.01)


@pytest.mark.parametrize('make', [_plain, _managed], ids=['node', 'lifecycle'])
def test_diagnostics_go_on_under_a_bag_loop_shorter_than_their_period(
    make: Callable[[Any], Any],
) -> None:
    # A bag of 0.2 s on a loop, diagnostics every 0.5 s of simulated time: rcl's timer waits a
    # whole period of the new time after each jump back, which the loop never reaches, so
    # /diagnostics went mute after the first loop (0 statuses in 3 s), without a word.
    with node_and_client(make) as (node, client):
        client.subscribe('/diagnostics', DiagnosticArray)
        clock = client.node.create_publisher(Clock, '/clock', QoSProfile(depth=10))
        assert wait_until(lambda: clock.get_subscription_count() > 0)
        _play_loop(clock, 0.2, 1.0)
        before = len(client.received['/diagnostics'])
        _play_loop(clock, 0.2, 3.0)
        assert len(client.received['/diagnostics']) - before >= 3
        if isinstance(node, ManagedConfidenceNode):
            # Cleaned up: the clock's jumps publish nothing (and raise nothing).
            assert node.trigger_deactivate() == TransitionCallbackReturn.SUCCESS
            assert node.trigger_cleanup() == TransitionCallbackReturn.SUCCESS
            time.sleep(0.3)
            before = len(client.received['/diagnostics'])
            _play_loop(clock, 0.2, 1.5)
            assert len(client.received['/diagnostics']) == before
            assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
            _play_loop(clock, 0.2, 2.0)
            assert len(client.received['/diagnostics']) - before >= 2

"""Review 37 of the node under simulated time (``use_sim_time``, a ``/clock`` of the test's
own, as Gazebo or ``ros2 bag play --clock`` publish it): regression tests of the faults found."""

from __future__ import annotations

from collections.abc import Callable
import time
from typing import Any

from node_test_utils import (
    SMALL_MLM,
    feed_frame,
    node_and_client,
    textured_pair,
    wait_until,
)
import pytest
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile
from rosgraph_msgs.msg import Clock

from cva_confidence_ros.node import ConfidenceNode, ManagedConfidenceNode
from cva_confidence_ros.ros.convert import ns_to_stamp

pytestmark = pytest.mark.timeout(120)

_SECOND = 1_000_000_000
_PARAMETERS = [
    *SMALL_MLM,
    Parameter('use_sim_time', value=True),
    # No timer window in the way: the test calls diagnostics() itself (600 s of simulated
    # time never pass here).
    Parameter('diagnostics_period_seconds', value=600.0),
]


def _plain(context: Any) -> ConfidenceNode:
    return ConfidenceNode(context=context, parameter_overrides=list(_PARAMETERS))


def _managed(context: Any) -> ManagedConfidenceNode:
    return ManagedConfidenceNode(
        context=context, parameter_overrides=[*_PARAMETERS, Parameter('autostart', value=True)]
    )


def _rate(node: Any) -> float:
    values = {kv.key: kv.value for kv in node.diagnostics().values}
    return float(values['processing_rate_hz'])


@pytest.mark.parametrize('make', [_plain, _managed], ids=['node', 'lifecycle'])
def test_the_processing_rate_is_per_second_of_simulated_time(
    make: Callable[[Any], Any],
) -> None:
    # The diagnostics timer ticks on the node's clock (simulated time), but the rate of its
    # window was counted per wall second: a 10 Hz camera read 20 Hz at 2× real time (and
    # max_rate_hz 5, per second of stamp time, read 10 Hz), 5 Hz at 0.5×, and 6.7 Hz or less
    # for the period in which the simulation paused for 1.5 s.
    with node_and_client(make) as (node, client):
        clock = client.node.create_publisher(Clock, '/clock', QoSProfile(depth=10))
        assert wait_until(lambda: clock.get_subscription_count() > 0)

        def sim_time(ns: int) -> None:
            def there() -> bool:
                clock.publish(Clock(clock=ns_to_stamp(ns)))
                return node.get_clock().now().nanoseconds == ns

            assert wait_until(there, poll=0.05), f'the node never reached simulated time {ns}'

        left, right = textured_pair(48, 64)

        def frames(start_ns: int, count: int) -> None:
            # A 10 Hz camera in the simulation, each frame processed before the next one.
            for i in range(count):
                stamp = start_ns + i * _SECOND // 10
                sim_time(stamp)
                done = node.stats()['frames_processed'] + 1
                feed_frame(node, left, right, stamp)
                assert wait_until(lambda done=done: node.stats()['frames_processed'] >= done)

        sim_time(100 * _SECOND)
        node.diagnostics()  # the window starts at simulated 100 s
        frames(100 * _SECOND, 10)
        sim_time(101 * _SECOND)
        time.sleep(1.5)  # the simulation paused: no simulated time passes
        assert _rate(node) == pytest.approx(10.0)
        # A simulator reset (the clock back to 5 s): a rate of the wall time taken, not a
        # negative or endless one; the next window is per simulated second again.
        sim_time(5 * _SECOND)
        frames(5 * _SECOND, 1)
        assert 0.0 < _rate(node) < 100.0
        frames(5 * _SECOND + _SECOND // 10, 5)
        sim_time(5 * _SECOND + 5 * _SECOND // 10)
        assert _rate(node) == pytest.approx(10.0)


def test_sim_time_without_a_clock_is_said_once(monkeypatch: pytest.MonkeyPatch) -> None:
    # use_sim_time and no /clock (a bag played without --clock): the diagnostics timer never
    # fires, and nothing said why /diagnostics stayed mute.
    from rcl_interfaces.msg import Log

    from cva_confidence_ros.ros import confidence_node

    monkeypatch.setattr(confidence_node, 'CLOCK_WAIT_S', 0.2)
    overrides = [*SMALL_MLM, Parameter('use_sim_time', value=True),
                 Parameter('diagnostics_period_seconds', value=0.2)]
    with node_and_client(
        lambda context: ConfidenceNode(context=context, parameter_overrides=overrides)
    ) as (node, client):
        # Transient local, as rcl's /rosout: the line may come before discovery.
        client.subscribe('/rosout', Log, QoSProfile(
            depth=100, durability=DurabilityPolicy.TRANSIENT_LOCAL
        ))

        def said() -> list[str]:
            return [m.msg for m in list(client.received['/rosout'])
                    if m.msg.startswith('use_sim_time is true and no /clock has come')]

        assert client.wait_for(lambda: bool(said()), timeout=10.0)
        time.sleep(0.6)
        assert len(said()) == 1
        assert not client.received.get('/diagnostics')

"""Review 27 of the ROS node: stamps that repeat or go back, leaks on destroy, a managed node
refused at start-up (each a regression test of a fault found in the review)."""

from __future__ import annotations

from collections.abc import Iterator
import gc
import os
import time
from typing import Any
import weakref

from diagnostic_msgs.msg import DiagnosticArray
from node_test_utils import (
    Spinner,
    StereoClient,
    first_stamp,
    localhost_context,
    rosout_reaches,
    running_nodes,
    spare_domain_id,
    textured_pair,
)
import pytest
from rcl_interfaces.msg import Log
from rclpy.context import Context
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile

from cva_confidence_ros.node import ConfidenceNode, ManagedConfidenceNode

pytestmark = pytest.mark.timeout(120)

# A namespace of its own: no other test's node or client shares these topics.
NAMESPACE = f'review27_{os.getpid()}'
OVERRIDES = [
    Parameter('matcher', value='census_bm'),
    Parameter('max_disparity', value=16),
    Parameter('confidence_method', value='mlm'),
]


class _Running:
    def __init__(self, context: Context) -> None:
        self.node = ConfidenceNode(
            context=context,
            namespace=NAMESPACE,
            parameter_overrides=[*OVERRIDES, Parameter('diagnostics_period_seconds', value=0.2)],
        )
        self.client = StereoClient(context, namespace=NAMESPACE)
        self.client.subscribe('/diagnostics', DiagnosticArray)
        self.client.subscribe('/rosout', Log, QoSProfile(depth=100))
        self.spinner = Spinner(context, self.node, self.client.node)
        self.stamp = first_stamp()
        assert self.client.wait_connected(), 'the node and the client did not discover'

    def next_stamp(self) -> int:
        self.stamp += 100 * 10**9
        return self.stamp

    def statuses(self, text: str) -> list[str]:
        """Messages of the node's ``/diagnostics`` statuses that contain ``text``."""
        name = self.node.get_fully_qualified_name()
        return [
            status.message
            for array in list(self.client.received['/diagnostics'])
            for status in array.status
            if status.hardware_id == name and text in status.message
        ]

    def logged(self, text: str) -> list[str]:
        """The node's ``/rosout`` warnings that contain ``text``."""
        name = self.node.get_logger().name
        return [
            msg.msg
            for msg in list(self.client.received['/rosout'])
            if msg.name == name and msg.level == Log.WARN and text in msg.msg
        ]

    def paired(self, stamp: int) -> int:
        """Publish a frame at ``stamp`` until it comes out; the stamp that did."""
        left, right = textured_pair(seed=27)
        out = self.client.send_until_output(left, right, stamp, topics=('disparity',))
        header = out['disparity'].header
        return header.stamp.sec * 10**9 + header.stamp.nanosec

    def send(self, stamp: int) -> None:
        """Publish a frame at ``stamp`` in a diagnostics period of its own."""
        time.sleep(2 * self.node.node_config.diagnostics_period_seconds)
        left, right = textured_pair(seed=27)
        self.client.publish_frame(left, right, stamp)


@pytest.fixture(scope='module')
def running() -> Iterator[_Running]:
    with running_nodes(spare_domain_id(), _Running) as state:
        yield state


def _seconds(stamp_ns: int) -> str:
    return f'{stamp_ns // 10**9}.{stamp_ns % 10**9:09d}'


def test_a_frame_played_again_is_reported_as_repeated_stamps_not_as_sync(
    running: _Running,
) -> None:
    # A bag of one frame played a second time: the frame the node paired last, again. Its
    # messages wait aside as repeats, and the status said 'exact sync pairs equal stamps only
    # (approximate_sync: true ...)' of four equal stamps.
    stamp = running.paired(running.next_stamp())
    running.send(stamp)
    wanted = f'the input stamps repeat: left/image_rect {_seconds(stamp)} again'
    assert running.client.wait_for(lambda: bool(running.statuses(wanted)), 10.0), (
        running.statuses('none pair up')
    )
    (message, *_) = running.statuses(wanted)
    assert message.startswith('messages arrive but none pair up: ')
    assert 'exact sync' not in message and 'approximate' not in message
    # Played a third time: a loop of one frame, paired again and logged as a repeat (it was
    # 'input stamps jumped back 0.000 s').
    running.send(stamp)
    logged = f'input stamps repeat: the frame {_seconds(stamp)} came again'
    assert running.client.wait_for(lambda: bool(running.logged(logged)), 10.0)
    assert not running.logged('jumped back 0.000 s')


def test_a_bag_played_again_from_its_start_says_how_far_the_stamps_went_back(
    running: _Running,
) -> None:
    first = running.paired(running.next_stamp())
    later = first + 600_000_000
    running.send(later)
    assert running.client.wait_for(
        lambda: running.client.by_stamp('disparity', later) is not None, 10.0
    )
    running.send(first)  # the start of the bag again, 0.6 s back: held aside, not paired yet
    wanted = f'the input stamps went back 0.600 s: left/image_rect {_seconds(first)} after'
    assert running.client.wait_for(lambda: bool(running.statuses(wanted)), 10.0), (
        running.statuses('none pair up')
    )
    (message, *_) = running.statuses(wanted)
    assert _seconds(later) in message and 'exact sync' not in message
    # Later frames, newer again, pair as before.
    running.paired(running.next_stamp())


def _destroyed(make: Any) -> tuple[weakref.ref, weakref.ref]:
    """Weak references to a node ``make()`` builds and to its pipeline, once it is destroyed
    (in a function of its own: no frame of the test holds the node)."""
    node = make()
    refs = weakref.ref(node), weakref.ref(node._pipeline)
    node.destroy_node()
    return refs


@pytest.mark.parametrize('managed', [False, True], ids=['node', 'managed'])
def test_a_destroyed_node_and_its_pipeline_are_freed_while_the_context_lives(
    managed: bool,
) -> None:
    # The context's shutdown callback was a lambda holding the node: a node destroyed in a
    # process that goes on (a launch of several, a component-like host, the tests) kept its
    # pipeline (the network's weights, GPU memory) until the context shut down.
    with localhost_context(spare_domain_id()) as context:
        if managed:
            overrides = [*OVERRIDES, Parameter('autostart', value=True)]
            refs = _destroyed(
                lambda: ManagedConfidenceNode(context=context, parameter_overrides=overrides)
            )
        else:
            refs = _destroyed(
                lambda: ConfidenceNode(context=context, parameter_overrides=list(OVERRIDES))
            )
        gc.collect()
        assert [ref() is None for ref in refs] == [True, True]


def _refused(context: Context, overrides: list[Parameter]) -> str:
    """Build a managed node that refuses its start-up parameters; the error's name (the
    exception itself is not kept: its traceback would hold the node)."""
    try:
        ManagedConfidenceNode(context=context, parameter_overrides=overrides)
    except Exception as error:  # noqa: BLE001  (rclpy's own exception types)
        return type(error).__name__
    return 'nothing'


@pytest.mark.parametrize(
    'bad',
    [Parameter('max_disparity', value='abc'), Parameter('autostart', value='yes')],
    ids=['while-declaring', 'after-declaring'],
)
def test_a_managed_node_refused_at_start_leaves_rosout_to_the_next_of_its_name(
    bad: Parameter,
) -> None:
    # The managed node's constructor did not destroy a node it refused (ConfidenceNode's did):
    # collected later, it unregistered the /rosout publisher of its name, by then the next
    # node's, whose log lines were then lost.
    with localhost_context(spare_domain_id()) as context:
        assert _refused(context, [bad]) == 'InvalidParameterTypeException'
    with localhost_context(spare_domain_id()) as context:
        node = ManagedConfidenceNode(context=context, parameter_overrides=list(OVERRIDES))
        try:
            assert rosout_reaches(context, node, timeout=15)
        finally:
            node.destroy_node()

"""Review 30 of the confidence node: a frame left running past a cleanup must not reach into
the configuration made after it."""

from __future__ import annotations

import os
import threading
from typing import Any

from node_test_utils import (
    SMALL_MLM,
    first_stamp,
    image_msg,
    info_msgs,
    localhost_context,
    spare_domain_id,
    textured_pair,
)
import pytest
from rcl_interfaces.msg import ParameterType
from rclpy.parameter import Parameter

from cva_confidence_ros.node import ConfidenceNode, ManagedConfidenceNode
from cva_confidence_ros.ros import confidence_node
from cva_confidence_ros.ros.cloud_filter_node import CloudFilterNode

pytestmark = pytest.mark.timeout(180)

NAMESPACE = f'review30_{os.getpid()}'
OVERRIDES = [
    *SMALL_MLM,
    Parameter('autostart', value=True),
]


def test_a_frame_left_running_past_cleanup_leaves_the_new_configuration_alone(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # A frame still converting its messages when cleanup's wait ran out went on after a new
    # configure: it wrote its image size into the new configuration (a parameter change was
    # then checked against images the new configuration never received) and ran the new
    # pipeline beside the new worker.
    monkeypatch.setattr(confidence_node.ConfidenceCore.stop, '__defaults__', (0.3,))
    started, release = threading.Event(), threading.Event()
    convert = confidence_node.stereo_pair_from_messages

    def slow_convert(*args: Any) -> Any:
        started.set()
        release.wait(30.0)
        return convert(*args)

    monkeypatch.setattr(confidence_node, 'stereo_pair_from_messages', slow_convert)
    with localhost_context(spare_domain_id()) as context:
        node = ManagedConfidenceNode(
            context=context, namespace=NAMESPACE, parameter_overrides=OVERRIDES
        )
        try:
            left, right = textured_pair()
            stamp = first_stamp()
            left_info, right_info = info_msgs(stamp, *left.shape[:2])
            for key, msg in (('left_info', left_info), ('right_info', right_info),
                             ('left', image_msg(left, stamp)), ('right', image_msg(right, stamp))):
                node._on_message(key, msg)
            assert started.wait(30.0), 'the frame did not start'
            old_worker = node._worker
            node.trigger_deactivate()
            node.trigger_cleanup()
            assert old_worker is not None and old_worker.is_alive()
            node.trigger_configure()
            node.trigger_activate()
            ran: list[int] = []
            process = node._pipeline.process
            node._pipeline.process = lambda *a: ran.append(1) or process(*a)
            release.set()
            old_worker.join(30.0)
            assert not old_worker.is_alive()
            assert node._input_size is None
            assert ran == []
        finally:
            release.set()
            node.destroy_node()


@pytest.mark.parametrize('kind', ['confidence', 'cloud_filter'])
def test_double_parameters_stay_doubles_whatever_is_offered(kind: str) -> None:
    # rclpy types a dynamically typed parameter by the value offered: -p max_rate_hz:=2 made
    # it an integer parameter (ros2 param describe/get said so), and a refused set of 'abc'
    # left it a string parameter holding 2.
    name, given = ('max_rate_hz', 2) if kind == 'confidence' else ('threshold', 1)
    with localhost_context(spare_domain_id()) as context:
        if kind == 'confidence':
            node = ConfidenceNode(
                context=context, namespace=NAMESPACE,
                parameter_overrides=[*OVERRIDES[:3], Parameter(name, value=given)],
            )
        else:
            node = CloudFilterNode(
                context=context, namespace=NAMESPACE,
                parameter_overrides=[Parameter(name, value=given)],
            )
        try:

            def declared() -> tuple[int, int, object]:
                value = node.get_parameter(name)
                return node.describe_parameter(name).type, value.type_.value, value.value

            double = ParameterType.PARAMETER_DOUBLE
            assert declared() == (double, double, float(given))
            [refused] = node.set_parameters([Parameter(name, value='abc')])
            assert not refused.successful
            assert declared() == (double, double, float(given))
            [accepted] = node.set_parameters([Parameter(name, value=0)])
            assert accepted.successful, accepted.reason
            assert declared() == (double, double, 0.0)
        finally:
            node.destroy_node()

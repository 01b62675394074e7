"""Review 33 of the node as a robot runs it for hours: a camera that stops (or never starts)
left ``/diagnostics`` OK, 'processing at 0.0 Hz', for as long as it stayed silent (regression
tests of a fault found in a soak run)."""

from __future__ import annotations

import time

from diagnostic_msgs.msg import DiagnosticStatus
from node_test_utils import (
    SMALL_MLM,
    LogRecorder,
    feed_frame,
    first_stamp,
    localhost_context,
    spare_domain_id,
    textured_pair,
    wait_until,
)
import pytest
from rclpy.parameter import Parameter

from cva_confidence_ros.node import ConfidenceNode

pytestmark = pytest.mark.timeout(120)

PERIOD_S = 0.2
TOPICS = 'left/image_rect, right/image_rect, left/camera_info, right/camera_info'


def _node(context: object) -> ConfidenceNode:
    return ConfidenceNode(
        context=context,
        parameter_overrides=[
            *SMALL_MLM,
            Parameter('diagnostics_period_seconds', value=PERIOD_S),
        ],
    )


def test_a_camera_that_stops_is_a_warning_naming_the_topics() -> None:
    with localhost_context(spare_domain_id()) as context:
        node = _node(context)
        try:
            left, right = textured_pair()
            stamp = first_stamp()
            for i in range(4):  # a burst: three gaps between left images, each of a moment
                feed_frame(node, left, right, stamp + i * 100_000_000)
            done = ('frames_processed', 'frames_dropped')
            assert wait_until(lambda: sum(node.stats()[k] for k in done) == 4, 30.0)
            node.diagnostics()  # the window with the frames
            time.sleep(0.4)  # longer than the period and three times the gaps
            status = node.diagnostics()
            assert status.level == DiagnosticStatus.WARN, status.message
            assert status.message.startswith('no input for '), status.message
            assert f'nothing on {TOPICS} since the last message' in status.message
            # The camera back: OK again.
            processed = node.stats()['frames_processed']
            feed_frame(node, left, right, stamp + 10 * 100_000_000)
            assert wait_until(lambda: node.stats()['frames_processed'] > processed, 30.0)
            assert node.diagnostics().level == DiagnosticStatus.OK
        finally:
            node.destroy_node()


def test_a_slow_camera_is_silent_after_three_of_its_gaps_not_between_frames() -> None:
    with localhost_context(spare_domain_id()) as context:
        node = _node(context)
        try:
            left, right = textured_pair()
            stamp = first_stamp()
            for i in range(4):  # 0.5 s apart: silent is 1.5 s, not one diagnostics period
                if i:
                    time.sleep(0.5)
                feed_frame(node, left, right, stamp + i * 500_000_000)
            done = ('frames_processed', 'frames_dropped')
            assert wait_until(lambda: sum(node.stats()[k] for k in done) == 4, 30.0)
            with node._lock:  # as if the last image came now: a slow machine's processing
                node._stats.last_message_at = time.monotonic()  # is no silence of the camera
            node.diagnostics()
            time.sleep(0.4)
            status = node.diagnostics()
            assert status.level == DiagnosticStatus.OK, status.message
            time.sleep(1.3)  # now silent for three times its gaps
            status = node.diagnostics()
            assert status.message.startswith('no input for '), status.message
        finally:
            node.destroy_node()


def test_a_camera_that_never_starts_is_a_warning() -> None:
    with localhost_context(spare_domain_id()) as context:
        node = _node(context)
        try:
            with node._lock:  # subscribed just now (a slow start-up is not the camera's)
                node._stats.subscribed_at = time.monotonic()
            assert node.diagnostics().level == DiagnosticStatus.OK
            time.sleep(0.3)
            status = node.diagnostics()
            assert status.level == DiagnosticStatus.WARN, status.message
            assert status.message.startswith(f'no input: nothing on {TOPICS} in the ')
            assert 'since the node subscribed' in status.message
        finally:
            node.destroy_node()


def test_a_camera_gone_blind_is_logged_as_a_warning() -> None:
    # Below min_kept_fraction, /diagnostics warned but the status line went to the log as an
    # info line, the only line that said so: a blinded camera over hours was never a warning.
    with localhost_context(spare_domain_id()) as context:
        node = ConfidenceNode(
            context=context,
            parameter_overrides=[*SMALL_MLM, Parameter('min_kept_fraction', value=1.0)],
        )
        try:
            left, right = textured_pair()
            node.diagnostics()  # a fresh window
            feed_frame(node, left, right, first_stamp())
            assert wait_until(lambda: node.stats()['frames_processed'] == 1, 30.0)
            recorder = LogRecorder()
            node.get_logger = lambda: recorder  # type: ignore[method-assign]
            node._publish_diagnostics()
            ((severity, line),) = recorder.lines
            assert line.startswith('only ') and 'are confident' in line, line
            assert severity == 'warning'
        finally:
            node.__dict__.pop('get_logger', None)
            node.destroy_node()


def test_no_input_with_reliable_subscriptions_names_the_qos() -> None:
    # A sensor-data (best-effort) driver never reaches reliable subscriptions: rclpy says so
    # once at discovery, and the status only that nothing comes.
    with localhost_context(spare_domain_id()) as context:
        node = ConfidenceNode(
            context=context,
            parameter_overrides=[
                *SMALL_MLM,
                Parameter('diagnostics_period_seconds', value=PERIOD_S),
                Parameter('input_qos', value='reliable'),
            ],
        )
        try:
            node.diagnostics()
            time.sleep(0.3)
            status = node.diagnostics()
            assert status.level == DiagnosticStatus.WARN, status.message
            assert 'input_qos reliable takes nothing from a best-effort' in status.message
        finally:
            node.destroy_node()

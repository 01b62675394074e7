"""Review 31 of the confidence node: image_transport topics that ignored a remapped base topic,
a window with failed frames besides processed ones reported OK, and a status log line whose
counters did not add up (each a regression test of a fault found in the review)."""

from __future__ import annotations

import os
import re
from typing import Any

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
import numpy as np
import pytest
from rclpy.parameter import Parameter

from cva_confidence_ros.node import ConfidenceNode

pytestmark = pytest.mark.timeout(120)

NAMESPACE = f'review31_{os.getpid()}'
OVERRIDES = [
    *SMALL_MLM,
]


def test_image_transport_topics_follow_a_remapped_base_topic() -> None:
    # image_transport (and stereo_image_proc) put <base>/compressed under the base topic as
    # remapped: with -r left/image_rect:=/cam/left/image_rect and image_transport compressed
    # the node subscribed to /<ns>/left/image_rect/compressed (nothing ever came), and with
    # -r depth:=/mapper/depth it advertised /<ns>/depth/compressedDepth.
    remaps = [
        'left/image_rect:=/cam/left/image_rect',
        'right/image_rect/compressed:=/cam/right_jpeg',  # the transport's own, base as it is
        'depth:=/mapper/depth',
        'confidence_overlay:=/viz/overlay',
    ]
    with localhost_context(spare_domain_id()) as context:
        node = ConfidenceNode(
            context=context,
            namespace=NAMESPACE,
            parameter_overrides=[*OVERRIDES, Parameter('image_transport', value='compressed')],
            cli_args=['--ros-args', *(arg for rule in remaps for arg in ('-r', rule))],
        )
        try:
            inputs = {sub.topic_name for sub in node._subscriptions_in}
            assert inputs == {
                '/cam/left/image_rect/compressed',
                '/cam/right_jpeg',
                f'/{NAMESPACE}/left/camera_info',
                f'/{NAMESPACE}/right/camera_info',
            }
            assert node._pub_depth.topic_name == '/mapper/depth'
            assert node._pub_depth_compressed.topic_name == '/mapper/depth/compressedDepth'
            assert node._pub_overlay_compressed.topic_name == '/viz/overlay/compressed'
        finally:
            node.destroy_node()


def test_a_window_in_which_frames_failed_besides_processed_ones_warns() -> None:
    # Every other frame raised inside the pipeline: /diagnostics stayed OK 'processing at
    # 24.1 Hz' (only a window with no frame out at all was an ERROR), the failures unsaid.
    with localhost_context(spare_domain_id()) as context:
        node = ConfidenceNode(context=context, namespace=NAMESPACE, parameter_overrides=OVERRIDES)
        try:
            pipeline = node._pipeline
            process = pipeline.process
            calls = [0]

            def flaky(left: np.ndarray, right: np.ndarray) -> Any:
                calls[0] += 1
                if calls[0] % 2:
                    raise RuntimeError('simulated fault on every other frame')
                return process(left, right)

            pipeline.process = flaky
            left, right = textured_pair()
            stamp = first_stamp()
            node.diagnostics()  # a fresh window
            for i in range(4):
                feed_frame(node, left, right, stamp + i * 10**9)
                assert wait_until(
                    lambda i=i: sum(node.stats()[k] for k in ('frames_processed', 'frames_failed'))
                    > i,
                    30.0,
                )
            assert (node.stats()['frames_processed'], node.stats()['frames_failed']) == (2, 2)
            status = node.diagnostics()
            assert status.level == DiagnosticStatus.WARN, status.message
            assert '2 frame(s) failed' in status.message, status.message
            assert 'simulated fault on every other frame' in status.message
            # A window with none failed is OK again.
            pipeline.process = process
            feed_frame(node, left, right, stamp + 4 * 10**9)
            assert wait_until(lambda: node.stats()['frames_processed'] == 3, 30.0)
            assert node.diagnostics().level == DiagnosticStatus.OK
        finally:
            node.destroy_node()


def test_the_status_line_counts_every_frame_received() -> None:
    # The periodic log line named received, processed, dropped and invalid only: with
    # max_rate_hz it read 'received 3, processed 1, dropped 0, invalid 0', the throttled (and
    # failed) frames missing from the sum.
    with localhost_context(spare_domain_id()) as context:
        node = ConfidenceNode(
            context=context,
            namespace=NAMESPACE,
            parameter_overrides=[*OVERRIDES, Parameter('max_rate_hz', value=1.0)],
        )
        try:
            pipeline = node._pipeline
            process = pipeline.process
            fail = [True]

            def fail_first(left: np.ndarray, right: np.ndarray) -> Any:
                if fail[0]:
                    fail[0] = False
                    raise RuntimeError('simulated fault')
                return process(left, right)

            pipeline.process = fail_first
            left, right = textured_pair()
            stamp = first_stamp()
            feed_frame(node, left, right, stamp)
            assert wait_until(lambda: node.stats()['frames_failed'] == 1, 30.0)
            for i in (1, 2):  # 0.1 s and 0.2 s after it: within 1 / max_rate_hz
                feed_frame(node, left, right, stamp + i * 10**8)
            feed_frame(node, left, right, stamp + 2 * 10**9)
            assert wait_until(lambda: node.stats()['frames_processed'] == 1, 30.0)
            logger = LogRecorder()
            node.get_logger = lambda: logger
            node._publish_diagnostics()
            ((_, line),) = logger.lines
            counts = {
                name: int(value)
                for name, value in re.findall(
                    r'\b(received|processed|dropped|throttled|invalid|failed) (\d+)', line
                )
            }
            assert counts == {
                'received': 4, 'processed': 1, 'dropped': 0, 'throttled': 2, 'invalid': 0,
                'failed': 1,
            }, line
            assert counts['received'] == sum(v for k, v in counts.items() if k != 'received')
        finally:
            node.destroy_node()

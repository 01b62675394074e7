"""Review 32 of the confidence node: the status of input that never pairs named the topics as
declared, not the ones a remapping moved the subscriptions to (a regression test of a fault
found in the review)."""

from __future__ import annotations

import os

from diagnostic_msgs.msg import DiagnosticStatus
from node_test_utils import (
    SMALL_MLM,
    first_stamp,
    info_msgs,
    localhost_context,
    spare_domain_id,
)
import pytest
from rclpy.parameter import Parameter

from cva_confidence_ros.node import ConfidenceNode

pytestmark = pytest.mark.timeout(120)

NAMESPACE = f'review32_{os.getpid()}'


@pytest.mark.parametrize('transport', ['raw', 'compressed'])
def test_input_that_never_pairs_names_the_remapped_topics(transport: str) -> None:
    # With -r right/camera_info:=/cam/right/info and nothing coming there, /diagnostics said
    # 'nothing on ... right/camera_info': a topic the node does not listen on, while the one
    # it does (/cam/right/info) went unnamed.
    remaps = ['left/image_rect:=/cam/left/image_rect', 'right/camera_info:=/cam/right/info']
    with localhost_context(spare_domain_id()) as context:
        node = ConfidenceNode(
            context=context,
            namespace=NAMESPACE,
            parameter_overrides=[*SMALL_MLM, Parameter('image_transport', value=transport)],
            cli_args=['--ros-args', *(arg for rule in remaps for arg in ('-r', rule))],
        )
        try:
            suffix = '/compressed' if transport == 'compressed' else ''
            node.diagnostics()  # a fresh window
            left_info, _ = info_msgs(first_stamp())
            node._on_message('left_info', left_info)
            status = node.diagnostics()
            assert status.level == DiagnosticStatus.WARN
            silent = status.message.split('nothing on ')[1].split(' in the last')[0]
            # Remapped inputs by the topic listened on; the others by their relative name.
            assert silent.split(', ') == [
                f'/cam/left/image_rect{suffix}',
                f'right/image_rect{suffix}',
                '/cam/right/info',
            ], status.message
        finally:
            node.destroy_node()

"""The node on image_transport's compressed topics (``image_transport: compressed``), over DDS."""

from __future__ import annotations

from collections.abc import Iterator
import time

import cv2
from node_test_utils import (
    TRUE_DISPARITY,
    Spinner,
    StereoClient,
    first_stamp,
    info_msgs,
    running_nodes,
    spare_domain_id,
    textured_pair,
)
import numpy as np
import pytest
from rcl_interfaces.msg import Log
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile
from sensor_msgs.msg import CompressedImage
from std_msgs.msg import Header

from cva_confidence_ros.node import ConfidenceNode
from cva_confidence_ros.ros.convert import disparity_from_message, ns_to_stamp

pytestmark = pytest.mark.timeout(120)

MAX_DISPARITY = 16


class _Compressed:
    def __init__(self, context: object) -> None:
        self.node = ConfidenceNode(
            context=context,
            parameter_overrides=[
                Parameter('image_transport', value='compressed'),
                Parameter('max_disparity', value=MAX_DISPARITY),
                Parameter('confidence_method', value='mlm'),
            ],
        )
        self.client = StereoClient(context)
        self.client.subscribe('/rosout', Log, QoSProfile(depth=100))
        self.compressed = {
            side: self.client.node.create_publisher(
                CompressedImage, f'{side}/image_rect/compressed', QoSProfile(depth=10)
            )
            for side in ('left', 'right')
        }
        self.spinner = Spinner(context, self.node, self.client.node)

    def publish(self, left: np.ndarray, right: np.ndarray, stamp: int, *, broken: bool = False):
        left_info, right_info = info_msgs(stamp, *left.shape[:2])
        self.client.pubs['left_info'].publish(left_info)
        self.client.pubs['right_info'].publish(right_info)
        for side, array in (('left', left), ('right', right)):
            ok, data = cv2.imencode('.png', array)
            assert ok
            payload = b'\x89PNG broken' if broken and side == 'left' else data.tobytes()
            self.compressed[side].publish(CompressedImage(
                header=Header(stamp=ns_to_stamp(stamp), frame_id='left_optical'),
                format='mono8; png compressed',
                data=payload,
            ))  # fmt: skip

    def answered(self, stamp: int, timeout: float = 3.0) -> bool:
        return self.client.wait_for(
            lambda: self.client.by_stamp('disparity', stamp) is not None, timeout
        )


@pytest.fixture
def running() -> Iterator[_Compressed]:
    with running_nodes(spare_domain_id(), _Compressed) as state:
        yield state


def test_compressed_images_are_matched_and_a_broken_one_is_skipped(running: _Compressed) -> None:
    left, right = textured_pair(seed=9)
    stamp = first_stamp()
    # Discovery first: until the node's subscriptions match ours, frames may be lost.
    deadline = time.monotonic() + 30
    while not running.answered(stamp, timeout=1.0):
        assert time.monotonic() < deadline, 'no disparity for the compressed frames'
        stamp += 1_000_000
        running.publish(left, right, stamp)
    disparity = disparity_from_message(running.client.by_stamp('disparity', stamp))
    assert disparity.shape == (64, 96)
    inner = disparity[4:-4, MAX_DISPARITY + 4:-4]
    assert np.mean(np.abs(inner - TRUE_DISPARITY) < 0.5) > 0.95

    broken = stamp + 10**9
    running.publish(left, right, broken, broken=True)
    assert running.client.wait_for(lambda: any(
        'is neither a JPEG nor a PNG' in msg.msg and 'left image' in msg.msg
        for msg in list(running.client.received['/rosout'])
    ), 10.0)  # fmt: skip
    assert running.client.by_stamp('disparity', broken) is None
    # ... and the node goes on with the next frame.
    following = broken + 10**9
    running.publish(left, right, following)
    assert running.answered(following, timeout=10.0)
    assert running.node.stats()['frames_invalid'] == 1

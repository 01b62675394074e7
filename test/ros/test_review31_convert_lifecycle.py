"""Review 31 of ``ros/convert.py``, the managed node and the cloud filter node: the camera info
published with the outputs, clouds with more data than their header, a filter refused at start,
a frame in progress at a deactivate (each a regression test of a fault found in the review)."""

from __future__ import annotations

import time
from typing import Any

from node_test_utils import (
    feed_frame,
    first_stamp,
    held_pipeline,
    info_msgs,
    localhost_context,
    rosout_reaches,
    spare_domain_id,
    textured_pair,
)
import numpy as np
import pytest
from rclpy.parameter import Parameter
from std_msgs.msg import Header

from cva_confidence_ros.camera_info import image_projection
from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.node import ManagedConfidenceNode
from cva_confidence_ros.pointcloud import CLOUD_CONFIDENCE_DTYPE
from cva_confidence_ros.ros.cloud_filter_node import CloudFilterNode
from cva_confidence_ros.ros.convert import (
    camera_info_to_geometry,
    cloud_to_message,
    image_camera_info,
    point_cloud_to_records,
    scale_camera_info,
)

pytestmark = pytest.mark.timeout(120)


@pytest.mark.parametrize('factor', [1, 2, 4])
@pytest.mark.parametrize(
    'change',
    [{'binning_x': 2, 'binning_y': 2}, {'binning_x': 4},
     {'x_offset': 8, 'y_offset': 4, 'width': 48, 'height': 32}],
    ids=['binning-2', 'binning-x-4', 'roi'],
)
def test_the_published_camera_info_describes_the_published_images(
    change: dict[str, int], factor: int
) -> None:
    # Images of the info's calibration size (96×64) with binning or an ROI in the info: the
    # node reads P as it is, but published the binning and ROI along (scaled, at downsample),
    # so that image_geometry read 96×64 images with binning 2 as 48×32 of fx 50 (and an ROI
    # at (8, 4) moved cx from 48 to 40).
    left_info, right_info = info_msgs(0)
    for name, value in change.items():
        setattr(left_info if name.startswith('binning') else left_info.roi, name, value)
    geometry = camera_info_to_geometry(left_info, right_info, 96, 64).scaled(1.0 / factor)
    out = scale_camera_info(image_camera_info(left_info, 96, 64), factor, Header())
    assert (out.width, out.height) == (96 // factor, 64 // factor)
    assert (out.binning_x, out.binning_y) == (0, 0)
    roi = out.roi
    assert (roi.x_offset, roi.y_offset, roi.width, roi.height) == (0, 0, 0, 0)
    # As REP 104 and image_geometry read it: the published size and the node's geometry.
    size, projection = image_projection(out, 'published camera info')
    assert size == (out.width, out.height)
    np.testing.assert_allclose(
        [projection[0, 0], projection[1, 1], projection[0, 2], projection[1, 2]],
        [geometry.fx, geometry.fy, geometry.cx, geometry.cy],
    )
    np.testing.assert_allclose(np.reshape(out.k, (3, 3)), projection[:, :3])
    assert image_camera_info(info_msgs(0)[0], 96, 64).binning_x == 0  # a plain info as it was


def test_a_cloud_with_more_data_than_its_header_says_is_refused() -> None:
    # 40 bytes beyond 2 rows of 3 points were dropped unseen (a width or height that does not
    # fit the data decoded as a part of the cloud); fewer bytes were refused already.
    msg = cloud_to_message(np.zeros((2, 3), CLOUD_CONFIDENCE_DTYPE), Header())
    assert point_cloud_to_records(msg).shape == (2, 3)
    msg.data = bytes(msg.data) + bytes(40)
    with pytest.raises(InputError, match=r'^cloud data holds 160 bytes; 2 rows of row_step 60 '
                                         r'need 120$'):
        point_cloud_to_records(msg)


def _refused_filter(context: Any) -> str:
    """Build a cloud filter that refuses its start-up QoS override; the error's name (the
    exception itself is not kept: its traceback would hold the node)."""
    bad = Parameter('qos_overrides./points2.subscription.reliability', value='bogus')
    try:
        CloudFilterNode(context=context, parameter_overrides=[bad])
    except ConfigError as error:
        return type(error).__name__
    return 'nothing'


def test_a_cloud_filter_refused_at_start_leaves_rosout_to_the_next_of_its_name() -> None:
    # A filter refused once its parameter callback and publisher existed was not destroyed:
    # collected later, it unregistered the /rosout publisher of its name, by then the next
    # filter's, whose log lines were then lost.
    with localhost_context(spare_domain_id()) as context:
        assert _refused_filter(context) == 'ConfigError'
    with localhost_context(spare_domain_id()) as context:
        node = CloudFilterNode(context=context)
        try:
            assert rosout_reaches(context, node, timeout=5)
        finally:
            node.destroy_node()


def test_a_frame_in_progress_at_deactivate_is_not_published_after_a_quick_activate() -> None:
    # "deactivate: a frame in progress finishes unpublished": it went out (and counted as
    # processed) when activate came before it ended, an old frame after pairing started afresh.
    overrides = [
        Parameter('matcher', value='census_bm'),
        Parameter('max_disparity', value=16),
        Parameter('confidence_method', value='mlm'),
        Parameter('autostart', value=True),
    ]
    with localhost_context(spare_domain_id()) as context:
        node = ManagedConfidenceNode(context=context, parameter_overrides=overrides)
        started, release = held_pipeline(node)
        try:
            published: list[int] = []
            publish = node._publish

            def record(result: Any, header: Header, *args: Any) -> None:
                published.append(header.stamp.sec)
                publish(result, header, *args)

            node._publish = record
            left, right = textured_pair()
            stamp = first_stamp()
            feed_frame(node, left, right, stamp)
            assert started.wait(10.0), 'the frame did not start'
            node.trigger_deactivate()
            node.trigger_activate()
            release.set()
            # A frame of the new activation is published: the one before is not.
            feed_frame(node, left, right, stamp + 10**9)
            deadline = time.monotonic() + 20.0
            while not published and time.monotonic() < deadline:
                time.sleep(0.02)
            assert published == [(stamp + 10**9) // 10**9]
            assert node.stats()['frames_processed'] == 1
        finally:
            release.set()
            node.destroy_node()

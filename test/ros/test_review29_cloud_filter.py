"""Review 29: the cloud filter node reads an integer confidence field as a fraction of its
type's full scale (as ``pointcloud.filter_cloud`` does)."""

from __future__ import annotations

from node_test_utils import localhost_context, spare_domain_id
import numpy as np
import pytest
from rclpy.parameter import Parameter
from std_msgs.msg import Header

from cva_confidence_ros.ros.cloud_filter_node import CloudFilterNode
from cva_confidence_ros.ros.convert import point_cloud_to_records, records_to_point_cloud


@pytest.mark.timeout(60)
def test_cloud_filter_node_cuts_a_uint8_confidence_field_at_its_threshold() -> None:
    # uint8 confidences were compared raw with the [0, 1] threshold: 26 passed 0.5.
    xyz = [('x', '<f4'), ('y', '<f4'), ('z', '<f4')]
    cloud = np.zeros((2, 3), np.dtype([*xyz, ('confidence', 'u1')]))
    cloud['z'] = 1.0
    cloud['confidence'] = [[0, 26, 127], [128, 200, 255]]
    with localhost_context(spare_domain_id()) as context:
        node = CloudFilterNode(
            context=context, parameter_overrides=[Parameter('threshold', value=0.5)]
        )
        try:
            published: list = []
            node._publisher = type('Capture', (), {'publish': staticmethod(published.append)})()
            node._on_cloud(records_to_point_cloud(cloud, Header(frame_id='cam')))
            assert len(published) == 1 and node.stats()['clouds_invalid'] == 0
            out = point_cloud_to_records(published[0])
            np.testing.assert_array_equal(
                np.isfinite(out['z']), [[False, False, False], [True, True, True]]
            )
            assert node.stats()['points_kept'] == 3
        finally:
            node.destroy_node()

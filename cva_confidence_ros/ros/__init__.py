"""rclpy side of the package: message ⇄ numpy conversions, parameters, the two nodes.

The core (matching, confidence, model, pipeline, point cloud, sync) never imports rclpy or ROS
message types. They are imported here, by the entry points (:mod:`cva_confidence_ros.node`,
:mod:`cva_confidence_ros.cloud_filter`), by the node and cloud benchmarks, and by the bag tools'
live mode and message serialisation (``msg_tools``).
"""

from __future__ import annotations

__all__ = ['cloud_filter_node', 'common', 'confidence_node', 'convert', 'interrupt', 'params']

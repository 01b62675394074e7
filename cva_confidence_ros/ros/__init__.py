"""rclpy side of the package: message ⇄ numpy conversions, the node's parameters, the node.

Only :mod:`cva_confidence_ros.node` and this subpackage import rclpy or ROS message types; the
core (matching, confidence, pipeline, point cloud, sync) stays ROS-free.
"""

from __future__ import annotations

__all__ = ['confidence_node', 'convert', 'params']

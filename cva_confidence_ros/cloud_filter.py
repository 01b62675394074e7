"""ROS 2 node: keep the points of a point cloud whose confidence is at least a threshold.

``ros2 run cva_confidence_ros cloud_filter`` (``cva-cloud-filter`` after a pip install)
subscribes to ``points2`` and publishes ``points2_filtered``. Run the confidence node with
``points_confidence: true`` so that its ``points2`` holds every point with a ``confidence``
field; each consumer then cuts it where it needs, and the threshold can be changed while running
(``ros2 param set /cva_cloud_filter threshold 0.8``). Any ``PointCloud2`` with x, y, z and a
confidence field works (``confidence_field`` names it); its other fields are carried along.

Parameters: ``threshold`` ([0, 1], 0.5), ``organized`` (true: keep the grid, NaN for dropped
points; false: kept points only), ``confidence_field`` ('confidence'), ``input_qos``
(sensor_data, the default: best effort, receives from any publisher | reliable),
``output_qos`` (reliable, the default | sensor_data), ``diagnostics_period_seconds``. A cloud it
cannot read (no such field, truncated data, big-endian) is logged and skipped; counts go to
``/diagnostics``.

The node itself lives in :mod:`cva_confidence_ros.ros.cloud_filter_node`.
"""

from __future__ import annotations

from collections.abc import Sequence
import sys

__all__ = ['main']


def main(argv: Sequence[str] | None = None) -> int:
    """Run the filter until Ctrl-C or SIGTERM.

    Returns:
        0 on a clean stop, 2 for invalid ROS arguments or parameters, 130 when interrupted
        before the node is up.
    """
    from cva_confidence_ros.node import run_entry

    return run_entry('cva_confidence_ros.ros.cloud_filter_node', argv)


if __name__ == '__main__':
    sys.exit(main())

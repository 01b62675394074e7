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
cannot read (no such field, truncated data, big-endian, a confidence outside [0, 1]) is logged
and skipped; counts go to ``/diagnostics``.

The node itself lives in :mod:`cva_confidence_ros.ros.cloud_filter_node`. ``-h``/``--help``
lists the topics and the parameters with their defaults (:func:`usage`) and exits; any other
argument outside ``--ros-args`` is refused (exit status 2).
"""

from __future__ import annotations

from collections.abc import Sequence
import sys

__all__ = ['main', 'usage']


def main(argv: Sequence[str] | None = None) -> int:
    """Run the filter until Ctrl-C or SIGTERM.

    Args:
        argv: Command line including ROS arguments; None = ``sys.argv``.

    Returns:
        0 on a clean stop or after ``--help``, 2 for an argument outside ``--ros-args``, invalid
        ROS arguments or parameters, 130 when interrupted before the node is up.
    """
    from cva_confidence_ros.node import run_entry

    return run_entry(
        'cva_confidence_ros.ros.cloud_filter_node', argv, usage=usage, example=_EXAMPLE
    )


_TOPICS = (
    ('in', 'points2', 'sensor_msgs/PointCloud2', 'x, y, z and a confidence field'),
    ('out', 'points2_filtered', 'sensor_msgs/PointCloud2', 'points with confidence >= threshold'),
    ('out', '/diagnostics', 'diagnostic_msgs/DiagnosticArray', ''),
)
_EXAMPLE = 'threshold:=0.8'


def usage(prog: str = 'cva-cloud-filter') -> str:
    """The filter's ``--help``: its topics, and its parameters with defaults and descriptions."""
    from dataclasses import fields

    from cva_confidence_ros.ros.cloud_filter_node import (
        PARAMETER_DESCRIPTIONS,
        READ_ONLY_PARAMETERS,
        CloudFilterConfig,
    )
    from cva_confidence_ros.ros.common import usage_text

    parameters = []
    for spec in fields(CloudFilterConfig):
        # The declared range of threshold, the only one (CloudFilterNode.__init__).
        limits = '[0.0, 1.0]' if spec.name == 'threshold' else ''
        if spec.name in READ_ONLY_PARAMETERS:
            limits = '(start-up only)'
        parameters.append((spec.name, spec.default, limits, PARAMETER_DESCRIPTIONS[spec.name]))
    return usage_text(
        prog,
        'Point-cloud confidence filter: republishes the points of a cloud whose confidence is at '
        'least a threshold.',
        _TOPICS,
        parameters,
        example=_EXAMPLE,
        qos_topic='points2',
    )


if __name__ == '__main__':
    sys.exit(main())

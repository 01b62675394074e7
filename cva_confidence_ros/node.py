"""The ROS 2 node: rectified stereo in; disparity, confidence and a filtered point cloud out.

A thin adapter over :class:`~cva_confidence_ros.pipeline.StereoPipeline`, with the topic names
and message conventions of ``stereo_image_proc``:

Subscribes (all remappable): ``left/image_rect``, ``right/image_rect`` (``sensor_msgs/Image``:
mono8, mono16, rgb8, bgr8, rgba8, bgra8), ``left/camera_info``, ``right/camera_info``. The four
are matched by stamp (:mod:`cva_confidence_ros.sync`).

Publishes: ``disparity`` and ``disparity_filtered`` (``stereo_msgs/DisparityImage``; the
filtered one is invalid wherever confidence < ``confidence_threshold``), ``confidence``
(``sensor_msgs/Image`` 32FC1 in [0, 1]), ``points2`` (``sensor_msgs/PointCloud2`` x, y, z, rgb
of the pixels with confidence ≥ threshold), ``camera_info`` (the left camera info at the output
resolution, for consumers of ``confidence``) and ``/diagnostics``. Everything is stamped with the
left image's header and published at the processed resolution (1/``downsample``).

Threads: subscription callbacks only synchronise and drop the newest complete set into a
one-slot mailbox; a worker thread processes whatever is in the slot. When frames come faster
than they are processed, older ones are overwritten (counted as dropped) and nothing queues
without bound. A bad frame is logged (the first of each kind at once, repeats throttled) and
dropped; the node keeps going. Stamps that jump back in time (a looped bag, a driver restart, a
simulator reset) are logged and pairing starts over from them.

The node itself lives in :mod:`cva_confidence_ros.ros.confidence_node`; this module is the light
entry point, which imports it inside :func:`main`'s ``try`` (so that an early Ctrl-C ends quietly)
and hands ``ConfidenceNode`` and ``NODE_NAME`` on to ``from cva_confidence_ros.node import …``.
"""

from __future__ import annotations

from collections.abc import Sequence
import importlib
import sys
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from cva_confidence_ros.ros.confidence_node import NODE_NAME, ConfidenceNode

__all__ = ['NODE_NAME', 'ConfidenceNode', 'main', 'run_entry']

_EXIT_INTERRUPTED = 130  # 128 + SIGINT, as a shell reports a Ctrl-C


def main(argv: Sequence[str] | None = None) -> int:
    """Run the node until Ctrl-C or SIGTERM (``cva-node`` / ``ros2 run cva_confidence_ros node``).

    Args:
        argv: Command line including ROS arguments (``--ros-args -p max_disparity:=128 -r
            left/image_rect:=/cam/left/image``); None = ``sys.argv``.

    Returns:
        0 on a clean stop, 2 when the ROS arguments or the start-up configuration are invalid,
        130 when interrupted before the node is up.
    """
    return run_entry('cva_confidence_ros.ros.confidence_node', argv)


def run_entry(module: str, argv: Sequence[str] | None = None) -> int:
    """Import ``module`` and return its ``run(argv)``, a Ctrl-C at any point ending quietly.

    rclpy, the message types and the pipeline take a second or two to import, and a Ctrl-C in
    that time must end the program as quietly as one a moment later. From here on SIGINT is only
    noted (:mod:`cva_confidence_ros.ros.interrupt`: raised as ``KeyboardInterrupt`` it could land
    inside torch's or rclpy's C++ and abort the process, or be swallowed on the way); a Ctrl-C
    during the imports ends the program right after them, and ``run`` stops at its own points
    (:func:`cva_confidence_ros.ros.common.run_node`). Every node entry point goes through this.
    """
    from cva_confidence_ros.ros import interrupt

    interrupt.install()
    try:
        run = importlib.import_module(module).run
        if interrupt.requested():
            return _EXIT_INTERRUPTED
        return run(argv)
    finally:
        interrupt.restore()


def __getattr__(name: str) -> Any:
    if name in ('NODE_NAME', 'ConfidenceNode'):
        from cva_confidence_ros.ros import confidence_node

        return getattr(confidence_node, name)
    raise AttributeError(f'module {__name__!r} has no attribute {name!r}')


if __name__ == '__main__':
    sys.exit(main())

"""The ROS 2 node: rectified stereo in; disparity, confidence and a filtered point cloud out.

A thin adapter over :class:`~cva_confidence_ros.pipeline.StereoPipeline`, with the topic names
and message conventions of ``stereo_image_proc``:

Subscribes (all remappable): ``left/image_rect``, ``right/image_rect`` (``sensor_msgs/Image``:
mono8, mono16, rgb8, bgr8, rgba8, bgra8), ``left/camera_info``, ``right/camera_info``. The four
are matched by stamp (:mod:`cva_confidence_ros.sync`).

Publishes: ``disparity`` and ``disparity_filtered`` (``stereo_msgs/DisparityImage``; the
filtered one is invalid wherever confidence < ``confidence_threshold`` or the pixel lies in a
speckle, ``speckle_size``), ``confidence`` (``sensor_msgs/Image`` 32FC1 in [0, 1]), ``points2``
(``sensor_msgs/PointCloud2`` x, y, z, rgb of those kept pixels), ``depth``
(``sensor_msgs/Image``, REP 118: the depth of those pixels, 32FC1 metres with NaN or 16UC1
millimetres with 0 where there is none), ``confidence_overlay`` (``sensor_msgs/Image`` rgb8,
for a person to look at: the kept pixels tinted red → yellow → green by confidence over the
dimmed scene), ``scan`` (``sensor_msgs/LaserScan`` of the kept pixels in a height band, for
obstacle layers; in the camera's body frame, :mod:`cva_confidence_ros.scan`), ``camera_info``
(the left camera info at the output resolution, for consumers of ``confidence`` and ``depth``),
``confidence_overlay/compressed`` and ``depth/compressedDepth`` (``image_transport``'s
``compressed`` and ``compressedDepth`` of those two, encoded only while subscribed:
:mod:`cva_confidence_ros.ros.transport`) and ``/diagnostics``. Everything is stamped with the
left image's header and published at the processed resolution (1/``downsample``).

Threads: subscription callbacks only synchronise and hand the newest complete set (or the two
a short jump back completes at once) to a mailbox; a worker thread processes what is in it.
When frames come faster than they are processed, older ones are overwritten (counted as
dropped) and nothing queues without bound. A bad frame is logged (the first of each kind at
once, repeats throttled) and dropped; the node keeps going. Stamps that jump back in time (a
looped bag, a driver restart, a simulator reset) are logged and pairing starts over from them.

The node itself lives in :mod:`cva_confidence_ros.ros.confidence_node`; this module is the light
entry point, which imports it inside :func:`main`'s ``try`` (so that an early Ctrl-C ends quietly)
and hands ``ConfidenceNode`` and ``NODE_NAME`` on to ``from cva_confidence_ros.node import …``.
``-h``/``--help`` lists the topics and the parameters with their defaults (:func:`usage`) and
exits; any other argument outside ``--ros-args`` is refused (exit status 2) before the node
module is imported.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
import importlib
import os
from pathlib import Path
import sys
from typing import TYPE_CHECKING, Any

from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.jit import ensure_jit_cache

if TYPE_CHECKING:
    from cva_confidence_ros.ros.confidence_node import NODE_NAME, ConfidenceNode
    from cva_confidence_ros.ros.lifecycle_node import ManagedConfidenceNode

__all__ = [
    'NODE_NAME',
    'ConfidenceNode',
    'ManagedConfidenceNode',
    'cpu_quota',
    'ensure_jit_cache',
    'lifecycle_main',
    'lifecycle_usage',
    'main',
    'match_threads_to_cpu_quota',
    'run_entry',
    'usage',
]

_EXIT_INTERRUPTED = 130  # 128 + SIGINT, as a shell reports a Ctrl-C

#: ``(direction, name, type, note)`` of every topic, for :func:`usage`.
_TOPICS = (
    ('in', 'left/image_rect', 'sensor_msgs/Image', 'mono8/16, rgb8, bgr8, rgba8, bgra8 '
     '(image_transport:=compressed: <topic>/compressed)'),
    ('in', 'right/image_rect', 'sensor_msgs/Image', 'paired with the left one by stamp'),
    ('in', 'left/camera_info', 'sensor_msgs/CameraInfo', ''),
    ('in', 'right/camera_info', 'sensor_msgs/CameraInfo', ''),
    ('out', 'disparity', 'stereo_msgs/DisparityImage', ''),
    ('out', 'disparity_filtered', 'stereo_msgs/DisparityImage',
     'invalid below the threshold and in speckles'),
    ('out', 'confidence', 'sensor_msgs/Image', '32FC1 in [0, 1]'),
    ('out', 'points2', 'sensor_msgs/PointCloud2', 'x y z rgb of the confident pixels'),
    ('out', 'depth', 'sensor_msgs/Image', 'depth of the confident pixels (REP 118)'),
    ('out', 'confidence_overlay', 'sensor_msgs/Image',
     'rgb8 for a person: the kept pixels red to green by confidence over the scene'),
    ('out', 'scan', 'sensor_msgs/LaserScan',
     'nearest kept point per bearing in scan_min/max_height; intensity = confidence'),
    ('out', 'camera_info', 'sensor_msgs/CameraInfo', 'left, at the output resolution'),
    ('out', 'confidence_overlay/compressed', 'sensor_msgs/CompressedImage',
     'image_transport compressed (JPEG), encoded only while subscribed'),
    ('out', 'depth/compressedDepth', 'sensor_msgs/CompressedImage',
     'image_transport compressedDepth (PNG), encoded only while subscribed'),
    ('out', '/diagnostics', 'diagnostic_msgs/DiagnosticArray', ''),
)
_EXAMPLE = 'confidence_threshold:=0.8'


def main(argv: Sequence[str] | None = None) -> int:
    """Run the node until Ctrl-C or SIGTERM (``cva-node`` / ``ros2 run cva_confidence_ros node``).

    Args:
        argv: Command line including ROS arguments (``--ros-args -p max_disparity:=128 -r
            left/image_rect:=/cam/left/image``); None = ``sys.argv``.

    Returns:
        0 on a clean stop or after ``--help``, 2 for an argument outside ``--ros-args`` or when
        the ROS arguments or the start-up configuration are invalid, 130 when interrupted before
        the node is up.
    """
    return run_entry(
        'cva_confidence_ros.ros.confidence_node', argv, usage=usage, example=_EXAMPLE
    )


def lifecycle_main(argv: Sequence[str] | None = None) -> int:
    """Run the managed (lifecycle) node (``cva-lifecycle-node`` / ``ros2 run cva_confidence_ros
    lifecycle_node``); arguments and exit codes as :func:`main`."""
    return run_entry(
        'cva_confidence_ros.ros.lifecycle_node',
        argv,
        usage=lifecycle_usage,
        example=_EXAMPLE,
    )


def usage(prog: str = 'cva-node') -> str:
    """The node's ``--help``: its topics, and its parameters with defaults and descriptions."""
    from cva_confidence_ros.ros.common import usage_text

    return usage_text(
        prog,
        'Stereo confidence node: rectified stereo in; disparity, confidence and a '
        'confidence-filtered point cloud out.',
        _TOPICS,
        _parameter_lines(),
        example=_EXAMPLE,
        qos_topic='left/image_rect',
    )


def lifecycle_usage(prog: str = 'cva-lifecycle-node') -> str:
    """The managed node's ``--help``: :func:`usage` plus its states and ``autostart``."""
    from cva_confidence_ros.ros.common import usage_text

    parameters = [
        ('autostart', False, '(start-up only)',
         'Configure and activate at start-up, without a lifecycle manager.'),
        *_parameter_lines(),
    ]
    return usage_text(
        prog,
        'Stereo confidence node as a ROS 2 managed (lifecycle) node: it starts unconfigured; '
        'configure loads the weights and warms up the matcher (a refused configuration fails '
        'the transition and leaves it unconfigured), activate subscribes and publishes, '
        'deactivate unsubscribes, cleanup releases the pipeline. Transitions through the '
        'standard lifecycle services (ros2 lifecycle set /cva_confidence configure, a '
        'lifecycle manager) or autostart:=true.',
        _TOPICS,
        parameters,
        example=_EXAMPLE,
        qos_topic='left/image_rect',
    )


def _parameter_lines() -> list[tuple[str, object, str, str]]:
    from cva_confidence_ros.ros.params import PARAMETERS

    parameters = []
    for spec in PARAMETERS:
        limits = []
        if spec.low is not None and spec.high is not None:
            limits.append(f'[{spec.low}, {spec.high}]')
        if spec.read_only:
            limits.append('(start-up only)')
        description = spec.description
        if spec.constraints:
            description += f' Allowed: {spec.constraints}.'
        parameters.append((spec.name, spec.default, ' '.join(limits), description))
    return parameters


def run_entry(
    module: str,
    argv: Sequence[str] | None = None,
    *,
    usage: Callable[[str], str] | None = None,
    example: str = 'name:=value',
) -> int:
    """Import ``module`` and return its ``run(argv)``, a Ctrl-C at any point ending quietly.

    rclpy, the message types and the pipeline take a second or two to import, and a Ctrl-C in
    that time must end the program as quietly as one a moment later. From here on SIGINT is only
    noted (:mod:`cva_confidence_ros.ros.interrupt`: raised as ``KeyboardInterrupt`` it could land
    inside torch's or rclpy's C++ and abort the process, or be swallowed on the way); a Ctrl-C
    during the imports ends the program right after them, and ``run`` stops at its own points
    (:func:`cva_confidence_ros.ros.common.run_node`). Every node entry point goes through this.

    The command line outside ``--ros-args`` is answered first, before ``module`` is imported
    (:func:`cva_confidence_ros.ros.common.check_arguments`): ``-h``/``--help`` prints
    ``usage(prog)`` and returns 0, any other argument there returns 2.

    Args:
        module: The node's module, with a ``run(argv) -> int``.
        argv: Command line including ROS arguments; None = ``sys.argv``.
        usage: The ``--help`` text for a program name; None = only how to pass ROS arguments.
        example: A ``name:=value`` of the node's, for the hint on an unrecognised argument.
    """
    from cva_confidence_ros.ros import interrupt

    interrupt.install()
    from cva_confidence_ros.memory import keep_freed_memory

    keep_freed_memory()  # before the first frame's allocations (see cva_confidence_ros.memory)
    try:
        from cva_confidence_ros.ros.common import EXIT_BAD_START, check_arguments

        code = check_arguments(sys.argv if argv is None else argv, usage, example)
        if code is not None:
            return code
        try:
            ensure_jit_cache()  # before the node module defines its numba kernels
        except ConfigError as error:
            print(f'cannot start: {error}', file=sys.stderr)
            return EXIT_BAD_START
        match_threads_to_cpu_quota()  # before torch and numba are imported
        if interrupt.requested():
            return _EXIT_INTERRUPTED
        run = importlib.import_module(module).run
        if interrupt.requested():
            return _EXIT_INTERRUPTED
        return run(argv)
    finally:
        interrupt.restore()


#: The thread-count variables of torch (OpenMP) and of numba, set by
#: :func:`match_threads_to_cpu_quota`.
THREAD_VARIABLES = ('OMP_NUM_THREADS', 'NUMBA_NUM_THREADS')


def match_threads_to_cpu_quota(
    root: Path = Path('/sys/fs/cgroup'), cgroup_file: Path = Path('/proc/self/cgroup')
) -> int | None:
    """Run torch's and numba's threads no more than a cgroup CPU quota lets run at once.

    Both start a thread per CPU the process may run on (its affinity, ``taskset``); a
    container's quota (``docker run --cpus``, Kubernetes' CPU limit) is not among what they
    look at, so under ``--cpus 1`` on two cores each frame ran two threads that the quota
    then stalled (320×240, Census-BM + CVA-Net-Fast: 7.4 fps against 9.0 with one thread),
    and a many-core robot fares worse. When the quota allows fewer whole CPUs than the
    affinity has, ``OMP_NUM_THREADS`` and ``NUMBA_NUM_THREADS`` are set to it (at least 1);
    either one already set is left as it is. Call it before torch and numba are imported.

    Returns:
        The thread count set, or None when there is no smaller quota.
    """
    limit = cpu_quota(root, cgroup_file)
    if limit is None:
        return None
    threads = max(1, int(limit))
    if threads >= len(os.sched_getaffinity(0)):
        return None
    for name in THREAD_VARIABLES:
        os.environ.setdefault(name, str(threads))
    return threads


def cpu_quota(
    root: Path = Path('/sys/fs/cgroup'), cgroup_file: Path = Path('/proc/self/cgroup')
) -> float | None:
    """CPUs the process's cgroup quota allows (the smallest along its cgroup's path), or None.

    Reads cgroup v2's ``cpu.max`` and v1's ``cpu.cfs_quota_us`` / ``cpu.cfs_period_us`` of
    the cgroup ``cgroup_file`` names under ``root``, and of the root there (a container sees
    its own cgroup as the root).
    """
    try:
        lines = cgroup_file.read_text().splitlines()
    except OSError:
        return None
    limits = []
    for line in lines:
        _, controllers, path = (line.split(':', 2) + ['', ''])[:3]
        if controllers:
            if 'cpu' not in controllers.split(','):
                continue
            bases = [root / controllers, root / 'cpu']
        else:
            bases = [root]
        relative = Path(path.lstrip('/'))
        for base in bases:
            for folder in (base / relative, *(base / parent for parent in relative.parents)):
                limit = _quota(folder, v2=not controllers)
                if limit is not None:
                    limits.append(limit)
    return min(limits, default=None)


def _quota(folder: Path, *, v2: bool) -> float | None:
    try:
        if v2:
            quota, period = (folder / 'cpu.max').read_text().split()[:2]
        else:
            quota = (folder / 'cpu.cfs_quota_us').read_text().strip()
            period = (folder / 'cpu.cfs_period_us').read_text().strip()
        cpus = int(quota) / int(period)
    except (OSError, ValueError, ZeroDivisionError):  # 'max' or -1: no quota
        return None
    return cpus if cpus > 0 else None


def __getattr__(name: str) -> Any:
    if name in ('NODE_NAME', 'ConfidenceNode'):
        from cva_confidence_ros.ros import confidence_node

        return getattr(confidence_node, name)
    if name == 'ManagedConfidenceNode':
        from cva_confidence_ros.ros import lifecycle_node

        return lifecycle_node.ManagedConfidenceNode
    raise AttributeError(f'module {__name__!r} has no attribute {name!r}')


if __name__ == '__main__':
    sys.exit(main())

"""The rclpy node behind :mod:`cva_confidence_ros.node` (topics and threads are described there).

Kept apart from the entry point so that ``cva-node`` can import rclpy, the message types and the
pipeline inside its ``try``: a Ctrl-C during that second of imports then ends the program quietly.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Hashable, Sequence
import contextlib
from dataclasses import dataclass, field
from functools import partial
import os
from pathlib import Path
import threading
import time
from typing import Any
import weakref

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
import numpy as np
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType, JumpThreshold
from rclpy.context import Context
from rclpy.duration import Duration
import rclpy.logging
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile
from rclpy.timer import Timer
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, LaserScan, PointCloud2
from stereo_msgs.msg import DisparityImage

from cva_confidence_ros.errors import ConfigError, CVAError, InputError, MemoryShortfallError
from cva_confidence_ros.pipeline import (
    COST_VOLUME_NETWORKS,
    PipelineConfig,
    PipelineResult,
    StereoPipeline,
)
from cva_confidence_ros.plots import confidence_overlay
from cva_confidence_ros.pointcloud import StereoGeometry, disparity_to_depth, stereo_cloud
from cva_confidence_ros.ros import interrupt
from cva_confidence_ros.ros.common import (
    LARGE_MESSAGES_HINT,
    LOG_THROTTLE_S,
    QOS_OVERRIDES,
    ReasonThrottle,
    diagnostic_status,
    large_messages_unset,
    publish_status,
    qos_override_errors,
    qos_profile,
    run_node,
    warn_unknown_parameters,
)
from cva_confidence_ros.ros.convert import (
    array_to_image,
    cloud_to_message,
    depth_to_image,
    disparity_to_message,
    image_camera_info,
    rgb_to_image,
    scale_camera_info,
    scan_to_message,
    stamp_to_ns,
    stereo_pair_from_messages,
)
from cva_confidence_ros.ros.params import (
    PARAMETERS,
    NodeConfig,
    build_configs,
    change_fault,
    declare_parameters,
    parameter_values,
    restore_types,
)
from cva_confidence_ros.ros.transport import depth_image_to_compressed_depth, rgb_to_compressed
from cva_confidence_ros.scan import disparity_to_scan, scan_frame_id
from cva_confidence_ros.sync import MatchedSet, StampSynchronizer

__all__ = [
    'NODE_NAME', 'PUBLISH_WAIT_S', 'STOP_TIMEOUT_S', 'ConfidenceCore', 'ConfidenceNode', 'run',
]

NODE_NAME = 'cva_confidence'
#: How long a stop waits for the frame in progress, in seconds.
STOP_TIMEOUT_S = 10.0
#: How long a deactivate waits for the outputs of a frame being published, in seconds.
PUBLISH_WAIT_S = 1.0
#: How long (steady seconds, at least a diagnostics period) simulated time may stay unstarted
#: under use_sim_time before the node says that no /clock came.
CLOCK_WAIT_S = 5.0
_OWN_PARAMETERS = frozenset(spec.name for spec in PARAMETERS)
#: Parameters naming a file, read when set (again: the file may have changed under its name).
_FILE_PARAMETERS = frozenset({'mask_path', 'model_path'})
# Synchroniser key → the topic it subscribes to (named in the logs).
_TOPICS = {
    'left': 'left/image_rect',
    'right': 'right/image_rect',
    'left_info': 'left/camera_info',
    'right_info': 'right/camera_info',
}
#: The outputs (message type, topic), in the order of the node's publisher attributes.
_OUTPUTS: tuple[tuple[type, str], ...] = (
    (DisparityImage, 'disparity'),
    (DisparityImage, 'disparity_filtered'),
    (Image, 'confidence'),
    (PointCloud2, 'points2'),
    (Image, 'depth'),
    (Image, 'confidence_overlay'),
    (LaserScan, 'scan'),
    (CameraInfo, 'camera_info'),
    # image_transport's other transports of two image outputs (ros/transport.py)
    (CompressedImage, 'confidence_overlay/compressed'),
    (CompressedImage, 'depth/compressedDepth'),
)
#: The share by which the left-image period must move from the one named in the "tolerance too
#: wide" warning for the warning to be logged again (the median of a few gaps jitters less).
_PERIOD_CHANGE = 0.25


class _Mailbox:
    """A hand-over between the executor and the worker: the newest sets win.

    It holds the sets of one synchroniser call (one, or the two a short jump back emits at
    once, oldest first); a newer call's sets replace those never taken.
    """

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._items: deque[MatchedSet] = deque()
        self._closed = False
        self._poked = False
        #: How many times :meth:`clear` was called, and how many before the item taken last
        #: was taken (noted under the lock: an item taken at a clear is either dropped or an
        #: item of before it, never one of after).
        self.clears = 0
        self.taken_clears = 0

    def put(self, items: list[MatchedSet]) -> int:
        """Store ``items`` (oldest first); return how many waiting ones they replaced."""
        with self._cond:
            replaced = len(self._items)
            self._items = deque(items)
            self._cond.notify()
            return replaced

    def take(self) -> MatchedSet | None:
        """Wait for an item (the oldest waiting); None once closed, or after a :meth:`poke`
        (the items, if any, stay for the next call)."""
        with self._cond:
            while not self._items and not self._closed and not self._poked:
                self._cond.wait()
            if self._closed or self._poked:
                self._poked = False
                return None
            self.taken_clears = self.clears
            return self._items.popleft()

    def poke(self) -> None:
        """Wake the worker without an item (a new pipeline to warm up before the next one)."""
        with self._cond:
            self._poked = True
            self._cond.notify()

    def clear(self) -> int:
        """Drop the items waiting; return how many there were."""
        with self._cond:
            dropped = len(self._items)
            self._items.clear()
            self.clears += 1
            return dropped

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` was called."""
        return self._closed

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()


def _close_mailbox(node: weakref.ref[ConfidenceCore]) -> None:
    """Close the mailbox of ``node``, if it is still there (a context's shutdown callback)."""
    alive = node()
    if alive is not None:
        alive._mailbox.close()


def _seconds(stamp_ns: int) -> str:
    return f'{stamp_ns // 1_000_000_000}.{stamp_ns % 1_000_000_000:09d}'


def _fraction(value: float | None) -> str:
    return '' if value is None else f'{value:.4f}'


def _wide_tolerance_message(tolerance_ns: int, period_ns: float) -> str:
    """The warning (log and ``/diagnostics``) of an approximate-sync tolerance of half the
    left images' period or more."""
    return (
        f'approximate_sync_tolerance_seconds = {tolerance_ns / 1e9:g} is at least half the '
        f'frame period ({period_ns / 1e9:.3f} s between left images): images of different '
        f'frames can pair; set it below {period_ns / 2e9:.3f}'
    )


def _file_stamps(config: PipelineConfig) -> dict[str, tuple[int, ...] | None]:
    """Per file parameter, what tells its file's content changed (inode, size, modification
    and change times; None: unset, or cannot be looked at)."""
    stamps: dict[str, tuple[int, ...] | None] = {}
    for name in _FILE_PARAMETERS:
        path, stamps[name] = getattr(config, name), None
        if path:
            with contextlib.suppress(OSError, ValueError):
                info = os.stat(path)
                stamps[name] = (info.st_ino, info.st_size, info.st_mtime_ns, info.st_ctime_ns)
    return stamps


@dataclass
class _Stats:
    """Counters and timings shown in ``/diagnostics`` (guarded by the node's lock)."""

    messages: int = 0
    pairs: int = 0
    processed: int = 0
    dropped: int = 0
    unmatched: int = 0
    invalid: int = 0
    failed: int = 0
    jumps: int = 0
    throttled: int = 0
    # stamp of the last set handed to the worker (max_rate_hz)
    last_taken_ns: int | None = None
    # why the last invalid frame was dropped, and how the last failed one failed (apart: the
    # status of a window with both names each by its own)
    last_invalid: str = ''
    last_failure: str = ''
    last_timings_ms: dict[str, float] = field(default_factory=dict)
    mean_timings_ms: dict[str, float] = field(default_factory=dict)
    window_messages: int = 0
    window_pairs: int = 0
    window_processed: int = 0
    window_invalid: int = 0
    window_failed: int = 0
    # share of the pixels kept (finite disparity, confidence ≥ threshold, no speckle): the
    # last frame's and the sum over the window's processed frames; the last frame's mean
    # confidence
    last_kept_fraction: float | None = None
    window_kept_sum: float = 0.0
    last_mean_confidence: float | None = None
    # the share of the last frame's pixels that passed the threshold but were speckles
    last_speckle_fraction: float | None = None
    # the share of the last frame's pixels judged at all (region of interest and ignore mask;
    # the kept share and the mean confidence are of those)
    last_judged_fraction: float | None = None
    # the error rate a probabilistic confidence predicts for the kept pixels (mean of
    # 1 − confidence there): the last frame's; over the window's frames that have one, the
    # sums of it × kept share and of the kept share
    last_expected_kept_error: float | None = None
    window_expected_wrong: float = 0.0
    window_expected_kept: float = 0.0
    window_start: float = field(default_factory=time.monotonic)
    # the node's clock (ns) at the window's start under use_sim_time (None otherwise, or no
    # /clock yet): the diagnostics timer ticks on that clock, so a window's rate is per second
    # of it
    window_start_clock_ns: int | None = None
    # per synchroniser key: messages in the window, and the stamp of the newest one
    window_keys: dict[str, int] = field(default_factory=dict)
    last_stamps_ns: dict[str, int] = field(default_factory=dict)
    # per synchroniser key: the stamp of its message in the set paired last (what the
    # synchroniser holds aside as a repeat or a late one when a message is at or before it),
    # and how many messages of the window were so (a bag played again, time gone back)
    paired_stamps_ns: dict[Hashable, int] = field(default_factory=dict)
    window_old: int = 0
    # left image stamps: the previous one and the last gaps between them (ns)
    left_stamp_ns: int | None = None
    left_gaps_ns: deque[int] = field(default_factory=lambda: deque(maxlen=8))
    # monotonic times: the subscriptions made (None while not subscribed), the last message
    # (None before the first since then); input silent since either is a warning
    subscribed_at: float | None = None
    last_message_at: float | None = None
    # left images: when the last one arrived and the last gaps between arrivals (monotonic s;
    # a slow camera, or a bag played slowly, is not silent between its frames)
    left_arrived_at: float | None = None
    # per synchroniser key: when its last message arrived since subscribed (monotonic s; an
    # input that stopped is not one whose messages never arrive)
    key_arrived_at: dict[str, float] = field(default_factory=dict)
    left_arrival_gaps_s: deque[float] = field(default_factory=lambda: deque(maxlen=8))

    @property
    def left_arrival_period_s(self) -> float | None:
        """The median time between the recent left images' arrivals (s), once three gaps are
        known."""
        if len(self.left_arrival_gaps_s) < 3:
            return None
        return float(np.median(self.left_arrival_gaps_s))

    @property
    def left_period_ns(self) -> float | None:
        """The median spacing of the recent left images (ns), once three gaps are known."""
        if len(self.left_gaps_ns) < 3:
            return None
        return float(np.median(self.left_gaps_ns))

    def record_timings(self, timings: dict[str, float]) -> None:
        self.last_timings_ms = dict(timings)
        # A stage the frame did not run (speckle_size or subpixel switched off at run time)
        # has no mean any more: /diagnostics kept its old one for good.
        for key in set(self.mean_timings_ms) - set(timings):
            del self.mean_timings_ms[key]
        for key, value in timings.items():
            previous = self.mean_timings_ms.get(key)
            # Exponential moving average: recent frames dominate, one spike does not.
            self.mean_timings_ms[key] = value if previous is None else 0.9 * previous + 0.1 * value


class ConfidenceCore(Node):
    """The confidence node's work, shared by :class:`ConfidenceNode` and the managed node.

    A ``Node`` whose set-up is split into stages: the managed node (this class before
    ``rclpy.lifecycle.LifecycleNode`` in its bases) runs them as its transitions, and
    :class:`ConfidenceNode` runs the first three in its constructor. A new configuration
    starts its counters afresh.

    * :meth:`_init_core` — declare the parameters and the parameter callback (nothing runs);
    * :meth:`_configure` — build and warm up the pipeline, create the publishers, the
      diagnostics timer and the worker thread (raises :class:`CVAError` for a configuration it
      refuses: missing weights, a device that is not there, …);
    * :meth:`_activate` / :meth:`_deactivate` — subscribe to / unsubscribe from the inputs;
    * :meth:`_cleanup` — stop the worker and release everything :meth:`_configure` made.
    """

    _pipeline: StereoPipeline | None
    _worker: threading.Thread | None
    # A pipeline a parameter change swapped in, which the worker has yet to warm up.
    _cold: StereoPipeline | None
    # Whether the approximate-sync tolerance was too wide at the last left image, and
    # (tolerance ns, period ns, monotonic s) of the warning logged last (guarded by _lock).
    _wide_holds: bool
    _wide_logged: tuple[int, float, float] | None
    # _file_stamps() of the files the pipeline read (mask_path, model_path)
    _files: dict[str, tuple[int, ...] | None]

    def _init_core(self) -> None:
        declare_parameters(self)
        self._lock = threading.Lock()
        # Held by the worker while it publishes a frame and by a deactivate while it clears the
        # mailbox (up to PUBLISH_WAIT_S): a frame's outputs all go out before the deactivate,
        # or none do (taken before _lock where both are held).
        self._publishing = threading.Lock()
        self._pipeline = None
        self._cold = None
        self._worker = None
        self._subscriptions_in: list[Any] = []
        self._owned: list[Any] = []
        # Under use_sim_time: the jump callback of the node's clock (see _on_clock_back), and
        # when /diagnostics was published last (monotonic s).
        self._clock_back: Any = None
        self._diagnostics_at = 0.0
        self._mailbox = _Mailbox()
        self._mailbox.close()  # nothing to hand over before the first configuration
        #: Set by :meth:`destroy_node` when a frame outlasted the stop's wait.
        self.frame_left_running = False
        # rclpy.shutdown() from another thread: the worker must not publish on a dead context.
        # (Ctrl-C shuts the context down in C without these callbacks; see _work.) The context
        # keeps the callback as long as it lives: one that held the node would keep a destroyed
        # node and its pipeline (the network's weights, GPU memory) alive as long. (A bound
        # method, which the context holds weakly, has its weak reference's callback fail at
        # interpreter exit: 'Exception ignored in WeakMethod._cb'.)
        self.context.on_shutdown(partial(_close_mailbox, weakref.ref(self)))
        self.add_on_set_parameters_callback(self._on_set_parameters)

    def _create_output_publisher(self, msg_type: type, topic: str, qos: Any) -> Any:
        """A publisher of the node's outputs (the managed node's are lifecycle publishers)."""
        return self.create_publisher(msg_type, topic, qos, qos_overriding_options=QOS_OVERRIDES)

    def _output_publishers(self, output_qos: str) -> list[Any]:
        """The outputs' publishers, in :data:`_OUTPUTS` order, each with its own profile of
        the preset and its ``qos_overrides``; none is left behind when an override is bad."""
        made: list[Any] = []
        outputs = {topic for _, topic in _OUTPUTS}
        try:
            for msg_type, topic in _OUTPUTS:
                base, _, transport = topic.rpartition('/')
                name = self._transport_topic(base, transport) if base in outputs else topic
                with qos_override_errors(self.resolve_topic_name(name)):
                    made.append(
                        self._create_output_publisher(msg_type, name, qos_profile(output_qos))
                    )
        except ConfigError:
            for publisher in made:
                self.destroy_publisher(publisher)
            raise
        return made

    def _configure(self) -> None:
        pipeline_config, node_config = build_configs(parameter_values(self))
        files = _file_stamps(pipeline_config)  # before the files are read
        pipeline = StereoPipeline(pipeline_config)
        pipeline.warm_up()
        _warm_up_scan()
        # Before anything is kept: a bad qos_overrides value leaves the node as it was.
        publishers = self._output_publishers(node_config.output_qos)
        with self._lock:
            self._pipeline = pipeline
            self._cold = None
            self._pipeline_config = pipeline_config
            self._files = files
            self._node_config = node_config
            # (width, height) of the last images received and when (monotonic s): a parameter
            # change that could not process them (max_disparity, downsample) is refused.
            # Forgotten on unsubscribing: the camera may come back with another resolution.
            self._input_size: tuple[int, int] | None = None
            self._input_size_at = 0.0
            self._sync = self._make_sync(node_config)
            self._stats = _Stats(window_start_clock_ns=self._sim_clock_ns())
            self._reset_wide_tolerance()
        self._log_throttle = ReasonThrottle()
        self._mailbox = _Mailbox()
        (
            self._pub_disparity, self._pub_filtered, self._pub_confidence, self._pub_points,
            self._pub_depth, self._pub_overlay, self._pub_scan, self._pub_info,
            self._pub_overlay_compressed, self._pub_depth_compressed,
        ) = publishers
        self._scan_frame_warned = False
        self._scan_pitch_warned = False
        self._pub_diagnostics = self.create_publisher(
            DiagnosticArray, '/diagnostics', QoSProfile(depth=10)
        )
        self._diag_timer = self.create_timer(
            node_config.diagnostics_period_seconds, self._publish_diagnostics
        )
        self._owned = [*publishers, self._pub_diagnostics, self._diag_timer]
        if getattr(self.get_clock(), 'ros_time_is_active', False):
            # Once, on the steady clock: under use_sim_time with no /clock (a bag played
            # without --clock) the diagnostics timer never fires, and nothing said why
            # /diagnostics is mute.
            self._clock_check = self.create_timer(
                max(CLOCK_WAIT_S, node_config.diagnostics_period_seconds),
                self._check_sim_clock,
                clock=Clock(clock_type=ClockType.STEADY_TIME),
            )
            self._owned.append(self._clock_check)
            # rcl's timer waits a whole period of the new time after the clock went back: a
            # bag on a loop shorter than the period (ros2 bag play --loop --clock) left
            # /diagnostics mute for good after its first loop.
            self._diagnostics_at = time.monotonic()
            self._clock_back = self.get_clock().create_jump_callback(
                JumpThreshold(min_forward=None, min_backward=Duration(nanoseconds=-1),
                              on_clock_change=False),
                post_callback=self._on_clock_back,
            )
        self._worker = threading.Thread(
            target=self._work, args=(self._mailbox,), name='cva_confidence_worker'
        )
        self._worker.daemon = True
        self._worker.start()
        self._warn_if_slow(pipeline)

    def _transport_topic(self, base: str, transport: str) -> str:
        """The topic of an ``image_transport`` transport of ``base``: under ``base`` as remapped,
        as image_transport and ``stereo_image_proc`` name it (``-r left/image_rect:=/cam/left``
        moves ``left/image_rect/compressed`` to ``/cam/left/compressed``); a remapping of the
        transport's own topic still applies while ``base`` is not remapped."""
        return f'{self.resolve_topic_name(base)}/{transport}'

    def _input_topics(self) -> dict[str, tuple[str, type]]:
        """Synchroniser key → (topic, message type) of the four inputs (no lock taken: called
        with it held too; ``image_transport`` is start-up only)."""
        compressed = self._node_config.image_transport == 'compressed'
        topics: dict[str, tuple[str, type]] = {}
        for key, topic in _TOPICS.items():
            if key.endswith('_info'):
                topics[key] = (topic, CameraInfo)
            elif compressed:
                topics[key] = (f'{topic}/compressed', CompressedImage)
            else:
                topics[key] = (topic, Image)
        return topics

    def _activate(self) -> None:
        preset = self.node_config.input_qos
        try:
            for key, (topic, msg_type) in self._input_topics().items():
                name = (
                    self._transport_topic(_TOPICS[key], 'compressed')
                    if msg_type is CompressedImage
                    else topic
                )
                with qos_override_errors(self.resolve_topic_name(name)):
                    self._subscriptions_in.append(self.create_subscription(
                        msg_type, name, partial(self._on_message, key), qos_profile(preset),
                        qos_overriding_options=QOS_OVERRIDES,
                    ))
        except ConfigError:
            for subscription in self._subscriptions_in:
                self.destroy_subscription(subscription)
            self._subscriptions_in = []
            raise
        with self._lock:
            self._stats.subscribed_at, self._stats.last_message_at = time.monotonic(), None
            self._stats.key_arrived_at = {}

    def _deactivate(self) -> None:
        """Unsubscribe; a frame waiting in the mailbox is dropped, pairing starts afresh."""
        for subscription in self._subscriptions_in:
            self.destroy_subscription(subscription)
        self._subscriptions_in = []
        # A frame being published: all of its outputs go out before (bounded: a deactivate
        # must not hang on a publish that does not end).
        waited = self._publishing.acquire(timeout=PUBLISH_WAIT_S)
        try:
            with self._lock:
                # Not subscribed, no input is expected: no warning for its silence.
                self._stats.subscribed_at = self._stats.last_message_at = None
                # The images to come (after an activate) may be of another camera or
                # resolution: parameter changes are not judged by these any more.
                self._input_size = None
                self._stats.dropped += self._mailbox.clear()
                self._stats.unmatched += sum(self._sync.pending().values())
                self._sync = self._make_sync(self._node_config)
                self._stats.paired_stamps_ns = {}
        finally:
            if waited:
                self._publishing.release()
        if not waited:
            # Not the node's own logger: this runs in a cleanup on shutdown too. Its name all
            # the same, namespace included: two cameras' nodes of one name are told apart.
            rclpy.logging.get_logger(self.get_logger().name).warning(
                f'a frame was still being published {PUBLISH_WAIT_S:g} s after the '
                'unsubscribe; not waiting for it (its remaining outputs may go out late)'
            )

    def _cleanup(self) -> bool:
        """Stop the worker and release the pipeline, publishers and timer.

        Returns:
            Whether the worker has ended (False: a frame outlasted :data:`STOP_TIMEOUT_S` and
            was left running, logged).
        """
        self._deactivate()
        stopped = self._stop_worker()
        for entity in self._owned:
            if isinstance(entity, Timer):
                self.destroy_timer(entity)
            else:
                self.destroy_publisher(entity)
        self._owned = []
        self._release_clock_back()
        with self._lock:
            self._pipeline = self._cold = None
        return stopped

    def _release_clock_back(self) -> None:
        # The clock outlives a cleanup: its callback would publish on a destroyed publisher.
        if self._clock_back is not None:
            self._clock_back.unregister()
            self._clock_back = None

    def _stop_worker(self) -> bool:
        if self.stop():
            return True
        self.frame_left_running = True
        device = self._pipeline.device if self._pipeline is not None else 'its device'
        # Not the node's own logger: its /rosout publisher dies with the context. Named after
        # it, namespace included (robot1.front.cva_confidence.stop), as its own lines are.
        when = f'{STOP_TIMEOUT_S:g} s after'
        if interrupt.hurried():
            when = 'at the SIGTERM that followed'
        rclpy.logging.get_logger(f'{self.get_logger().name}.stop').warning(
            f'a frame was still being processed {when} the stop '
            f'(confidence_method {self._pipeline_config.confidence_method} on '
            f'{device}); stopping without it'
        )
        return False

    @property
    def configured(self) -> bool:
        """Whether a pipeline is built (the managed node between configure and cleanup)."""
        with self._lock:
            return self._pipeline is not None

    def summary(self) -> str:
        """One line on what the node computes, for its ready line."""
        config, node_config = self.pipeline_config, self.node_config
        return (
            f'matcher={config.matcher} max_disparity={config.max_disparity} '
            f'confidence_method={config.confidence_method} downsample={config.downsample} '
            f'sync={"approximate" if node_config.approximate_sync else "exact"}'
            + (f' roi={config.roi_top:g}-{config.roi_bottom:g}'
               if (config.roi_top, config.roi_bottom) != (0.0, 1.0) else '')
            + (f' mask={Path(config.mask_path).name}' if config.mask_path else '')
        )

    # Configuration -------------------------------------------------------------------------

    @property
    def pipeline_config(self) -> PipelineConfig:
        """The configuration the next frame is processed with."""
        with self._lock:
            return self._pipeline_config

    @property
    def node_config(self) -> NodeConfig:
        """The node-side configuration in force."""
        with self._lock:
            return self._node_config

    @staticmethod
    def _make_sync(config: NodeConfig) -> StampSynchronizer:
        return StampSynchronizer(
            queue_size=config.queue_size,
            approximate=config.approximate_sync,
            tolerance_ns=config.tolerance_ns,
        )

    def _warn_if_slow(self, pipeline: StereoPipeline) -> None:
        """Say so when the paper network is to run on every pixel on a CPU (seconds a frame),
        and name the ``cva_*`` options that change nothing for the configured method."""
        config = pipeline.config
        unused = config.unused_options()
        if unused:
            self.get_logger().warning(
                f'{", ".join(unused)}: no effect on confidence_method '
                f'{config.confidence_method}' + (
                    ' (cva_cascade_fraction needs a cva_cascade)'
                    if config.confidence_method in COST_VOLUME_NETWORKS
                    else f' (they apply to {", ".join(COST_VOLUME_NETWORKS)})'
                )
            )
        if (
            config.confidence_method == 'cva_net'
            and pipeline.device.type == 'cpu'
            and config.cva_stride == 1
            and config.cva_cascade == 'none'
        ):
            self.get_logger().warning(
                'confidence_method cva_net on the CPU runs the paper network on every pixel '
                '(≈ 35 M multiply-adds a pixel at D = 64): seconds to minutes a frame. For '
                'online use take a GPU (device: cuda) or confidence_method cva_net_fast (the '
                'default: a few frames a second on a CPU, develop AUC within a few percent of '
                "cva_net's); the sparse paths (cva_stride, cva_cascade) stay seconds a frame on "
                'a CPU'
            )

    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        result = self._set_parameters(params)
        if not result.successful:
            restore_types(self, params)
        return result

    def _set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        # rclpy's own parameters (use_sim_time, …) are for rclpy to accept or refuse.
        params = [param for param in params if param.name in _OWN_PARAMETERS]
        if not params:
            return SetParametersResult(successful=True)
        asked = ', '.join(f'{p.name}={p.value!r}' for p in params)
        if not self.configured:
            # The managed node before configure (or after cleanup): the next configure builds
            # the pipeline; here the values only have to make a valid configuration, but for
            # faults of other parameters (start-up values, checked first at configure), which
            # are left to their own changes.
            fault: CVAError | None
            try:
                fault = change_fault(parameter_values(self), params)
            except CVAError as error:
                fault = error
            if fault is not None:
                self.get_logger().warning(f'parameter change refused ({asked}): {fault}')
                return SetParametersResult(successful=False, reason=str(fault))
            try:
                build_configs(parameter_values(self), params)
            except CVAError as error:
                self.get_logger().warning(
                    f'parameters set: {asked}; configure still refuses the configuration: {error}'
                )
            else:
                self.get_logger().info(f'parameters set: {asked}')
            return SetParametersResult(successful=True)
        try:
            pipeline_config, node_config = build_configs(parameter_values(self), params)
            pipeline = None
            # A file parameter set again to the same path reloads the file if it changed
            # since it was read: an edited mask (cva-mask --start … --overwrite) or retrained
            # weights at the same name were accepted as "set" while the old ones stayed. An
            # unchanged one is not (a parameter file loaded again rebuilt the pipeline).
            files = _file_stamps(pipeline_config)
            reload = any(
                p.name in _FILE_PARAMETERS and p.value and files[p.name] != self._files[p.name]
                for p in params
            )
            still: InputError | None = None
            if reload or pipeline_config != self.pipeline_config:
                # Built here, before accepting, so that e.g. missing weights or a device that
                # is not there reject the change, and checked against the images coming in.
                pipeline = StereoPipeline(pipeline_config)
                with self._lock:
                    size, seen_at = self._input_size, self._input_size_at
                if size is not None:
                    try:
                        pipeline.check_input_size(*size)
                    except InputError as error:
                        # Say which images: a camera restarted with another resolution is
                        # judged by its first frame, not before.
                        said = InputError(
                            f'{error} (the images coming in: {size[0]}×{size[1]} px, the last '
                            f'one {time.monotonic() - seen_at:.1f} s ago)'
                        )
                        if not self._eases_memory(pipeline, size, error):
                            raise said from error
                        still = said
        except CVAError as error:
            self.get_logger().warning(f'parameter change refused ({asked}): {error}')
            return SetParametersResult(successful=False, reason=str(error))
        except Exception as error:  # noqa: BLE001  (raised here, it would end the executor's spin)
            # Not a refusal the pipeline foresaw (CUDA out of memory loading the weights, a
            # fault in a library): refused all the same, and the node goes on as it was.
            why = f'{type(error).__name__}: {error}'
            self.get_logger().error(f'parameter change refused ({asked}): building the new '
                                    f'pipeline raised {why}')
            return SetParametersResult(successful=False, reason=why)
        with self._lock:
            if pipeline is not None:
                self._pipeline, self._pipeline_config = pipeline, pipeline_config
                self._files = files
                # Warmed up as on start-up, but by the worker before its next frame (the
                # matcher's kernels compile: seconds on a cold cache), not here on the executor.
                self._cold = pipeline
            old = self._node_config
            self._node_config = node_config
            sync_keys = ('queue_size', 'approximate_sync', 'approximate_sync_tolerance_seconds')
            if any(getattr(old, key) != getattr(node_config, key) for key in sync_keys):
                self._stats.unmatched += sum(self._sync.pending().values())
                self._sync = self._make_sync(node_config)
                self._stats.paired_stamps_ns = {}
            if (old.approximate_sync, old.tolerance_ns) != (
                node_config.approximate_sync, node_config.tolerance_ns
            ):
                # A user's change is judged afresh: still too wide, it is logged with its new
                # value; set back to a value logged a moment ago, it is logged again too.
                self._reset_wide_tolerance()
        if still is not None:
            # Taken though its frames are still dropped (rclpy's reply to a change taken has
            # no reason: the log says it).
            self.get_logger().warning(
                f'parameters set: {asked}; the images coming in still do not fit: {still}'
            )
        else:
            self.get_logger().info(f'parameters set: {asked}')
        if pipeline is not None:
            self._mailbox.poke()
            self._warn_if_slow(pipeline)
        return SetParametersResult(successful=True)

    def _eases_memory(
        self, pipeline: StereoPipeline, size: tuple[int, int], error: InputError
    ) -> bool:
        """Whether ``error``, of ``pipeline.check_input_size(*size)``, is its memory check's
        alone and ``pipeline`` needs less memory for such images than the current one, which
        does not fit them either: a step toward a configuration that fits, taken (warned)
        rather than refused. Refused, an operator had no way out one ``param set`` at a time
        while every frame was dropped: 2448×2048 px with census_sgm at D = 256 and 0.5 GB
        left, downsample 4 needs 0.56 GB and max_disparity 128 4.49 GB, both at once 0.28."""
        from cva_confidence_ros.memory import shortfall

        # The memory check comes last: raised there, the size, mask and width checks passed.
        if not isinstance(error, MemoryShortfallError):
            return False
        with self._lock:
            current = self._pipeline
        if current is None:
            return False
        try:
            need = current.memory_needed(*size)
        except InputError:  # the current mask is not of these images: nothing to compare
            return False
        return pipeline.memory_needed(*size) < need and shortfall(need) is not None

    # Executor side ------------------------------------------------------------------------

    def _on_message(self, key: str, msg: Any) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        arrived = time.monotonic()
        with self._lock:
            self._stats.last_message_at = arrived
            self._stats.key_arrived_at[key] = arrived
            if key == 'left':
                if self._stats.left_arrived_at is not None:
                    self._stats.left_arrival_gaps_s.append(arrived - self._stats.left_arrived_at)
                self._stats.left_arrived_at = arrived
            self._stats.messages += 1
            self._stats.window_messages += 1
            self._stats.window_keys[key] = self._stats.window_keys.get(key, 0) + 1
            self._stats.last_stamps_ns[key] = stamp
            paired = self._stats.paired_stamps_ns.get(key)
            if paired is not None and stamp <= paired:
                self._stats.window_old += 1
            too_wide = self._note_left_stamp(stamp, arrived) if key == 'left' else None
            sync = self._sync
            before = sync.dropped
            matched = sync.add(key, stamp, msg)
            self._stats.unmatched += sync.dropped - before
            jumps = [
                (item.jumped_from_ns, item.stamp_ns)
                for item in matched
                if item.jumped_from_ns is not None
            ]
            self._stats.jumps += len(jumps)
            taken = []
            for item in matched:
                self._stats.paired_stamps_ns.update(item.stamps_ns)
                self._stats.pairs += 1
                self._stats.window_pairs += 1
                if self._throttled(item):
                    self._stats.throttled += 1
                else:
                    taken.append(item)
            if taken:  # both sets of a short jump back are processed, oldest first
                self._stats.dropped += self._mailbox.put(taken)
        if too_wide is not None:
            # Once as it starts or changes, not every throttle period: /diagnostics shows it
            # as a warning for as long as it holds.
            self.get_logger().warning(too_wide)
        if stamp == 0:
            # A driver that leaves its header stamps at zero: frames pair by stamp, so every
            # frame after the first looked like the first one again ('a bag on a loop?').
            self._log_throttle.log(
                self.get_logger(),
                'header stamp 0',
                f'{self._input_names()[key]} has header stamp 0: its driver does not stamp its '
                'messages; frames pair by stamp (left, right and both camera infos of a frame '
                'need the time of its exposure), so most frames are lost: set the stamps in the '
                'driver',
            )
        for previous, now in jumps:
            if previous == now == 0:
                continue  # said above
            if previous == now:
                # Not back at all: the frame paired last came again (a bag of one frame played
                # again, or on a loop).
                self._log_throttle.log(
                    self.get_logger(),
                    'input stamps repeat',
                    f'input stamps repeat: the frame {_seconds(now)} came again (a bag played '
                    'again or on a loop?): pairing starts over from there',
                )
                continue
            self._log_throttle.log(
                self.get_logger(),
                'input stamps jumped back',
                f'input stamps jumped back {(previous - now) / 1e9:.3f} s, from '
                f'{_seconds(previous)} to {_seconds(now)} (bag loop, driver restart or simulator '
                'reset?): pairing starts over from there',
            )

    def _throttled(self, item: MatchedSet) -> bool:
        """Whether ``max_rate_hz`` skips this set (call with the lock held): its stamp is
        closer to the last set taken than the smallest period, and no jump back lies between."""
        period = self._node_config.min_period_ns
        last = self._stats.last_taken_ns
        # A stamp before the last one taken is a reset the synchroniser may not have seen (it
        # is made anew on activate and on sync changes): taken, not skipped until time is back.
        if period and last is not None and item.jumped_from_ns is None and (
            0 <= item.stamp_ns - last < period
        ):
            return True
        self._stats.last_taken_ns = item.stamp_ns
        return False

    def _note_left_stamp(self, stamp: int, now: float) -> str | None:
        """Track the spacing of the left images and whether the approximate-sync tolerance is
        too wide for it (call with the lock held).

        Args:
            stamp: The left image's stamp (ns).
            now: Its arrival (monotonic s).

        Returns:
            The warning to log when the tolerance is too wide (:meth:`_wide_tolerance_period`)
            and that has not been logged yet: it just began, the tolerance changed, or the
            period moved by more than :data:`_PERIOD_CHANGE`; a return to the values logged
            within the throttle period (a period on the border, in and out) is not logged
            again. Else None.
        """
        stats = self._stats
        previous, stats.left_stamp_ns = stats.left_stamp_ns, stamp
        config = self._node_config
        if not config.approximate_sync:
            self._wide_holds = False
            return None
        if previous is None or stamp <= previous:
            return None  # no new spacing (the first image, stamps gone back): as it was
        stats.left_gaps_ns.append(stamp - previous)
        period = self._wide_tolerance_period()
        if period is None:
            self._wide_holds = False
            return None
        tolerance = config.tolerance_ns
        last = self._wide_logged
        if (
            last is not None
            and last[0] == tolerance
            and abs(period - last[1]) <= _PERIOD_CHANGE * last[1]
            and (self._wide_holds or now - last[2] < LOG_THROTTLE_S)
        ):
            self._wide_holds = True
            return None
        self._wide_holds = True
        self._wide_logged = (tolerance, period, now)
        return _wide_tolerance_message(tolerance, period)

    def _wide_tolerance_period(self) -> float | None:
        """The left images' period (ns) when approximate sync is on with a tolerance of half
        of it or more, so that an image can pair with its neighbour's partner; else None
        (lock held)."""
        config = self._node_config
        period = self._stats.left_period_ns
        if not config.approximate_sync or period is None:
            return None
        return period if 2 * config.tolerance_ns >= period else None

    def _reset_wide_tolerance(self) -> None:
        """Forget the "tolerance too wide" warning logged (lock held): judged afresh."""
        self._wide_holds = False
        self._wide_logged = None

    def _input_names(self) -> dict[str, str]:
        """Synchroniser key → the input's topic as the logs name it: the relative name, or
        the topic it is remapped to (the one to check with ``ros2 topic``)."""
        names = {key: topic for key, (topic, _) in self._input_topics().items()}
        for key, subscription in zip(names, self._subscriptions_in, strict=False):
            if subscription.topic_name != self.resolve_topic_name(names[key], only_expand=True):
                names[key] = subscription.topic_name
        return names

    def _unpaired_reason(self, stats: _Stats, elapsed: float) -> str:
        """Why messages arrive but none pair up, naming the topics (lock held)."""
        names = self._input_names()
        silent = [topic for key, topic in names.items() if not stats.window_keys.get(key)]
        if silent:
            text = (
                f'messages arrive but none pair up: nothing on {", ".join(silent)} in the last '
                f'{elapsed:.1f} s'
            )
            silent_keys = [key for key in names if names[key] in silent]
            images_only = all(not key.endswith('_info') for key in silent_keys)
            if images_only:
                text += ' while the camera infos come' + self._silent_images_reason(
                    stats, silent_keys
                )
            elif all(key.endswith('_info') for key in names if names[key] in silent):
                # A driver that publishes its camera_info once, latched (transient local):
                # `ros2 topic echo` shows it, and a volatile subscriber gets none.
                text += (
                    ' while the images come: every image pairs with the camera_info of its '
                    'stamp, so one published once (latched) is not enough'
                )
            return text
        # (A new synchroniser, after a parameter change, forgets what was paired.)
        paired = stats.paired_stamps_ns
        if stats.window_old == stats.window_messages and all(key in paired for key in names):
            return self._old_stamps_reason(stats, names)
        stamps = ', '.join(
            f'{topic} {_seconds(stats.last_stamps_ns[key])}' for key, topic in names.items()
        )
        how = (
            f'approximate sync pairs stamps within {self._node_config.tolerance_ns / 1e9:g} s'
            if self._node_config.approximate_sync
            else 'exact sync pairs equal stamps only (approximate_sync: true for cameras '
            'that are not hardware-synchronised)'
        )
        return f'messages arrive but none pair up; newest stamps: {stamps}; {how}'

    def _silent_images_reason(self, stats: _Stats, keys: list[str]) -> str:
        """Why the images of ``keys`` do not come while their camera infos do (lock held): the
        large-message hint only where it can hold, images that never arrived from a publisher
        there is; one that stopped, or no publisher, is said as such."""
        names = self._input_names()
        topics = dict(zip(names, self._subscriptions_in, strict=False))
        unpublished = [
            names[key] for key in keys
            if key in topics and not self.count_publishers(topics[key].topic_name)
        ]
        if unpublished:
            return (
                f': no publisher on {", ".join(unpublished)} (its driver or rectifier not '
                'running, or on another topic name?)'
            )
        arrived = [stats.key_arrived_at[key] for key in keys if key in stats.key_arrived_at]
        if arrived:
            # They came (small enough to come): a paused or restarted publisher, whose size
            # matters only if it changed.
            text = (
                f'; images came until {time.monotonic() - max(arrived):.1f} s ago and stopped '
                '(their publisher stopped sending, or was restarted?)'
            )
            if large_messages_unset():
                text += f'; restarted at a larger size: {LARGE_MESSAGES_HINT}'
            return text
        return f': {LARGE_MESSAGES_HINT}' if large_messages_unset() else ''

    def _crowded_inputs(self) -> str:
        """The inputs with more than one publisher, with their counts ('' when none; lock
        held, while subscribed)."""
        names = self._input_names()
        counts = {
            names[key]: self.count_publishers(subscription.topic_name)
            for key, subscription in zip(names, self._subscriptions_in, strict=False)
        }
        return ', '.join(f'{topic} ({count})' for topic, count in counts.items() if count > 1)

    def _few_paired_reason(self, stats: _Stats, elapsed: float) -> str:
        """Why most left images of the period paired with nothing, naming each input's count;
        '' when most pair (lock held). A camera_info at a lower rate than the images pairs only
        the images of its stamps: the node then processed a tenth of a camera's frames with an
        OK status."""
        lefts = stats.window_keys.get('left', 0)
        if not stats.window_pairs or lefts < 4 or 2 * stats.window_pairs >= lefts:
            return ''
        counts = ', '.join(
            f'{topic} {stats.window_keys.get(key, 0)}'
            for key, topic in self._input_names().items()
        )
        return (
            f'only {stats.window_pairs} of {lefts} left images paired in the last {elapsed:.1f} '
            f's (messages: {counts}): a frame needs all four inputs with its stamp (a '
            'camera_info published less often than the images pairs only those of its stamps)'
        )

    def _silent_input(self, stats: _Stats, now: float) -> str:
        """Why no input came for a while, naming the topics; '' when it comes (lock held).

        Silent means no message on any input for a whole diagnostics period, and for three
        times the usual time between the left images once that is known (a slow camera is not
        silent between its frames), while subscribed, and with no frame processed in the period.
        """
        if stats.subscribed_at is None or stats.window_messages or stats.window_processed:
            return ''
        since = stats.last_message_at if stats.last_message_at is not None else stats.subscribed_at
        silent_s = now - since
        limit = self._node_config.diagnostics_period_seconds
        if stats.left_arrival_period_s is not None:
            limit = max(limit, 3 * stats.left_arrival_period_s)
        if silent_s < limit:
            return ''
        topics = ', '.join(self._input_names().values())
        if stats.last_message_at is None:
            text = (
                f'no input: nothing on {topics} in the {silent_s:.1f} s since the node '
                'subscribed (camera driver not running, or on other topic names?)'
            )
            if self._node_config.input_qos == 'reliable':
                # rclpy says so once, when it discovers the driver; this says it every period.
                text += (
                    '; input_qos reliable takes nothing from a best-effort (sensor-data) '
                    'publisher: input_qos sensor_data takes both'
                )
            return text
        return (
            f'no input for {silent_s:.1f} s: nothing on {topics} since the last message '
            '(camera driver stopped or disconnected?)'
        )

    def _old_stamps_reason(self, stats: _Stats, names: dict[str, str]) -> str:
        """Why messages no newer than the frame paired last do not pair (lock held): the
        synchroniser holds them aside as repeats or late ones until they show a jump back."""
        key = next(iter(names))
        newest, paired = stats.last_stamps_ns[key], stats.paired_stamps_ns[key]
        if newest == paired:
            what = (
                f'the input stamps repeat: {names[key]} {_seconds(newest)} again, the frame '
                'paired last (the same frames a second time: a bag played again?)'
            )
        else:
            what = (
                f'the input stamps went back {(paired - newest) / 1e9:.3f} s: {names[key]} '
                f'{_seconds(newest)} after the frame {_seconds(paired)} was paired (a bag '
                'played again, a driver restart or a simulator reset?)'
            )
        jump = self._sync.min_jump_ns / 1e9
        return (
            f'messages arrive but none pair up: {what}; such messages wait aside (counted '
            f'unmatched) until a whole frame of them lies {jump:g} s or more back, or a second '
            'one follows: then pairing starts over from them'
        )

    # Worker side --------------------------------------------------------------------------

    def _stopping(self, mailbox: _Mailbox) -> bool:
        """Whether the worker of ``mailbox`` is being stopped: the mailbox closed (a stop, a
        cleanup) or the context shut down."""
        return mailbox.closed or not self.context.ok()

    def _work(self, mailbox: _Mailbox) -> None:
        # The worker's own mailbox, not the node's: after a cleanup and a new configure, a
        # worker left running with a long frame must not take the new worker's frames.
        while True:
            item = mailbox.take()
            if self._stopping(mailbox):
                return
            self._warm_up_new_pipeline(mailbox)
            if item is None:  # woken for the warm-up: the next frame waits in the mailbox
                continue
            try:
                self._process(item, mailbox)
            except CVAError as error:
                with self._lock:
                    if self._stopping(mailbox):
                        # As below: after a new configure, a frame of the old one must not
                        # count in the new statistics (nor be logged as the new one's).
                        return
                    self._stats.invalid += 1
                    self._stats.window_invalid += 1
                    self._stats.last_invalid = str(error)
                self._log_throttle.log(
                    self.get_logger(), str(error),
                    f'dropped frame {_seconds(item.stamp_ns)}: {error}',
                )
            except Exception as error:  # noqa: BLE001  (the worker must outlive any frame)
                if self._stopping(mailbox):
                    # Ctrl-C shuts the context down (in C, before any Python runs), and the
                    # frame in progress then fails to publish: that is the stop, not a fault.
                    return
                what = f'{type(error).__name__}: {error}'
                with self._lock:
                    self._stats.failed += 1
                    self._stats.window_failed += 1
                    self._stats.last_failure = what
                self._log_throttle.log(
                    self.get_logger(),
                    what,
                    f'processing failed on frame {_seconds(item.stamp_ns)}: {what}',
                    error=True,
                )
            if self._stopping(mailbox):
                # A frame dropped because the stop came while it ran; Ctrl-C (the context
                # shut down in C) closes no mailbox, so take() would wait for good.
                return

    def _warm_up_new_pipeline(self, mailbox: _Mailbox) -> None:
        """Warm up the pipeline a parameter change swapped in, if any, as the node does on
        start-up: the matcher's kernels compile (or load from their cache) and MC-CNN loads its
        weights here, on the worker, and not in the parameter callback on the executor. Frames
        that come meanwhile wait in the mailbox, the newest replacing the others (dropped)."""
        with self._lock:
            pipeline, self._cold = self._cold, None
            dropped = self._stats.dropped
        if pipeline is None:
            return
        tic = time.perf_counter()
        try:
            pipeline.warm_up()
        except Exception as error:  # noqa: BLE001  (the worker must outlive a warm-up)
            if not self._stopping(mailbox):
                self.get_logger().warning(
                    f'warming up the new pipeline failed ({type(error).__name__}: {error}); '
                    'its first frame may be slow'
                )
            return
        if self._stopping(mailbox):
            return
        with self._lock:
            dropped = self._stats.dropped - dropped
        self.get_logger().info(
            f'new pipeline warmed up in {(time.perf_counter() - tic) * 1e3:.0f} ms'
            + (f'; {dropped} frame(s) dropped meanwhile' if dropped else '')
        )

    def _process(self, item: MatchedSet, mailbox: _Mailbox) -> None:
        start = time.perf_counter()
        left_msg = item.items['left']
        left, right, geometry = stereo_pair_from_messages(
            left_msg, item.items['right'], item.items['left_info'], item.items['right_info']
        )
        with self._lock:
            if self._stopping(mailbox):
                # Left running past a cleanup (and perhaps a new configure): neither the new
                # configuration's input size nor its pipeline are this frame's.
                return
            self._input_size = (left.shape[1], left.shape[0])
            self._input_size_at = time.monotonic()
            pipeline, config, node_config = (
                self._pipeline,
                self._pipeline_config,
                self._node_config,
            )
        if pipeline is None:  # cleaned up (the managed node) while this frame waited
            return
        convert_ms = (time.perf_counter() - start) * 1e3

        result = pipeline.process(left, right)
        with self._publishing:
            if self._stopping(mailbox):
                # Stopped or cleaned up while it ran: after a new configure, its outputs (of
                # the old parameters) must not go out on the new publishers nor count in new
                # stats. (The managed node: deactivated since it was taken.)
                return
            tic = time.perf_counter()
            self._publish(result, left_msg.header, geometry, config, node_config)
            if self._pub_info.get_subscription_count():
                info = item.items['left_info']
                self._pub_info.publish(
                    scale_camera_info(
                        image_camera_info(info, left.shape[1], left.shape[0]),
                        config.downsample,
                        left_msg.header,
                    )
                )
        timings = dict(result.timings_ms)
        timings['convert'] = convert_ms
        timings['publish'] = (time.perf_counter() - tic) * 1e3
        timings['frame'] = (time.perf_counter() - start) * 1e3
        kept_fraction = result.kept_fraction
        region = result.region
        judged = result.confidence if region is None else result.confidence[region]
        mean_confidence = float(np.mean(np.nan_to_num(judged, nan=0.0))) if judged.size else 0.0
        judged_fraction = 1.0 if region is None else float(region.mean())
        expected_error = result.expected_kept_error
        with self._lock:
            if self._stopping(mailbox):
                # Stopped while it published (and perhaps configured anew): not the new stats'.
                return
            self._stats.processed += 1
            self._stats.window_processed += 1
            self._stats.record_timings(timings)
            self._stats.last_kept_fraction = kept_fraction
            self._stats.window_kept_sum += kept_fraction
            self._stats.last_mean_confidence = mean_confidence
            self._stats.last_judged_fraction = judged_fraction
            self._stats.last_speckle_fraction = result.speckle_fraction
            self._stats.last_expected_kept_error = expected_error
            if expected_error is not None:
                # Weighted by the kept pixels: the predicted share of wrong ones among all kept.
                self._stats.window_expected_wrong += expected_error * kept_fraction
                self._stats.window_expected_kept += kept_fraction

    def _publish(
        self,
        result: PipelineResult,
        header: Any,
        geometry: StereoGeometry,
        config: PipelineConfig,
        node_config: NodeConfig,
    ) -> None:
        disparity = result.disparity
        if result.scale != 1.0:
            # The pipeline crops the bottom/right rest and shrinks by exactly 1/downsample.
            geometry = geometry.scaled(result.scale)
        # Already in [0, 1] by the method's fixed map; NaN (none expected) would break that.
        confidence = np.clip(np.nan_to_num(result.confidence, nan=0.0), 0.0, 1.0)
        keep = result.valid
        if self._pub_disparity.get_subscription_count():
            self._pub_disparity.publish(
                disparity_to_message(
                    disparity, header, geometry, config.max_disparity, config.disparity_step
                )
            )
        if self._pub_confidence.get_subscription_count():
            self._pub_confidence.publish(array_to_image(confidence, header))
        if self._pub_filtered.get_subscription_count():
            filtered = result.filtered_disparity
            self._pub_filtered.publish(
                disparity_to_message(
                    filtered, header, geometry, config.max_disparity, config.disparity_step
                )
            )
        if node_config.publish_points and self._pub_points.get_subscription_count():
            cloud = stereo_cloud(
                disparity,
                confidence,
                result.left,
                geometry,
                keep,
                organized=node_config.points_organized,
                with_confidence=node_config.points_confidence,
            )
            self._pub_points.publish(cloud_to_message(cloud, header))
        depth_raw = self._pub_depth.get_subscription_count()
        depth_compressed = self._pub_depth_compressed.get_subscription_count()
        if node_config.publish_depth and (depth_raw or depth_compressed):
            depth = disparity_to_depth(disparity, geometry, keep)
            depth_msg = depth_to_image(depth, header, node_config.depth_encoding)
            if depth_raw:
                self._pub_depth.publish(depth_msg)
            if depth_compressed:
                self._pub_depth_compressed.publish(
                    depth_image_to_compressed_depth(
                        depth_msg,
                        node_config.compressed_depth_max,
                        node_config.compressed_depth_quantization,
                        node_config.compressed_depth_png_level,
                    )
                )
        overlay_raw = self._pub_overlay.get_subscription_count()
        overlay_compressed = self._pub_overlay_compressed.get_subscription_count()
        if overlay_raw or overlay_compressed:
            overlay = confidence_overlay(result.left, confidence, keep)
            if overlay_raw:
                self._pub_overlay.publish(rgb_to_image(overlay, header))
            if overlay_compressed:
                self._pub_overlay_compressed.publish(
                    rgb_to_compressed(
                        overlay, header, jpeg_quality=node_config.overlay_jpeg_quality
                    )
                )
        if node_config.publish_scan and self._pub_scan.get_subscription_count():
            scan = disparity_to_scan(
                disparity, geometry, keep, confidence, node_config.scan_config()
            )
            frame = scan_frame_id(header.frame_id, node_config.scan_frame_id)
            if frame == header.frame_id and not (
                node_config.scan_frame_id or self._scan_frame_warned
            ):
                self._scan_frame_warned = True
                self.get_logger().warning(
                    f'scan is published in the camera frame {frame!r}, which is not named as '
                    'an optical frame (<name>_optical_frame); a LaserScan needs x forward and z '
                    'up: set scan_frame_id to the camera body frame'
                )
            pitch = node_config.scan_pitch
            if pitch and not (node_config.scan_frame_id or self._scan_pitch_warned):
                self._scan_pitch_warned = True
                self.get_logger().warning(
                    f'scan is level (scan_pitch {pitch:g} rad taken out) but published in the '
                    f'camera frame {frame!r}, which is pitched with the camera: consumers place '
                    'its returns on a plane tilted by the pitch; set scan_frame_id to a level '
                    'frame (e.g. base_link)'
                )
            self._pub_scan.publish(scan_to_message(scan, header, frame))

    # Diagnostics --------------------------------------------------------------------------

    def diagnostics(self) -> DiagnosticStatus:
        """The node's current ``DiagnosticStatus`` (counters since start, rates per window)."""
        now, clock_ns = time.monotonic(), self._sim_clock_ns()
        with self._lock:
            stats = self._stats
            elapsed = max(now - stats.window_start, 1e-9)
            if clock_ns is not None and stats.window_start_clock_ns is not None:
                # Under use_sim_time the window is a period of simulated time (the timer's
                # clock): in wall seconds a 10 Hz camera read 20 Hz at 2× real time (max_rate_hz
                # 5, of stamp time, as 10), and a pause of the simulation lowered the rate of
                # the period that spans it. Not when the clock went back (a simulator reset).
                sim_elapsed = (clock_ns - stats.window_start_clock_ns) / 1e9
                if sim_elapsed > 0:
                    elapsed = sim_elapsed
            rate = stats.window_processed / elapsed
            level, message = DiagnosticStatus.OK, f'processing at {rate:.1f} Hz'
            kept = (
                stats.window_kept_sum / stats.window_processed if stats.window_processed else None
            )
            expected = (
                stats.window_expected_wrong / stats.window_expected_kept
                if stats.window_expected_kept > 0
                else None
            )
            floor = self._node_config.min_kept_fraction
            if kept is not None and kept < floor:
                level = DiagnosticStatus.WARN
                message = (
                    f'only {100 * kept:.1f} % of the pixels are confident (min_kept_fraction '
                    f'{floor:g}): a blinded or covered camera, no texture, or a wrong '
                    'calibration?'
                )
            ceiling = self._node_config.max_expected_kept_error
            if expected is not None and expected > ceiling:
                level = DiagnosticStatus.WARN
                message = (
                    f'the confidence predicts {100 * expected:.1f} % wrong disparities among the '
                    f'kept pixels (max_expected_kept_error {ceiling:g}): blur, fog, or a '
                    'rectification gone wrong?'
                )
            # Logged once where it is seen; here for as long as it holds (while subscribed:
            # no input comes to pair otherwise).
            wide = self._wide_tolerance_period() if stats.subscribed_at is not None else None
            if wide is not None:
                level = DiagnosticStatus.WARN
                message = _wide_tolerance_message(self._node_config.tolerance_ns, wide)
            few = self._few_paired_reason(stats, elapsed)
            if few:
                level, message = DiagnosticStatus.WARN, few
            if stats.window_invalid:
                level = DiagnosticStatus.WARN
                message = f'{stats.window_invalid} bad frame(s) dropped: {stats.last_invalid}'
            if stats.window_failed:
                # Some frames came out (none: the ERROR below); the others failed all the same.
                level = DiagnosticStatus.WARN
                failed = f'{stats.window_failed} frame(s) failed: {stats.last_failure}'
                message = f'{message}; {failed}' if stats.window_invalid else failed
            crowded = self._crowded_inputs()
            if crowded:
                # Two cameras (or a bag and the live driver) on one input: their messages pair
                # with the other's (approximate sync), silently wrong; or are dropped unpaired.
                level = DiagnosticStatus.WARN
                message = (
                    f'more than one publisher on {crowded}: two cameras, or a bag played '
                    "beside the driver, on one topic? A frame may pair one camera's image with "
                    "the other's; stop or remap all but one"
                )
            if stats.window_messages and not stats.window_pairs:
                level = DiagnosticStatus.WARN
                message = self._unpaired_reason(stats, elapsed)
            silence = self._silent_input(stats, now)
            if silence:
                level, message = DiagnosticStatus.WARN, silence
            if stats.window_failed and not stats.window_processed:
                level, message = DiagnosticStatus.ERROR, f'processing fails: {stats.last_failure}'
            values = {
                'messages_received': stats.messages,
                'frames_received': stats.pairs,
                'frames_processed': stats.processed,
                'frames_dropped': stats.dropped,
                'frames_throttled': stats.throttled,
                'messages_unmatched': stats.unmatched,
                'frames_invalid': stats.invalid,
                'frames_failed': stats.failed,
                'stamp_jumps': stats.jumps,
                'processing_rate_hz': f'{rate:.3f}',
                'matcher': self._pipeline_config.matcher,
                'confidence_method': self._pipeline_config.confidence_method,
                'max_disparity': self._pipeline_config.max_disparity,
                'downsample': self._pipeline_config.downsample,
                'kept_fraction': _fraction(kept),
                'last_kept_fraction': _fraction(stats.last_kept_fraction),
                'last_mean_confidence': _fraction(stats.last_mean_confidence),
                'last_speckle_fraction': _fraction(stats.last_speckle_fraction),
                'last_judged_fraction': _fraction(stats.last_judged_fraction),
                'expected_kept_error': _fraction(expected),
                'last_expected_kept_error': _fraction(stats.last_expected_kept_error),
            }
            for key, value in stats.last_timings_ms.items():
                values[f'last_{key}_ms'] = f'{value:.2f}'
            for key, value in stats.mean_timings_ms.items():
                values[f'mean_{key}_ms'] = f'{value:.2f}'
            stats.window_messages = stats.window_pairs = 0
            stats.window_processed = stats.window_invalid = stats.window_failed = 0
            stats.window_kept_sum = 0.0
            stats.window_expected_wrong = stats.window_expected_kept = 0.0
            stats.window_keys = {}
            stats.window_old = 0
            stats.window_start, stats.window_start_clock_ns = now, clock_ns
        return diagnostic_status(self, 'stereo confidence', level, message, values)

    def _check_sim_clock(self) -> None:
        """Warn once when the node runs on simulated time that has not started."""
        self._clock_check.cancel()
        clock = self.get_clock()
        if getattr(clock, 'ros_time_is_active', False) and clock.now().nanoseconds == 0:
            self.get_logger().warning(
                'use_sim_time is true and no /clock has come: /diagnostics is published on '
                'simulated time and waits for it (a bag played without --clock? ros2 bag play '
                '--clock, or use_sim_time false); frames are processed all the same'
            )

    def _sim_clock_ns(self) -> int | None:
        """The node's clock (ns) while it runs on simulated time (``use_sim_time``); None on
        the system clock, or before the first ``/clock`` message (simulated time 0)."""
        clock = self.get_clock()
        if not getattr(clock, 'ros_time_is_active', False):
            return None
        return clock.now().nanoseconds or None

    def _on_clock_back(self, jump: object) -> None:
        """Publish /diagnostics as the simulated clock goes back (a bag's loop, a simulator
        reset) where a period of wall time has passed without: the timer then waits a whole
        period of the new time, which a loop shorter than the period never reaches."""
        with self._lock:
            period = self._node_config.diagnostics_period_seconds
        if time.monotonic() - self._diagnostics_at >= period:
            self._publish_diagnostics()

    def _publish_diagnostics(self) -> None:
        self._diagnostics_at = time.monotonic()
        status = self.diagnostics()
        publish_status(self, self._pub_diagnostics, status)
        summary = {kv.key: kv.value for kv in status.values}
        # Bad frames are logged where they are dropped; input that never pairs is logged here.
        line = (
            f'{status.message}; received {summary["frames_received"]}, processed '
            f'{summary["frames_processed"]}, dropped {summary["frames_dropped"]}, throttled '
            f'{summary["frames_throttled"]}, invalid {summary["frames_invalid"]}, failed '
            f'{summary["frames_failed"]}, frame {summary.get("mean_frame_ms", "-")} ms'
        )
        # rclpy throttles per call site and allows one severity per site: a site for each
        # warning, so that none throttles another away. (Bad and failed frames are logged as
        # warnings and errors where they are dropped, a too wide approximate-sync tolerance
        # where it is first seen: their status is an info line here.)
        if status.message.startswith('messages arrive but none pair up'):
            self.get_logger().warning(line, throttle_duration_sec=LOG_THROTTLE_S)
        elif status.message.startswith('no input'):
            self.get_logger().warning(line, throttle_duration_sec=LOG_THROTTLE_S)
        elif status.message.startswith('more than one publisher'):
            self.get_logger().warning(line, throttle_duration_sec=LOG_THROTTLE_S)
        elif status.message.startswith(('only ', 'the confidence predicts')):
            # min_kept_fraction / max_expected_kept_error: logged nowhere else
            self.get_logger().warning(line, throttle_duration_sec=LOG_THROTTLE_S)
        else:
            self.get_logger().info(line, throttle_duration_sec=LOG_THROTTLE_S)

    def stats(self) -> dict[str, int]:
        """Counters since start.

        ``frames_received`` counts synchronised sets; each is then throttled (skipped under
        ``max_rate_hz``), processed, dropped (replaced by a newer one before the worker took
        it, or left by a deactivate of the managed node), invalid (bad input) or failed.
        ``messages_unmatched`` counts single messages the synchroniser evicted unpaired;
        ``stamp_jumps`` the times the input stamps went back and pairing started over.
        """
        with self._lock:
            s = self._stats
            return {
                'messages_received': s.messages,
                'frames_received': s.pairs,
                'frames_processed': s.processed,
                'frames_dropped': s.dropped,
                'frames_throttled': s.throttled,
                'messages_unmatched': s.unmatched,
                'frames_invalid': s.invalid,
                'frames_failed': s.failed,
                'stamp_jumps': s.jumps,
            }

    # Life cycle ---------------------------------------------------------------------------

    def stop(self, timeout: float = STOP_TIMEOUT_S) -> bool:
        """Stop the worker thread (waits for the frame in progress, up to ``timeout`` s).

        Returns:
            Whether the worker has ended: False while a frame is still being processed.
        """
        self._mailbox.close()
        worker = self._worker
        if worker is None:
            return True
        if worker.is_alive() and worker is not threading.current_thread():
            # In slices: a SIGTERM during the wait (ros2 launch's, 5 s after its SIGINT and 5 s
            # before its SIGKILL) ends it (interrupt.hurry), the frame left running.
            deadline = time.monotonic() + timeout
            while worker.is_alive() and not interrupt.hurried():
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    break
                worker.join(min(remaining, 0.1))
        return not worker.is_alive()

    def destroy_node(self) -> None:
        """Stop the worker, then destroy the node.

        A frame that outlasts :data:`STOP_TIMEOUT_S` (the paper network on a CPU takes minutes)
        is logged and left running; :attr:`frame_left_running` is then True, and
        :func:`~cva_confidence_ros.ros.common.run_node` ends the process without waiting.
        """
        self._stop_worker()
        self._release_clock_back()
        super().destroy_node()


def _warm_up_scan() -> None:
    """Compile (or load from its cache) the scan's numba kernel, which the pipeline's warm-up
    does not reach: on a cold cache it took ≈ 0.3 s of the first frame a ``scan`` subscriber
    got (a container whose cache lives in a fresh temporary folder: every start)."""
    geometry = StereoGeometry(fx=1.0, fy=1.0, cx=1.0, cy=0.5, cx_right=1.0, baseline=1.0)
    ones = np.ones((2, 4), np.float32)
    disparity_to_scan(ones, geometry, ones > 0, ones)


class ConfidenceNode(ConfidenceCore):
    """rclpy node around :class:`StereoPipeline`; see the module docstring for topics.

    Configured and subscribed as soon as it is built; the managed (lifecycle) variant is
    :class:`~cva_confidence_ros.ros.lifecycle_node.ManagedConfidenceNode`.

    Args:
        context: rclpy context (tests use one per node); None = the global one.
        parameter_overrides: Start-up parameter values, as with ``--ros-args -p``.
        **kwargs: Passed on to :class:`rclpy.node.Node`.

    Raises:
        CVAError: The start-up parameters give an invalid configuration or weights that cannot
            be loaded.
    """

    def __init__(
        self,
        *,
        context: Context | None = None,
        parameter_overrides: list[Parameter] | None = None,
        **kwargs: Any,
    ) -> None:
        super().__init__(
            NODE_NAME, context=context, parameter_overrides=parameter_overrides, **kwargs
        )
        try:
            self._init_core()
            warn_unknown_parameters(self)
            self._configure()
            self._activate()
        except BaseException:
            # Destroyed here, not left to the garbage collector: collecting it would unregister
            # the /rosout publisher of its name, by then perhaps a later node's.
            if hasattr(self, '_mailbox'):
                self.destroy_node()
            else:  # refused while declaring its parameters
                Node.destroy_node(self)
            raise


def run(argv: Sequence[str] | None = None) -> int:
    """Run the node until Ctrl-C or SIGTERM: the body of :func:`cva_confidence_ros.node.main`,
    with its arguments and exit codes (imported by it once a Ctrl-C can be caught)."""
    return run_node(ConfidenceNode, NODE_NAME, argv)

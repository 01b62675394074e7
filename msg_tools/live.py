"""Live mode of ``cva-bag-replay``: play the bag to the running node over DDS and record it.

The bag's input messages are published as they are stored (raw CDR, rclpy publishers,
reliable QoS) at the recorded pace times ``rate_scale``; the node's outputs are received raw,
written unchanged into the output bag and scored like the offline mode's. What this measures
is the node as it really behaves: frames it drops under load have no output and count as
``dropped``, and each answered frame carries its latency (last input published → last
scored output received).

The node is started as a subprocess (``cva-node`` next to the running Python, with the
replay's pipeline and sync parameters, reliable QoS, and every topic remapped onto the
replay's names), or, with ``start_node=False``, an already running one is used. With
``options.compressed`` the replay subscribes to the node's ``depth/compressedDepth`` and
``confidence_overlay/compressed`` instead of ``depth`` and ``confidence_overlay`` (the node
then encodes them, with the replay's settings as its parameters, and leaves the raw ones be).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
import os
from pathlib import Path
import queue
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from typing import Any, cast

from cva_confidence_ros.errors import BagError, ConfigError, InputError, reason
from cva_confidence_ros.mask import load_mask
from cva_confidence_ros.pipeline import output_region
from msg_tools.bagio import InputBag
from msg_tools.convert import camera_geometry, disparity_from_msg, jazzy_typestore, stamp_to_ns
from msg_tools.progress import GracefulInterrupt, Progress
from msg_tools.replay import (
    COMPRESSED_OUTPUTS,
    GT_WAIT_FRAMES,
    STOPPING,
    CompressionConfig,
    FrameResult,
    Logger,
    ReplayOptions,
    ReplayOutcome,
    ReplaySession,
    TopicPlan,
    check_output_bag_folder,
    log_stderr,
    make_synchronizer,
    output_left_image,
    plan_topics,
    preload,
)
from msg_tools.scoring import ReportFolderLock, clear_report

__all__ = ['NodeProcess', 'node_arguments', 'recorded_outputs', 'run_live']

# The node's topic names (relative, as it declares them) → the replay's output names.
_NODE_INPUTS = {
    'left': 'left/image_rect',
    'right': 'right/image_rect',
    'left_info': 'left/camera_info',
    'right_info': 'right/camera_info',
}
_NODE_OUTPUTS = {
    'disparity': 'disparity',
    'confidence': 'confidence',
    'disparity_filtered': 'disparity_filtered',
    'points': 'points2',
    'depth': 'depth',
    'overlay': 'confidence_overlay',
    'scan': 'scan',
    'camera_info': 'camera_info',
    'depth_compressed': 'depth/compressedDepth',
    'overlay_compressed': 'confidence_overlay/compressed',
}
_OUTPUT_TYPES = {
    'disparity': 'stereo_msgs/msg/DisparityImage',
    'confidence': 'sensor_msgs/msg/Image',
    'disparity_filtered': 'stereo_msgs/msg/DisparityImage',
    'points': 'sensor_msgs/msg/PointCloud2',
    'depth': 'sensor_msgs/msg/Image',
    'overlay': 'sensor_msgs/msg/Image',
    'scan': 'sensor_msgs/msg/LaserScan',
    'camera_info': 'sensor_msgs/msg/CameraInfo',
    'depth_compressed': 'sensor_msgs/msg/CompressedImage',
    'overlay_compressed': 'sensor_msgs/msg/CompressedImage',
}
# Outputs that an option turns off.
_OPTIONAL = {
    'points': 'publish_points',
    'depth': 'publish_depth',
    'overlay': 'publish_overlay',
    'scan': 'scan',
    'depth_compressed': 'publish_depth',
    'overlay_compressed': 'publish_overlay',
}
# What a frame needs before it can be scored; points2, depth, the overlay, the scan and
# camera_info are only recorded.
_SCORED = ('disparity', 'confidence', 'disparity_filtered')
# Frames no longer pending that are kept (their bag times and outputs received), so that their
# outputs that come after the scored ones (points2, depth, ...) are written at the input's bag
# time too.
_DONE_TIMES = 100


# Strings that rcl takes as they are in a -p override (names like census_bm, reliable), less
# the words it reads as a bool or a double.
_PLAIN = re.compile(r'[A-Za-z_][A-Za-z0-9_]*')
_NOT_STRINGS = {'y', 'n', 'yes', 'no', 'true', 'false', 'on', 'off', 'nan', 'inf', 'infinity'}


def _ros_value(value: object) -> str:
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, float):
        return repr(float(value))
    if isinstance(value, str) and not (
        _PLAIN.fullmatch(value) and value.lower() not in _NOT_STRINGS
    ):
        # rcl reads a -p value as YAML: quoted, a path stays the string it is (unquoted,
        # '/data/run #2/mask.png' read '/data/run', '123' an integer, 'a: b' did not parse).
        return "'" + value.replace("'", "''") + "'"
    return str(value)


def recorded_outputs(options: ReplayOptions) -> list[str]:
    """The outputs the replay subscribes to and records: those its options ask for, with
    ``depth`` and ``overlay`` as their compressed transports under ``options.compressed``."""
    replaced = (
        {raw for raw, _ in COMPRESSED_OUTPUTS.values()} if options.compressed is not None
        else set(COMPRESSED_OUTPUTS)
    )
    return [
        name for name in _OUTPUT_TYPES
        if name not in replaced and (name not in _OPTIONAL or getattr(options, _OPTIONAL[name]))
    ]


def node_arguments(
    options: ReplayOptions, node_name: str, image_transport: str = 'raw'
) -> list[str]:
    """``--ros-args`` for a ``cva-node`` that computes what the replay asks for.

    Parameters: every ``PipelineConfig`` field, the sync, point-cloud and compression
    options, and reliable QoS on inputs and outputs (so that DDS itself loses nothing and
    every drop is the node's). Remappings put the node's topics (its compressed transports
    included) onto the replay's resolved names; with
    ``image_transport='compressed'`` the node's ``left/image_rect/compressed`` (and right) go
    onto the bag's image topics.

    Raises:
        ConfigError: An option outside the range the node declares (its start-up would end).
    """
    from cva_confidence_ros.ros.params import NodeConfig, check_declared_ranges, scan_parameters
    from cva_confidence_ros.scan import ScanConfig

    node_config = NodeConfig(
        **asdict(options.compressed or CompressionConfig()),
        publish_scan=options.scan is not None,
        scan_frame_id=options.scan_frame_id,
        **scan_parameters(options.scan or ScanConfig()),
        publish_points=options.publish_points,
        points_organized=options.points_organized,
        points_confidence=options.points_confidence,
        publish_depth=options.publish_depth,
        depth_encoding=options.depth_encoding,
        input_qos='reliable',
        output_qos='reliable',
        approximate_sync=options.approximate_sync,
        approximate_sync_tolerance_seconds=float(options.sync_tolerance_s),
        queue_size=options.queue_size,
        image_transport=image_transport,
    )
    params = {**asdict(options.pipeline), **asdict(node_config)}
    check_declared_ranges(params)
    args = ['--ros-args', '-r', f'__node:={node_name}']
    for name, value in params.items():
        if value == '':
            continue  # an empty override does not parse; the node's default is '' anyway
        args += ['-p', f'{name}:={_ros_value(value)}']
    inputs = options.topics.inputs()
    outputs = options.topics.outputs()
    for key, topic in _NODE_INPUTS.items():
        if image_transport == 'compressed' and not key.endswith('_info'):
            topic = f'{topic}/compressed'
        args += ['-r', f'{topic}:={inputs[key]}']
    for key, topic in _NODE_OUTPUTS.items():
        args += ['-r', f'{topic}:={outputs[key]}']
    return args


def _node_command() -> tuple[list[str], dict[str, str]]:
    """The node's command line and extra environment.

    The ``cva-node`` script of this Python's environment comes first; without one (a source
    checkout that is not installed) the module runs with the package's folder on the path.
    """
    beside = Path(sys.executable).with_name('cva-node')
    if beside.exists():
        return [str(beside)], {}
    found = shutil.which('cva-node')
    if found:
        return [found], {}
    import cva_confidence_ros

    source = str(Path(cva_confidence_ros.__file__).resolve().parents[1])
    path = os.pathsep.join(p for p in (source, os.environ.get('PYTHONPATH', '')) if p)
    return [sys.executable, '-m', 'cva_confidence_ros.node'], {'PYTHONPATH': path}


class NodeProcess:
    """``cva-node`` as a subprocess; its output goes to ``log_path``.

    Args:
        options: The replay options (parameters and topic names).
        log_path: File that receives the node's stdout and stderr.
        image_transport: ``raw`` or ``compressed``, as the bag stores the images.
    """

    #: Exit codes of a node that ended on :meth:`stop`'s SIGINT: 0 once it is up, 130 while
    #: it is still starting, −SIGINT before its Python handles signals at all.
    STOPPED_CODES = (0, 130, -signal.SIGINT)

    def __init__(
        self, options: ReplayOptions, log_path: Path, image_transport: str = 'raw'
    ) -> None:
        self.name = f'cva_confidence_replay_{os.getpid()}'
        command, self.env = _node_command()
        self.command = command + node_arguments(options, self.name, image_transport)
        self.log_path = log_path
        self.process: subprocess.Popen[bytes] | None = None

    def start(self) -> NodeProcess:
        """Start the node (returns at once; it is ready when its topics connect).

        The node runs in a session of its own: a Ctrl-C in the terminal goes to the replay
        only, which then stops the node itself (:meth:`stop`), instead of reaching the node
        too, possibly half-way through its imports.

        Raises:
            ConfigError: The log file cannot be written or the node cannot be started.
        """
        env = dict(os.environ, PYTHONUNBUFFERED='1', **self.env)
        try:
            self.log_path.parent.mkdir(parents=True, exist_ok=True)
            with self.log_path.open('wb') as log:
                self.process = subprocess.Popen(
                    self.command, stdout=log, stderr=subprocess.STDOUT, env=env,
                    stdin=subprocess.DEVNULL, start_new_session=True,
                )
        except OSError as err:
            raise ConfigError(
                f'cannot start cva-node with its log in {self.log_path}: {reason(err)}'
            ) from None
        return self

    @property
    def exit_code(self) -> int | None:
        """None while running."""
        return None if self.process is None else self.process.poll()

    def last_lines(self, count: int = 3) -> str:
        """The end of the node's log, for error messages."""
        try:
            lines = self.log_path.read_text(errors='replace').strip().splitlines()
        except OSError:
            return ''
        return ' | '.join(line.strip() for line in lines[-count:])

    def stop(self, timeout: float = 10.0) -> int | None:
        """Ctrl-C the node, then terminate and kill it if it does not exit.

        Returns:
            None when the node was never started; 0 when it was running and ended on the
            Ctrl-C (with one of :attr:`STOPPED_CODES`); else its exit code: it had failed
            before, failed on the way out, or had to be terminated or killed.
        """
        process = self.process
        if process is None:
            return None
        if process.poll() is not None:
            return process.returncode
        process.send_signal(signal.SIGINT)
        try:
            code = process.wait(timeout)
        except subprocess.TimeoutExpired:
            process.terminate()
            try:
                return process.wait(timeout)
            except subprocess.TimeoutExpired:
                process.kill()
                return process.wait()
        return 0 if code in self.STOPPED_CODES else code


@dataclass(eq=False)
class _PendingFrame:
    """A pair published to the node whose outputs have not all come yet."""

    frame: int
    timestamp_ns: int
    published: float
    stamp_ns: int = 0
    geometry: Any = None
    size: tuple[int, int] = (0, 0)
    items: dict[str, Any] | None = None
    error: str = ''  # why its camera infos give no geometry
    # The names of its outputs received so far, and its scored ones (name → message).
    received: set[str] = field(default_factory=set)
    parts: dict[str, Any] = field(default_factory=dict)


class _Player:
    """The replay's rclpy node: raw publishers of the inputs, raw subscriptions of the outputs.

    Output callbacks only queue ``(name, bytes, receive time)``; the main thread does the rest.
    """

    def __init__(self, plan: TopicPlan, options: ReplayOptions, reliable_outputs: bool) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
        from rclpy.signals import SignalHandlerOptions

        from cva_confidence_ros.ros.common import spin_until_shutdown

        self.context = Context()
        # No rclpy signal handlers: Ctrl-C is the replay's (GracefulInterrupt), and it shuts
        # this context down itself (close), after the frames in hand are written.
        rclpy.init(context=self.context, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node(f'cva_bag_replay_{os.getpid()}', context=self.context)
        self.received: queue.Queue[tuple[str, bytes, float]] = queue.Queue()
        publish_qos = QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=max(options.queue_size, 10),
            reliability=ReliabilityPolicy.RELIABLE,
        )
        # A best-effort reader accepts any writer: the only safe choice for a node we did not
        # configure; a node we started writes reliably, so we read reliably.
        receive_qos = QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=30,
            reliability=(ReliabilityPolicy.RELIABLE if reliable_outputs
                         else ReliabilityPolicy.BEST_EFFORT),
        )
        self.publishers = {
            topic: self.node.create_publisher(_message_class(kind), topic, publish_qos)
            for topic, kind in plan.input_types.items()
        }
        names = recorded_outputs(options)
        outputs = options.topics.outputs()
        self.subscriptions = {
            name: self.node.create_subscription(
                _message_class(_OUTPUT_TYPES[name]), outputs[name],
                # mypy cannot infer a lambda with a default argument against the callback type
                cast('Callable[[Any], None]',
                     lambda raw, name=name: self.received.put((name, raw, time.monotonic()))),
                receive_qos, raw=True,
            )
            for name in names
        }
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(
            target=spin_until_shutdown, args=(self.executor,), name='cva_bag_replay_spin',
            daemon=True,
        )
        self.thread.start()

    def connected(self) -> bool:
        """Every input has a reader and every output a writer."""
        return all(p.get_subscription_count() > 0 for p in self.publishers.values()) and all(
            s.get_publisher_count() > 0 for s in self.subscriptions.values()
        )

    def missing(self) -> list[str]:
        """Topics still without a partner (for error messages)."""
        lonely = [t for t, p in self.publishers.items() if p.get_subscription_count() == 0]
        lonely += [
            s.topic_name for s in self.subscriptions.values() if s.get_publisher_count() == 0
        ]
        return lonely

    def close(self) -> None:
        """Stop spinning and shut the context down."""
        self.executor.shutdown(timeout_sec=2.0)
        self.node.destroy_node()
        if self.context.ok():
            self.context.try_shutdown()
        self.thread.join(timeout=5.0)


def _message_class(msgtype: str) -> Any:
    import importlib

    package, _, name = msgtype.split('/')
    return getattr(importlib.import_module(f'{package}.msg'), name)


def run_live(
    options: ReplayOptions,
    log: Logger = log_stderr,
    interrupts: GracefulInterrupt | None = None,
) -> ReplayOutcome:
    """Play the bag to the node over DDS at the recorded speed × ``rate_scale``; record and
    score what it publishes.

    A Ctrl-C stops the run at its next step (a second one at once); the node we started is
    stopped and the frames done are in the outputs. ``interrupts``: the caller's Ctrl-C
    handling, if it has begun one; else the run's own.

    Returns:
        The :class:`ReplayOutcome` (same report as offline; ``dropped`` counts the pairs the
        node did not answer; after a Ctrl-C, ``in_flight`` those published after the last
        one it answered, which it may still have been working on, and ``dropped`` only the
        others).

    Raises:
        BagError: The bag cannot be opened or lacks an input topic.
        ConfigError: An option outside the range the node declares (checked before anything
            is written), or the node exits or does not connect within ``startup_timeout_s``.
    """
    interrupts = interrupts or GracefulInterrupt(notice=STOPPING)
    with interrupts, InputBag(options.bag) as bag:
        preload()
        plan = plan_topics(bag, options, log)
        interrupts.check()
        if options.start_node:
            # Values the node would refuse at start-up (a sync tolerance of a minute, a queue
            # of 5000) are refused here, before the old report goes.
            node_arguments(options, 'cva_confidence_replay', plan.image_transport)
        check_output_bag_folder(options.out)  # before the old report goes
        # Another run writing this report folder now is refused before its files go.
        with ReportFolderLock(options.report):
            if options.overwrite:
                clear_report(options.report)  # the files of an earlier report, node.log too
            with _large_messages_profile(options.start_node, log):
                return _run_with_node(bag, plan, options, log, interrupts)


@contextmanager
def _large_messages_profile(start_node: bool, log: Logger) -> Iterator[None]:
    """While no Fast DDS profile is set and the replay starts its own node: the large-message
    profile for this process's participant and the node's (both read it at their first).

    Without it an image over Fast DDS's 512 kB shared-memory segment (a 640×480 colour one)
    goes by UDP in fragments, and the node's best-effort input loses it at one lost fragment.
    A node already running (``--no-start-node``) keeps its own settings: they are left alone.
    """
    from cva_confidence_ros.ros.common import large_messages_unset
    from cva_confidence_ros.ros.dds_profile import profile_environment, write_profile

    if not (start_node and large_messages_unset()):
        yield
        return
    with tempfile.TemporaryDirectory(prefix='cva_replay_dds_') as folder:
        variables = profile_environment(write_profile(folder))
        previous = {name: os.environ.get(name) for name in variables}
        os.environ.update(variables)
        log('no Fast DDS profile set: this replay and its node use the large-message one '
            '(config/fastdds_large_messages.xml)')
        try:
            yield
        finally:
            for name, value in previous.items():
                if value is None:
                    os.environ.pop(name, None)
                else:
                    os.environ[name] = value


def _run_with_node(
    bag: InputBag,
    plan: TopicPlan,
    options: ReplayOptions,
    log: Logger,
    interrupts: GracefulInterrupt,
) -> ReplayOutcome:
    """Start the node (unless one runs), connect, play and record; stop the node after."""
    node = None
    if options.start_node:
        node = NodeProcess(
            options, Path(options.report) / 'node.log', plan.image_transport
        ).start()
        log(f'started cva-node (log {node.log_path})')
    player = None
    try:
        player = _Player(plan, options, reliable_outputs=node is not None)
        _wait_for_node(player, node, options, log, interrupts)
        return _play(bag, plan, player, node, options, log, interrupts)
    finally:
        # A second Ctrl-C must not cut the clean-up short (and leave the node running).
        with _signals_ignored():
            if player is not None:
                player.close()
            if node is not None:
                code = node.stop()
                if code not in (0, None):
                    log(f'cva-node exited with code {code}: {node.last_lines()}')


@contextmanager
def _signals_ignored() -> Iterator[None]:
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {sig: signal.signal(sig, signal.SIG_IGN) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _wait_for_node(
    player: _Player,
    node: NodeProcess | None,
    options: ReplayOptions,
    log: Logger,
    interrupts: GracefulInterrupt,
) -> None:
    deadline = time.monotonic() + options.startup_timeout_s
    while not player.connected():
        interrupts.check()
        if node is not None and node.exit_code is not None:
            raise ConfigError(
                f'cva-node exited with code {node.exit_code} before it connected: '
                f'{node.last_lines()}'
            )
        if time.monotonic() > deadline:
            hint = '' if node is not None else ' (start cva-node, or drop --no-start-node)'
            raise ConfigError(
                f'no node connected to {", ".join(player.missing())} within '
                f'{options.startup_timeout_s:.0f} s{hint}'
            )
        time.sleep(0.05)
    # This is our side of the matching; a message sent before the node's side has matched
    # our writers too would be lost (volatile QoS), so give discovery a moment to settle.
    time.sleep(1.0)
    interrupts.check()
    log('node connected; playing the bag')


def _play(
    bag: InputBag,
    plan: TopicPlan,
    player: _Player,
    node: NodeProcess | None,
    options: ReplayOptions,
    log: Logger,
    interrupts: GracefulInterrupt,
) -> ReplayOutcome:
    from rosbags.serde import SerdeError

    store = jazzy_typestore()
    sync = make_synchronizer(options)
    key_of = plan.key_of
    progress = Progress(plan.pairs_expected, prefix='[cva-bag-replay] live: ')
    # Outputs lag the inputs, so ground truth waits until its frame is answered (or a newer
    # one is); the cap only guards against a node that answers nothing at all.
    session = ReplaySession(
        options, plan, log, truth_window=max(GT_WAIT_FRAMES, 4 * options.queue_size),
        interrupts=interrupts,
    )
    recorder = _Recorder(session, store, options, player.received)
    with session, progress:
        position: int | None = None  # bag time of the last message read
        try:
            start_bag: int | None = None
            start_wall = 0.0
            for topic, msgtype, timestamp, raw in bag.messages(plan.topics, *plan.window):
                interrupts.check()
                position = timestamp
                if start_bag is None:
                    start_bag, start_wall = timestamp, time.monotonic()
                due = start_wall + (timestamp - start_bag) / 1e9 / options.rate_scale
                recorder.drain(until=due, progress=progress, node=node)
                try:
                    msg = store.deserialize_cdr(raw, msgtype)
                except SerdeError as err:
                    session.unreadable(topic, timestamp, err)  # no pair: not a skipped one
                    continue
                stamp = stamp_to_ns(msg.header.stamp)
                if topic == plan.ground_truth:
                    session.add_ground_truth(stamp, msg)
                    continue
                recorder.published(stamp)
                player.publishers[topic].publish(raw)
                for matched in sync.add(key_of[topic], stamp, (msg, timestamp)):
                    # Its outputs go at the left image's bag time, as offline.
                    logged = int(matched.items['left'][1])
                    items = {key: value[0] for key, value in matched.items.items()}
                    recorder.expect(
                        replace(matched, items=items), session.counts['pairs'], logged
                    )
                    session.counts['pairs'] += 1
                session.report_drops(sync)
            sync.drain()
            session.report_drops(sync)
            recorder.finish(node, progress)
            if plan.window[1] is not None:
                # As offline: the ground truth of the last frames may lie past the part played.
                session.read_ahead_ground_truth(bag, plan.window[1], store)
        finally:
            try:
                if interrupts.requested:
                    # The outputs already received (frames the node answered) are recorded
                    # too; a second Ctrl-C does not cut this short.
                    with interrupts.critical():
                        recorder.take_received(progress)
            finally:
                unanswered = recorder.unanswered()
                if interrupts.requested:
                    # Frames newer than the last one answered may still have been on their
                    # way (the node answers in order, so the older ones were dropped): a
                    # Ctrl-C does not make them dropped frames.
                    in_flight = recorder.waited_for()
                    session.counts['in_flight'] = in_flight
                    unanswered -= in_flight
                session.counts['dropped'] = unanswered
                session.stop_pairing(sync, bag, position, store)  # as offline
    return session.outcome()


def _check_running(node: NodeProcess | None) -> None:
    """Raise :class:`BagError` if the node the replay started has exited."""
    if node is not None and node.exit_code is not None:
        raise BagError(f'cva-node exited with code {node.exit_code}: {node.last_lines()}')


class _Recorder:
    """Receives the node's outputs: writes them to the bag, pairs them per frame, scores."""

    def __init__(
        self,
        session: ReplaySession,
        store: Any,
        options: ReplayOptions,
        received: queue.Queue[tuple[str, bytes, float]],
    ) -> None:
        self.session = session
        self.received = received
        self.store = store
        self.options = options
        self.topics = options.topics.outputs()
        # Stamp → its frames still waited for, in publish order: a stamp sent again before
        # the node answered it (a bag loop shorter than the node's latency, a stamp the bag
        # repeats) is one frame each, and the node answers them in that order.
        self.frames: dict[int, deque[_PendingFrame]] = {}
        # The frames answered or given up (the newest few, without their inputs), oldest first.
        self.done: deque[_PendingFrame] = deque(maxlen=_DONE_TIMES)
        self.publish_times: dict[int, float] = {}
        self.last_output = time.monotonic()
        self.answered = 0
        self.unreadable_topics: set[str] = set()
        # The frames waited for that still hold their input messages (for the plots' left
        # image), newest last: only the newest few do. A node answers none that far behind
        # (it holds one pair besides the one it works on), and one that answers nothing must
        # not have the replay hold every image of the bag.
        self.holding: deque[_PendingFrame] = deque()
        self.hold = max(GT_WAIT_FRAMES, 4 * options.queue_size)
        # The node's ignore mask, for the share of the judged pixels it keeps.
        path = options.pipeline.mask_path
        self.mask = load_mask(path, '--mask') if path else None

    def published(self, stamp_ns: int) -> None:
        """Note when the latest input message of a stamp went out."""
        self.publish_times[stamp_ns] = time.monotonic()

    def expect(self, matched: Any, frame: int, timestamp_ns: int) -> None:
        """Register a pair the node should answer (``timestamp_ns``: the bag time of its
        outputs)."""
        stamps = {matched.stamp_ns, *getattr(matched, 'stamps_ns', {}).values()}
        # The latency runs from the last of its inputs (of other stamps in approximate mode).
        times = [self.publish_times.pop(s) for s in stamps if s in self.publish_times]
        # Older stamps can no longer pair (the synchroniser let them go): forget them.
        for stale in [s for s in self.publish_times if s < min(stamps)]:
            del self.publish_times[stale]
        pending = _PendingFrame(
            frame=frame, timestamp_ns=timestamp_ns,
            published=max(times, default=time.monotonic()),
            stamp_ns=matched.stamp_ns, items=dict(matched.items),
        )
        try:
            left = matched.items['left']
            # (A compressed image has no size field: the node decodes it.)
            size = (int(left.width), int(left.height)) if hasattr(left, 'width') else None
            geometry, width, height = camera_geometry(
                matched.items['left_info'], matched.items['right_info'], size
            )
            pending.geometry, pending.size = geometry, (height, width)
        except InputError as err:
            # The node drops this pair too (it counts as not answered); a node that answers
            # it all the same gets the frame skipped with this reason.
            pending.error = str(err)
        self.frames.setdefault(matched.stamp_ns, deque()).append(pending)
        self.holding.append(pending)
        while len(self.holding) > self.hold:
            self.holding.popleft().items = None

    def unanswered(self) -> int:
        """Pairs published whose outputs never (all) came."""
        return self.session.counts['pairs'] - self.answered

    def waited_for(self) -> int:
        """Pairs still waited for: published after the last one answered, not given up."""
        return sum(len(frames) for frames in self.frames.values())

    def drain(self, until: float, progress: Progress, node: NodeProcess | None = None) -> None:
        """Handle outputs until the wall-clock time ``until`` (monotonic seconds), and those
        received already when that time has passed (a replay behind its schedule must not
        leave them queued: they hold memory, and the ground truth for them would not wait).

        Raises:
            BagError: ``node`` (the one the replay started) has exited (checked while waiting
                too: a pause in the bag does not keep the replay waiting for a dead node).
        """
        self._check_node(node, progress)
        while True:
            self.session.interrupts.check()
            left = until - time.monotonic()
            try:
                if left > 0:
                    item = self.received.get(timeout=min(left, 0.05))
                else:
                    item = self.received.get_nowait()
            except queue.Empty:
                if left <= 0:
                    return
                self._check_node(node, progress)
                continue
            self._handle(*item, progress=progress)

    def _check_node(self, node: NodeProcess | None, progress: Progress) -> None:
        """Raise :class:`BagError` if ``node`` has exited, once the outputs it sent before are
        handled (the frames it answered are processed, not dropped)."""
        if node is not None and node.exit_code is not None:
            self.take_received(progress)
            _check_running(node)

    def finish(self, node: NodeProcess | None, progress: Progress) -> None:
        """After the last input: wait for the outstanding outputs (or the drain timeout)."""
        self.last_output = time.monotonic()
        while self.frames and time.monotonic() - self.last_output < self.options.drain_timeout_s:
            self.session.interrupts.check()
            self._check_node(node, progress)
            try:
                item = self.received.get(timeout=0.1)
            except queue.Empty:
                continue
            self._handle(*item, progress=progress)
        # Late points2, depth, overlay, scan or camera_info of the last frame may still be queued:
        # record them too.
        self.take_received(progress)

    def take_received(self, progress: Progress) -> None:
        """Handle the outputs received so far, without waiting for more."""
        while True:
            try:
                item = self.received.get_nowait()
            except queue.Empty:
                return
            self._handle(*item, progress=progress)

    def _handle(self, name: str, raw: bytes, received: float, progress: Progress) -> None:
        from rosbags.serde import SerdeError

        self.last_output = received
        try:
            msg = self.store.deserialize_cdr(raw, _OUTPUT_TYPES[name])
        except SerdeError as err:
            # A message, not a stereo pair (``skipped`` counts pairs): counted unreadable, as
            # an input's; the frame it is of goes without it.
            topic = self.topics[name]
            counts = self.session.counts
            counts['unreadable'] = counts.get('unreadable', 0) + 1
            if topic not in self.unreadable_topics:
                self.unreadable_topics.add(topic)
                self.session.log(
                    f'skipped an output on {topic} (more on it are only counted): {err}'
                )
            return
        stamp = stamp_to_ns(msg.header.stamp)
        owner = self._owner(stamp, name)
        # At the input's bag time, as offline; the header stamp only for an unknown frame.
        known = owner or self._newest(stamp)
        timestamp = known.timestamp_ns if known is not None else stamp
        self.session.write([(self.topics[name], _OUTPUT_TYPES[name], raw)], timestamp)
        if owner is None:
            return
        owner.received.add(name)
        pending = self.frames.get(stamp, ())
        if owner not in pending or name not in _SCORED:
            return
        owner.parts[name] = msg
        if any(key not in owner.parts for key in _SCORED):
            return
        self._done(owner)
        self.answered += 1
        progress.update()
        self._score(owner, stamp, owner.parts, received)
        # Outputs come in the order the pairs went out: earlier pairs still incomplete were
        # dropped (by publish order, not stamp: after a jump back the stamps start over).
        for older in [p for q in self.frames.values() for p in q if p.frame < owner.frame]:
            self._done(older)
        self.session.drop_ground_truth_before(stamp)

    def _owner(self, stamp: int, name: str) -> _PendingFrame | None:
        """The frame an output ``name`` of ``stamp`` is of: the oldest frame of that stamp
        that has none yet, done ones first (the later outputs of a frame the node answered,
        or of one given up that got some), then those still waited for; None if no frame."""
        for frame in self.done:
            if frame.stamp_ns == stamp and frame.received and name not in frame.received:
                return frame
        for frame in self.frames.get(stamp, ()):
            if name not in frame.received:
                return frame
        return None

    def _newest(self, stamp: int) -> _PendingFrame | None:
        """The latest frame of ``stamp`` published (waited for or done), if any is known."""
        pending = self.frames.get(stamp)
        if pending:
            return pending[-1]
        return next((frame for frame in reversed(self.done) if frame.stamp_ns == stamp), None)

    def _done(self, frame: _PendingFrame) -> None:
        """Stop waiting for ``frame``; keep its bag time and outputs for its later outputs."""
        pending = self.frames[frame.stamp_ns]
        pending.remove(frame)
        if not pending:
            del self.frames[frame.stamp_ns]
        if frame.items is not None:
            self.holding.remove(frame)
        self.done.append(replace(frame, items=None, geometry=None, parts={}))

    def _score(
        self, pending: _PendingFrame, stamp: int, parts: dict[str, Any], received: float
    ) -> None:
        import numpy as np

        from cva_confidence_ros.ros.convert import float_image_to_array

        if pending.geometry is None:
            self.session.skip(f'outputs of frame {pending.frame}', pending.error)
            return
        disparity_msg = parts['disparity']
        height, width = int(disparity_msg.image.height), int(disparity_msg.image.width)
        geometry = pending.geometry
        if (height, width) != pending.size:
            # As the node: the pipeline crops the bottom/right rest and shrinks by exactly
            # 1/downsample, whatever the rounding of an odd size.
            geometry = geometry.scaled(1.0 / self.options.pipeline.downsample)
        try:
            disparity = disparity_from_msg(disparity_msg, geometry.disparity_offset)
            filtered = disparity_from_msg(
                parts['disparity_filtered'], geometry.disparity_offset
            )
            confidence = float_image_to_array(parts['confidence'])
            # An ignore mask of another resolution than the outputs: this frame is skipped.
            region = output_region(self.options.pipeline, confidence.shape, self.mask, '--mask')
        except InputError as err:
            self.session.skip(f'outputs of frame {pending.frame}', err)
            return
        items = pending.items
        self.session.add_result(
            FrameResult(
                frame=pending.frame,
                stamp_ns=stamp,
                disparity=disparity,
                confidence=confidence,
                kept=np.isfinite(filtered),
                offset=pending.geometry.disparity_offset,
                latency_ms=(received - pending.published) * 1e3,
                image=None if items is None else lambda: output_left_image(
                    items, confidence.shape, self.options.pipeline.downsample
                ),
                region=region,
                geometry=geometry,
                input_shape=pending.size,
            )
        )

"""Shared helpers of the node tests: synthetic stereo messages and a DDS test client."""

from __future__ import annotations

from collections.abc import Callable, Iterator
import contextlib
import os
from pathlib import Path
import threading
import time
from typing import Any

import numpy as np
from rcl_interfaces.msg import SetParametersResult
from rcl_interfaces.srv import SetParameters
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_msgs.msg import Header
from stereo_msgs.msg import DisparityImage

from cva_confidence_ros.node_benchmark import NodeProcess as BenchNodeProcess
from cva_confidence_ros.ros.common import spin_until_shutdown
from cva_confidence_ros.ros.convert import ns_to_stamp

FX = 100.0
BASELINE = 0.1
TRUE_DISPARITY = 5
FRAME = 'left_optical'

#: A node that starts in a second: Census block matching at D = 16 and the MLM measure.
SMALL_MLM = (
    Parameter('matcher', value='census_bm'),
    Parameter('max_disparity', value=16),
    Parameter('confidence_method', value='mlm'),
)


def domain_id(offset: int) -> int:
    """A ROS domain (101–220) for one test module (offset 0–3): from the pid, so that parallel
    runs do not cross-talk; ``test_colcon_layout`` uses offset 3 with the same formula."""
    return 101 + (os.getpid() % 30) * 4 + offset


def wait_until(predicate: Callable[[], object], timeout: float = 20.0, poll: float = 0.02) -> bool:
    """Poll ``predicate`` (its own threads spinning the nodes) until true or ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            return False
        time.sleep(poll)
    return True


def spare_domain_id() -> int:
    """A ROS domain (221–232) apart from :func:`domain_id`'s and the msg_tools tests' (1–90),
    for a module whose tests each bring up and shut down a context of their own."""
    return 221 + os.getpid() % 12


def first_stamp() -> int:
    """A per-process start stamp (ns): should two runs meet in one domain, their frames differ."""
    return (1 + os.getpid() % 1000) * 10**15


def textured_pair(
    height: int = 64, width: int = 96, disparity: int = TRUE_DISPARITY, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Random blob texture seen with a constant disparity: left[y, x] = right[y, x − d].

    Returns:
        (H, W) uint8 left and right images.
    """
    rng = np.random.default_rng(seed)
    coarse = rng.integers(0, 256, size=(height // 2 + 1, (width + disparity) // 2 + 1))
    texture = np.kron(coarse, np.ones((2, 2)))[:height, : width + disparity]
    texture = (0.5 * texture + 0.5 * rng.integers(0, 256, size=texture.shape)).astype(np.uint8)
    return texture[:, :width].copy(), texture[:, disparity : disparity + width].copy()


def image_msg(array: np.ndarray, stamp_ns: int, encoding: str | None = None) -> Image:
    """(H, W) uint8/uint16 or (H, W, 3) uint8 → Image (mono8/mono16/rgb8 unless told)."""
    if encoding is None:
        encoding = {1: 'mono8', 2: 'mono16'}[array.itemsize] if array.ndim == 2 else 'rgb8'
    height, width = array.shape[:2]
    data = np.ascontiguousarray(array)
    if data.dtype == np.uint16:
        data = data.astype('<u2')
    return Image(
        header=Header(stamp=ns_to_stamp(stamp_ns), frame_id=FRAME),
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=0,
        step=data.nbytes // height,
        data=data.tobytes(),
    )


def info_msgs(
    stamp_ns: int, height: int = 64, width: int = 96, fx: float = FX, baseline: float = BASELINE
) -> tuple[CameraInfo, CameraInfo]:
    """Rectified left and right camera infos (cx = W/2, cy = H/2, P_right[0, 3] = −fx·B)."""
    cx, cy = width / 2.0, height / 2.0
    infos = []
    for tx, frame in ((0.0, FRAME), (-fx * baseline, 'right_optical')):
        info = CameraInfo(
            header=Header(stamp=ns_to_stamp(stamp_ns), frame_id=frame),
            height=height,
            width=width,
            distortion_model='plumb_bob',
        )
        info.k = [fx, 0.0, cx, 0.0, fx, cy, 0.0, 0.0, 1.0]
        info.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
        info.p = [fx, 0.0, cx, tx, 0.0, fx, cy, 0.0, 0.0, 0.0, 1.0, 0.0]
        infos.append(info)
    return infos[0], infos[1]


def set_parameters_by_service(
    client: Node, node_name: str = '/cva_confidence', **values: object
) -> list[SetParametersResult]:
    """Set parameters of the node ``node_name`` over its ``set_parameters`` service, as
    ``ros2 param set`` does, from ``client`` (spun by someone else); its answers in order."""
    service = client.create_client(SetParameters, f'{node_name}/set_parameters')
    try:
        assert service.wait_for_service(timeout_sec=20.0), 'no parameter service'
        future = service.call_async(SetParameters.Request(
            parameters=[Parameter(k, value=v).to_parameter_msg() for k, v in values.items()]
        ))
        assert wait_until(future.done, 20.0), 'no answer from the parameter service'
        return list(future.result().results)
    finally:
        client.destroy_client(service)


class StereoClient:
    """A test-side node: publishes stereo inputs and collects the node's outputs over DDS.

    Args:
        context: The rclpy context (its domain decides who it talks to).
        namespace: Namespace of the stereo topics.
    """

    def __init__(self, context: Context, namespace: str = '') -> None:
        self.node = Node('stereo_test_client', namespace=namespace, context=context)
        qos = QoSProfile(depth=10)
        self.pubs = {
            'left': self.node.create_publisher(Image, 'left/image_rect', qos),
            'right': self.node.create_publisher(Image, 'right/image_rect', qos),
            'left_info': self.node.create_publisher(CameraInfo, 'left/camera_info', qos),
            'right_info': self.node.create_publisher(CameraInfo, 'right/camera_info', qos),
        }
        self.received: dict[str, list[Any]] = {}
        self._cond = threading.Condition()
        for topic, msg_type in (
            ('disparity', DisparityImage),
            ('disparity_filtered', DisparityImage),
            ('confidence', Image),
            ('points2', PointCloud2),
        ):
            self.received[topic] = []
            self.node.create_subscription(
                msg_type, topic, lambda msg, topic=topic: self._store(topic, msg), qos
            )

    def subscribe(self, topic: str, msg_type: type, qos: QoSProfile | None = None) -> None:
        """Also collect ``topic`` into :attr:`received`."""
        self.received[topic] = []
        self.node.create_subscription(
            msg_type,
            topic,
            lambda msg: self._store(topic, msg),
            qos or QoSProfile(depth=10),
        )

    def _store(self, topic: str, msg: Any) -> None:
        with self._cond:
            self.received[topic].append(msg)
            self._cond.notify_all()

    def publish_frame(
        self,
        left: np.ndarray,
        right: np.ndarray,
        stamp_ns: int,
        infos: tuple[CameraInfo, CameraInfo] | None = None,
    ) -> None:
        """Publish one stereo pair and its camera infos, all stamped ``stamp_ns``."""
        height, width = left.shape[:2]
        left_info, right_info = infos or info_msgs(stamp_ns, height, width)
        self.pubs['left_info'].publish(left_info)
        self.pubs['right_info'].publish(right_info)
        self.pubs['left'].publish(image_msg(left, stamp_ns))
        self.pubs['right'].publish(image_msg(right, stamp_ns))

    def wait_for(
        self, predicate: Callable[[], bool], timeout: float = 20.0, poll: float = 0.05
    ) -> bool:
        """Wait until ``predicate()`` holds (checked on every new message and every ``poll`` s)."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while not predicate():
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._cond.wait(min(poll, remaining))
        return True

    def by_stamp(self, topic: str, stamp_ns: int) -> Any | None:
        """The received message of ``topic`` stamped ``stamp_ns``, or None."""
        with self._cond:
            for msg in self.received[topic]:
                stamp = msg.header.stamp
                if stamp.sec * 1_000_000_000 + stamp.nanosec == stamp_ns:
                    return msg
        return None

    def wait_connected(self, timeout: float = 20.0) -> bool:
        """Wait until the node under test subscribes to all inputs and publishes the outputs."""
        topics = ('disparity', 'confidence', 'points2', 'disparity_filtered')
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            inputs = all(pub.get_subscription_count() > 0 for pub in self.pubs.values())
            outputs = all(self.node.count_publishers(self._resolve(t)) > 0 for t in topics)
            if inputs and outputs:
                return True
            time.sleep(0.05)
        return False

    def _resolve(self, topic: str) -> str:
        return self.node.resolve_topic_name(topic)

    def send_until_output(
        self,
        left: np.ndarray,
        right: np.ndarray,
        stamp_ns: int,
        topics: tuple[str, ...] = ('disparity', 'confidence', 'points2', 'disparity_filtered'),
        timeout: float = 30.0,
        resend: float = 2.0,
    ) -> dict[str, Any]:
        """Publish the frame until every topic has answered one of the published stamps.

        Discovery of the node's subscribers may lag behind ours, so the frame is sent again
        (with a stamp 1 ms later) every ``resend`` seconds without an answer.

        Returns:
            topic → the output message, all for the same published stamp.
        """
        deadline = time.monotonic() + timeout
        sent: list[int] = []

        def answered() -> int | None:
            for stamp in sent:
                if all(self.by_stamp(t, stamp) is not None for t in topics):
                    return stamp
            return None

        while time.monotonic() < deadline:
            sent.append(stamp_ns + len(sent) * 1_000_000)
            self.publish_frame(left, right, sent[-1])
            wait = min(resend, max(deadline - time.monotonic(), 0.0))
            if self.wait_for(lambda: answered() is not None, timeout=wait):
                stamp = answered()
                assert stamp is not None
                return {t: self.by_stamp(t, stamp) for t in topics}
        raise TimeoutError(f'no output on {topics} within {timeout} s')


class Spinner:
    """Spin an executor for some nodes in a background thread until :meth:`stop`."""

    def __init__(self, context: Context, *nodes: Node) -> None:
        self.executor = SingleThreadedExecutor(context=context)
        for node in nodes:
            self.executor.add_node(node)
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=spin_until_shutdown, args=(self.executor, self._stop), daemon=True
        )
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        self.executor.shutdown()


def rss_mb() -> float:
    """Resident memory of this process in MB (Linux)."""
    with open('/proc/self/status', encoding='ascii') as status:
        for line in status:
            if line.startswith('VmRSS:'):
                return int(line.split()[1]) / 1024.0
    return float('nan')


@contextlib.contextmanager
def localhost_context(domain: int) -> Iterator[Context]:
    """An initialised rclpy context on ``domain`` with discovery kept on this host."""
    previous = os.environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE')
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    context = Context()
    rclpy.init(context=context, domain_id=domain)
    try:
        yield context
    finally:
        rclpy.shutdown(context=context)
        if previous is None:
            os.environ.pop('ROS_AUTOMATIC_DISCOVERY_RANGE', None)
        else:
            os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = previous


@contextlib.contextmanager
def running_nodes(domain: int, make: Callable[[Context], Any]) -> Iterator[Any]:
    """A module's running nodes: ``make(context)`` in a fresh localhost context on ``domain``.

    ``make`` returns the test's state object with ``spinner`` (a :class:`Spinner`), ``node``
    (the node under test) and ``client.node`` (the test-side node); all three are stopped and
    destroyed afterwards.
    """
    with localhost_context(domain) as context:
        state = make(context)
        try:
            yield state
        finally:
            state.spinner.stop()
            state.node.destroy_node()
            state.client.node.destroy_node()


@contextlib.contextmanager
def node_and_client(make_node: Callable[[Context], Any]) -> Iterator[tuple[Any, StereoClient]]:
    """``make_node(context)`` and a :class:`StereoClient`, spun together in a fresh localhost
    context on a spare domain; both stopped and destroyed afterwards."""
    with localhost_context(spare_domain_id()) as context:
        node = make_node(context)
        client = StereoClient(context)
        spinner = Spinner(context, node, client.node)
        try:
            yield node, client
        finally:
            spinner.stop()
            client.node.destroy_node()
            node.destroy_node()


class NodeProcess(BenchNodeProcess):
    """A node executable in a subprocess, on ``domain`` (localhost discovery), with its output
    collected line by line; :attr:`ready` is set once it logs its ``ready:`` line."""

    def __init__(self, executable: Path, domain: int, *ros_args: str) -> None:
        env = dict(
            os.environ,
            ROS_DOMAIN_ID=str(domain),
            ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
            PYTHONUNBUFFERED='1',
            OMP_NUM_THREADS='1',
        )
        super().__init__([str(executable), '--ros-args', *ros_args], env)


def feed_frame(node: Any, left: np.ndarray, right: np.ndarray, stamp: int) -> None:
    """Hand one stereo frame (images and camera infos of ``stamp``) to the node's subscription
    callback, as the executor would, without DDS."""
    left_info, right_info = info_msgs(stamp, *left.shape[:2])
    for key, msg in (('left_info', left_info), ('right_info', right_info),
                     ('left', image_msg(left, stamp)), ('right', image_msg(right, stamp))):
        node._on_message(key, msg)


def held_pipeline(node: Any) -> tuple[threading.Event, threading.Event]:
    """Make ``node``'s pipeline hold each frame until released: ``(started, release)``, set
    when a frame reaches the pipeline and to let it (and every later one) go on."""
    started, release = threading.Event(), threading.Event()
    process = node._pipeline.process

    def held(left: np.ndarray, right: np.ndarray) -> Any:
        started.set()
        release.wait(20.0)
        return process(left, right)

    node._pipeline.process = held
    return started, release


def rosout_reaches(context: Context, node: Node, timeout: float) -> bool:
    """Whether a line ``node`` logs arrives on ``/rosout`` within ``timeout`` s (after a
    garbage collection: a refused node of the same name, collected late, unregistered the
    ``/rosout`` publisher of its name)."""
    import gc

    from rcl_interfaces.msg import Log

    client = StereoClient(context)
    client.subscribe('/rosout', Log, QoSProfile(depth=100))
    spinner = Spinner(context, node, client.node)
    try:
        gc.collect()
        marker = f'rosout marker {time.monotonic()}'

        def marked() -> bool:
            node.get_logger().warning(marker)
            return any(msg.msg == marker for msg in list(client.received['/rosout']))

        return client.wait_for(marked, timeout=timeout, poll=0.1)
    finally:
        spinner.stop()
        client.node.destroy_node()


class LogRecorder:
    """Stands in for a node's logger: keeps the lines logged as (severity, line)."""

    def __init__(self) -> None:
        self.lines: list[tuple[str, str]] = []

    def info(self, message: str, **_: object) -> None:
        self.lines.append(('info', message))

    def warning(self, message: str, **_: object) -> None:
        self.lines.append(('warning', message))

    def error(self, message: str, **_: object) -> None:
        self.lines.append(('error', message))

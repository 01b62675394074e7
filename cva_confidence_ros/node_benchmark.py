"""End-to-end latency and throughput of the ROS 2 node (``cva-benchmark --suite node``).

For every matcher × confidence method, the real ``cva-node`` is started as a subprocess with
those parameters (reliable QoS on its inputs and outputs, a ROS domain of its own, discovery
limited to this host), plus any ``--param NAME=VALUE`` (as ``-p NAME:=VALUE``, e.g.
``--param cva_stride=4``; the row's config name lists them). This process then talks to it
over DDS like any client would:

1. it waits for the node's ``ready`` line and for both sides of every topic to be matched;
2. one warm-up frame: the Motorcycle pair (scikit-image, Middlebury 2014) resized and
   centre-cropped to the input size, published as ``rgb8`` images with camera infos, all four
   messages stamped alike;
3. ``--repeat`` timed frames, one at a time: the clock starts before the first of the four
   messages is published and stops when the last of the awaited outputs (``disparity`` and
   ``confidence`` by default) has arrived here, deserialised. ``fps`` is 1000 / median latency,
   the rate of a client that sends the next pair when the last answer came; a frame is
   *online* at ≥ 5 Hz. Between frames the node's ``/diagnostics`` (published every 0.2 s)
   gives its own per-stage times of that frame (``convert``, ``resize``, ``matching``,
   ``confidence``, ``publish``, ``frame``);
4. the node's peak resident memory (``VmHWM`` of ``/proc/<pid>/status``, the whole process:
   interpreter, libraries, weights and frame buffers);
5. optionally (``--rate``) a burst: frames published at a fixed rate without waiting, stamped
   as a camera at that rate would stamp them; the node keeps only the newest pending pair (and
   with ``max_rate_hz`` skips the ones too close in time), so this shows the output rate it
   sustains, how many pairs it drops or skips, and the CPU cores it uses meanwhile (its user +
   system time over the burst's wall time).

DDS: by default both sides use :data:`FASTDDS_LARGE_MESSAGES_XML`, a Fast DDS profile with a
16 MB shared-memory segment. With stock Fast DDS (``--dds-profile inherit``), 640×480 frames
mostly take about 3 s whatever the node computes: the ~1 MB messages overflow the 512 kB
segment and wait for the reliable writer's next heartbeat. Users of the node need the same
profile (``FASTRTPS_DEFAULT_PROFILES_FILE``) or another RMW for the measured rates.

CVA-Net on a CPU needs minutes to an hour for one 640×480 frame at D = 128, so by default its
rows are *extrapolated*, and marked so: in a subprocess, the network's time on a small crop of
the frame's cost volume is measured through what the pipeline's confidence stage runs, and
scaled by the ratio of the network's floating-point operations on the whole frame (counted for
the very tiles ``predict_confidence`` cuts) to those on the crop; the rest of the frame (transport,
conversion, matching, publishing) is the measured node latency of the same matcher with
``pkrn``, whose own confidence stage is taken out. ``--full-cva-net`` (and ``--device cuda``)
run CVA-Net through the node for real. Where no weights for the matcher and D are shipped, a
randomly initialised network is saved to a temporary file: the time does not depend on the
weight values, and the row says so.
"""

from __future__ import annotations

import argparse
from collections import Counter
from collections.abc import Callable, Iterator, Mapping, Sequence
import contextlib
from dataclasses import dataclass
import itertools
import json
import os
from pathlib import Path
import re
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from typing import Any, cast

import numpy as np

from cva_confidence_ros import strict_json
from cva_confidence_ros.benchmark import (
    EXIT_CODES,
    BenchSettings,
    host_summary,
    make_pairs,
    memory_kb,
)
from cva_confidence_ros.benchmark import RECORD_KEYS as MATCHER_RECORD_KEYS
from cva_confidence_ros.errors import ConfigError, CVAError, ModelError
from cva_confidence_ros.outputs import check_output_file
from cva_confidence_ros.ros.dds_profile import (  # noqa: F401 (the profile, for callers)
    FASTDDS_LARGE_MESSAGES_XML,
    profile_environment,
    write_profile,
)

__all__ = [
    'BASE_METHOD',
    'DEFAULT_MATCHERS',
    'DEFAULT_METHODS',
    'ONLINE_HZ',
    'RECORD_KEYS',
    'NodeBenchSettings',
    'NodeProcess',
    'extrapolate_cva_net',
    'format_table',
    'main',
    'measure_network_crop',
    'measure_node',
    'network_flops',
    'parse_params',
    'run_suite',
]

_PROG = 'cva-benchmark --suite node'
#: Keys of every record written by ``--json`` (those of the matcher suite first).
RECORD_KEYS = MATCHER_RECORD_KEYS + ('latency_ms_median', 'fps', 'online', 'extrapolated')
#: A configuration is online from this output rate on (frames per second).
ONLINE_HZ = 5.0
DEFAULT_MATCHERS = ('census_bm', 'census_sgm', 'mccnn_fast')
DEFAULT_METHODS = ('pkrn', 'mlm', 'lrd', 'lrc', 'score', 'cva_net_fast', 'cva_net')
#: The hand-crafted method whose node run is the base of an extrapolated CVA-Net row: it reads
#: only the left-reference volume, as CVA-Net does, so its matching stage is the same.
BASE_METHOD = 'pkrn'
_NETWORK = 'cva_net'
_OUTPUTS = ('disparity', 'confidence', 'disparity_filtered', 'points2')
_DIAGNOSTICS_PERIOD_S = 0.2
_READY = 'ready:'
_RESEND_S = 5.0
_START_TIMEOUT_S = 180.0
_CROP_WORKER_FLAG = '--crop-worker'
_RECORD_PREFIX = 'NODE-BENCH-RECORD '
_STATUS_SUFFIX = 'stereo confidence'
# Rectified-camera model of the benchmark pair; it only sets the numbers in points2.
_BASELINE_M = 0.193
_DEVICES = ('cpu', 'cuda', 'auto')
_LARGE_SHM = 'large-shm'
_INHERIT = 'inherit'
#: A ROS parameter name as ``--param`` takes it.
_PARAM_NAME = re.compile(r'[A-Za-z][A-Za-z0-9_.]*')



@dataclass(frozen=True)
class NodeBenchSettings:
    """What every node configuration is measured on.

    Attributes:
        width: Input image width in pixels (≥ 16).
        height: Input image height in pixels (≥ 8).
        max_disparity: Cost-volume depth D at the processed resolution (≥ 1; ≥ 13 for cva_net).
        repeat: Timed frames per configuration, after one warm-up frame (≥ 1).
        downsample: The node's ``downsample`` parameter (1, 2 or 4).
        device: The node's ``device`` parameter (``cpu``, ``cuda``, ``auto``).
        full_cva_net: Run CVA-Net through the node even on a CPU instead of extrapolating.
        crop: (rows, columns) at the processed resolution of the crop that CVA-Net's speed is
            measured on when extrapolating; None = one tile of the frame as
            ``predict_confidence`` cuts it (so that the whole frame costs a count of such
            tiles, and the operation count only corrects the smaller edge tiles).
        threads: CPU threads of the node and crop processes (OMP/MKL/numba); None = their
            defaults (all cores).
        rate_hz: Publish rate of the optional burst; None = no burst.
        burst_frames: Frames of the burst (≥ 2).
        outputs: Output topics awaited per frame (a subset of ``disparity``, ``confidence``,
            ``disparity_filtered``, ``points2``); the node computes only what has subscribers.
        timeout_s: Longest wait for one frame's answer; a dead node is noticed at once.
        domain_id: ROS domain of the node and the client; None = one derived from the pid.
        dds_profile: ``large-shm`` (:data:`FASTDDS_LARGE_MESSAGES_XML` for the node and the
            client), ``inherit`` (the environment's DDS settings, stock Fast DDS unless set)
            or the path of a Fast DDS XML profiles file.
        params: Further node parameters, (name, value) pairs passed as ``-p name:=value``
            after (and so over) the benchmark's own, e.g. ``(('cva_stride', '4'),)``; see
            :func:`parse_params`.
    """

    width: int = 640
    height: int = 480
    max_disparity: int = 128
    repeat: int = 5
    downsample: int = 1
    device: str = 'cpu'
    full_cva_net: bool = False
    crop: tuple[int, int] | None = None
    threads: int | None = None
    rate_hz: float | None = None
    burst_frames: int = 20
    outputs: tuple[str, ...] = ('disparity', 'confidence')
    timeout_s: float = 3600.0
    domain_id: int | None = None
    dds_profile: str = _LARGE_SHM
    params: tuple[tuple[str, str], ...] = ()

    def __post_init__(self) -> None:
        for pair in self.params:
            if len(pair) != 2 or not _PARAM_NAME.fullmatch(str(pair[0])) or str(pair[1]) == '':
                raise ConfigError(
                    f'params must be (name, value) pairs with a parameter name and a non-empty '
                    f'value; got {pair!r}'
                )
        if self.height < 8 or self.width < 16:
            raise ConfigError(f'images must be at least 16×8; got {self.width}×{self.height}')
        if not 1 <= self.max_disparity <= 1024:
            raise ConfigError(f'max_disparity must be in [1, 1024]; got {self.max_disparity}')
        if self.repeat < 1:
            raise ConfigError(f'repeat must be ≥ 1; got {self.repeat}')
        if self.downsample not in (1, 2, 4):
            raise ConfigError(f'downsample must be 1, 2 or 4; got {self.downsample}')
        if self.device not in _DEVICES:
            raise ConfigError(f'device must be one of {_DEVICES}; got {self.device!r}')
        if self.crop is not None and (len(self.crop) != 2 or min(self.crop) < 1):
            raise ConfigError(f'crop must be two sizes ≥ 1 (rows, columns); got {self.crop}')
        if self.threads is not None and self.threads < 1:
            raise ConfigError(f'threads must be ≥ 1; got {self.threads}')
        if self.rate_hz is not None and not 0 < self.rate_hz <= 1e6:
            # above 1 MHz the burst's stamps (ns) would no longer be distinct
            raise ConfigError(f'rate must be in (0, 1e6] Hz; got {self.rate_hz}')
        if self.burst_frames < 2:
            raise ConfigError(f'burst_frames must be ≥ 2; got {self.burst_frames}')
        if not self.outputs or any(topic not in _OUTPUTS for topic in self.outputs):
            raise ConfigError(f'outputs must be some of {_OUTPUTS}; got {self.outputs}')
        if not self.timeout_s > 0:
            raise ConfigError(f'timeout must be > 0 s; got {self.timeout_s}')
        if self.domain_id is not None and not 0 <= self.domain_id <= 232:
            raise ConfigError(f'domain_id must be in [0, 232]; got {self.domain_id}')
        if self.dds_profile not in (_LARGE_SHM, _INHERIT) and not Path(
            self.dds_profile
        ).is_file():
            raise ConfigError(
                f'dds_profile must be {_LARGE_SHM!r}, {_INHERIT!r} or an existing XML file; '
                f'got {self.dds_profile!r}'
            )

    @property
    def processed_size(self) -> tuple[int, int]:
        """(rows, columns) the node matches at: the input shrunk by ``downsample``."""
        return self.height // self.downsample, self.width // self.downsample

    @property
    def domain(self) -> int:
        """The ROS domain used: given, or 1–100 from the pid (the node tests use 101–220)."""
        return self.domain_id if self.domain_id is not None else 1 + os.getpid() % 100


def parse_params(items: Sequence[str]) -> tuple[tuple[str, str], ...]:
    """``NAME=VALUE`` strings (``--param``) → (name, value) pairs, in order.

    Raises:
        ConfigError: An item without ``=``, or with an empty or malformed name or an empty
            value; the message names the item.
    """
    pairs = []
    for item in items:
        name, sep, value = str(item).partition('=')
        name, value = name.strip(), value.strip()
        if not sep or not _PARAM_NAME.fullmatch(name) or not value:
            raise ConfigError(
                f'--param must be NAME=VALUE with a node parameter name (letters, digits, '
                f'_ and .) and a value, e.g. cva_stride=4; got {item!r}'
            )
        pairs.append((name, value))
    return tuple(pairs)


def benchmark_pair(width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """The Motorcycle pair resized to cover width×height and centre-cropped.

    Returns:
        (left, right), each (height, width, 3) uint8 RGB.
    """
    # make_pairs also builds the synthetic pair (cheap); D only matters for that one.
    pairs = make_pairs(BenchSettings(width=width, height=height, max_disparity=1, repeat=1))
    return pairs['real']


# The node process ---------------------------------------------------------------------------


def _package_env(threads: int | None) -> dict[str, str]:
    env = dict(os.environ)
    # Children must import this very package, also when it runs from a source checkout.
    package_root = str(Path(__file__).resolve().parents[1])
    env['PYTHONPATH'] = os.pathsep.join(
        [package_root] + ([env['PYTHONPATH']] if env.get('PYTHONPATH') else [])
    )
    env['PYTHONUNBUFFERED'] = '1'
    if threads is not None:
        for name in ('OMP_NUM_THREADS', 'MKL_NUM_THREADS', 'NUMBA_NUM_THREADS'):
            env[name] = str(threads)
    return env


def node_command() -> list[str]:
    """The installed ``cva-node`` next to this interpreter, else the same entry point by module."""
    script = Path(sys.executable).parent / 'cva-node'
    if script.is_file() and os.access(script, os.X_OK):
        return [str(script)]
    return [sys.executable, '-m', 'cva_confidence_ros.node']


def node_parameters(
    settings: NodeBenchSettings, matcher: str, method: str, model_path: str = ''
) -> list[str]:
    """``-p name:=value`` arguments of one configuration (after ``--ros-args``)."""
    values: dict[str, Any] = {
        'matcher': matcher,
        'max_disparity': settings.max_disparity,
        'confidence_method': method,
        'device': settings.device,
        'downsample': settings.downsample,
        'input_qos': 'reliable',
        'output_qos': 'reliable',
        'diagnostics_period_seconds': _DIAGNOSTICS_PERIOD_S,
    }
    if model_path:
        values['model_path'] = model_path
    values.update(dict(settings.params))
    args: list[str] = []
    for name, value in values.items():
        args += ['-p', f'{name}:={value}']
    return args


class NodeProcess:
    """A node executable in a subprocess; its output (stdout and stderr) is collected line by
    line, and :attr:`ready` is set once it prints its ``ready:`` line.

    Args:
        command: The command line, e.g. ``[*node_command(), '--ros-args', ...]``.
        env: Its environment.
    """

    def __init__(self, command: Sequence[str], env: Mapping[str, str]) -> None:
        self.process = subprocess.Popen(
            list(command),
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        self.lines: list[str] = []
        self.ready = threading.Event()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            self.lines.append(line)
            if _READY in line:
                self.ready.set()

    def alive(self) -> bool:
        """Whether the process still runs."""
        return self.process.poll() is None

    @property
    def output(self) -> str:
        """Everything the node printed so far."""
        return ''.join(self.lines)

    def tail(self, lines: int = 30) -> str:
        """The last lines the node printed."""
        return ''.join(self.lines[-lines:])

    def fail(self, what: str) -> ConfigError:
        """An error saying ``what`` went wrong, with the node's exit code and last output."""
        code = self.process.poll()
        state = 'still running' if code is None else f'exit code {code}'
        return ConfigError(f'{what} (cva-node {state}); its last output:\n{self.tail()}')

    def wait_ready(self, timeout: float) -> None:
        """Wait for the ``ready`` line.

        Raises:
            ConfigError: The node exited or did not get ready in time.
        """
        deadline = time.monotonic() + timeout
        while not self.ready.wait(0.1):
            if not self.alive():
                self._reader.join(5)
                raise self.fail('the node exited before it was ready')
            if time.monotonic() > deadline:
                raise self.fail(f'the node printed no ready line within {timeout:.0f} s')

    def memory_mb(self, field_name: str) -> float | None:
        """``VmRSS``, ``VmHWM``… of the node process in MiB (``/proc`` counts KiB), None where
        unreadable."""
        try:
            with open(f'/proc/{self.process.pid}/status', encoding='ascii') as status:
                for line in status:
                    if line.startswith(field_name + ':'):
                        return int(line.split()[1]) / 1024.0
        except OSError:
            return None
        return None

    def cpu_seconds(self) -> float | None:
        """User + system CPU time of the node process so far (``/proc/<pid>/stat``), None
        where unreadable."""
        try:
            with open(f'/proc/{self.process.pid}/stat', encoding='ascii') as stat:
                # The command name (field 2) may hold spaces; the fields after it are plain.
                fields = stat.read().rsplit(')', 1)[1].split()
        except (OSError, IndexError):
            return None
        return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')

    def stop(self, sig: int = signal.SIGINT, timeout: float = 30.0) -> int:
        """Send ``sig`` (SIGINT: the node's clean stop), then SIGKILL if it does not end in
        ``timeout`` s; returns the exit code."""
        if self.alive():
            self.process.send_signal(sig)
            try:
                self.process.wait(timeout)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(10)
        self._reader.join(10)
        return self.process.returncode


@contextlib.contextmanager
def _stop_on_sigterm() -> Iterator[None]:
    """Turn SIGTERM (``timeout``, CI runners, systemd) into :class:`SystemExit` (143, with one
    line on stderr) meanwhile, so that ``finally`` blocks stop the node; its default action
    would end this process at once and leave the node running. Only in the main thread, and
    only over the default action (``cva-benchmark`` sets its own, which says the same)."""
    if threading.current_thread() is not threading.main_thread() or (
        signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL
    ):
        yield
        return

    def _exit(signum: int, _frame: object) -> None:
        # Said, as cva-benchmark says it: a bare 143 looked like a crash in a CI log.
        print(f'{_PROG}: terminated', file=sys.stderr, flush=True)
        raise SystemExit(128 + signum)

    signal.signal(signal.SIGTERM, _exit)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


# The DDS client -----------------------------------------------------------------------------


class _Client:
    """This side of the benchmark: publishes stereo pairs, times the node's answers over DDS.

    Args:
        domain_id: ROS domain shared with the node.
        outputs: Output topics to subscribe to and await.
    """

    def __init__(self, domain_id: int, outputs: Sequence[str]) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import CameraInfo, Image, PointCloud2
        from stereo_msgs.msg import DisparityImage

        from cva_confidence_ros.ros.common import spin_until_shutdown

        self._rclpy = rclpy
        self.outputs = tuple(outputs)
        self._context = Context()
        rclpy.init(context=self._context, domain_id=domain_id)
        self._node = Node('cva_node_benchmark', context=self._context)
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self._pubs = {
            'left_info': self._node.create_publisher(CameraInfo, 'left/camera_info', qos),
            'right_info': self._node.create_publisher(CameraInfo, 'right/camera_info', qos),
            'left': self._node.create_publisher(Image, 'left/image_rect', qos),
            'right': self._node.create_publisher(Image, 'right/image_rect', qos),
        }
        types = {
            'disparity': DisparityImage,
            'disparity_filtered': DisparityImage,
            'confidence': Image,
            'points2': PointCloud2,
        }
        self._cond = threading.Condition()
        self._arrivals: dict[int, dict[str, float]] = {}
        self._diagnostics: dict[str, str] | None = None
        self._diagnostics_count = 0
        self._subs = [
            self._node.create_subscription(
                types[topic],
                topic,
                # mypy cannot infer a lambda with a default argument against the callback type
                cast('Callable[[Any], None]',
                     lambda msg, topic=topic: self._on_output(topic, msg)),
                qos,
            )
            for topic in self.outputs
        ]
        self._node.create_subscription(
            DiagnosticArray, '/diagnostics', self._on_diagnostics, QoSProfile(depth=10)
        )
        self._executor = SingleThreadedExecutor(context=self._context)
        self._executor.add_node(self._node)
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=spin_until_shutdown, args=(self._executor, self._stop), daemon=True
        )
        self._thread.start()

    def close(self) -> None:
        """Stop spinning and shut the context down."""
        self._stop.set()
        self._thread.join(5.0)
        self._executor.shutdown()
        self._node.destroy_node()
        self._rclpy.try_shutdown(context=self._context)

    def __enter__(self) -> _Client:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    # Callbacks (executor thread)

    def _on_output(self, topic: str, msg: Any) -> None:
        now = time.perf_counter()
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        with self._cond:
            self._arrivals.setdefault(stamp, {})[topic] = now
            self._cond.notify_all()

    def _on_diagnostics(self, msg: Any) -> None:
        for status in msg.status:
            if status.name.endswith(_STATUS_SUFFIX):
                with self._cond:
                    self._diagnostics = {kv.key: kv.value for kv in status.values}
                    self._diagnostics_count += 1
                    self._cond.notify_all()

    # Main thread

    def matched(self) -> bool:
        """Whether the node subscribes to every input and publishes every awaited output."""
        inputs = all(pub.get_subscription_count() > 0 for pub in self._pubs.values())
        return inputs and all(sub.get_publisher_count() > 0 for sub in self._subs)

    def wait(
        self, predicate: Callable[[], bool], timeout: float, alive: Callable[[], bool]
    ) -> bool:
        """Wait until ``predicate()`` (checked under the lock) holds; False on timeout or when
        ``alive()`` turns False."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while not predicate():
                remaining = deadline - time.monotonic()
                if remaining <= 0 or not alive():
                    return False
                self._cond.wait(min(0.1, remaining))
        return True

    def answer_time(self, stamp: int) -> float | None:
        """``perf_counter`` time at which the last awaited output of ``stamp`` arrived."""
        arrivals = self._arrivals.get(stamp, {})
        if all(topic in arrivals for topic in self.outputs):
            return max(arrivals[topic] for topic in self.outputs)
        return None

    def diagnostics(self) -> dict[str, str] | None:
        """The node's latest diagnostic values (key → string), None before the first."""
        with self._cond:
            return None if self._diagnostics is None else dict(self._diagnostics)

    def counter(self, key: str) -> int:
        """An integer counter of the latest diagnostics (0 before the first)."""
        values = self._diagnostics or {}
        return int(values.get(key, 0))

    def idle_after(self, processed: int) -> bool:
        """Whether the node has processed ``processed`` frames and holds none pending."""
        if self._diagnostics is None:
            return False
        handled = sum(
            self.counter(key)
            for key in (
                'frames_processed', 'frames_dropped', 'frames_throttled', 'frames_invalid',
                'frames_failed',
            )
        )
        return (
            self.counter('frames_processed') >= processed
            and handled >= self.counter('frames_received')
        )

    def publish(self, messages: dict[str, Any]) -> float:
        """Publish one set of messages (infos first); return the ``perf_counter`` start."""
        start = time.perf_counter()
        for key in ('left_info', 'right_info', 'left', 'right'):
            self._pubs[key].publish(messages[key])
        return start


def frame_messages(left: np.ndarray, right: np.ndarray, stamp_ns: int) -> dict[str, Any]:
    """The four input messages of one stereo pair, all stamped ``stamp_ns``.

    Args:
        left: (H, W, 3) uint8 RGB rectified left image.
        right: Same for the right camera.
        stamp_ns: Header stamp in nanoseconds.

    Returns:
        ``left``, ``right`` (``rgb8`` Image) and ``left_info``, ``right_info`` (CameraInfo with
        fx = W, principal point in the centre and the right projection's Tx = −fx·B).
    """
    from sensor_msgs.msg import CameraInfo
    from std_msgs.msg import Header

    from cva_confidence_ros.ros.convert import ns_to_stamp, rgb_to_image

    height, width = left.shape[:2]
    focal = float(width)
    messages: dict[str, Any] = {}
    for side, image, tx in (('left', left, 0.0), ('right', right, -focal * _BASELINE_M)):
        header = Header(stamp=ns_to_stamp(stamp_ns), frame_id=f'{side}_optical')
        messages[side] = rgb_to_image(np.ascontiguousarray(image, dtype=np.uint8), header)
        info = CameraInfo(header=header, height=height, width=width, distortion_model='plumb_bob')
        info.k = [focal, 0.0, width / 2.0, 0.0, focal, height / 2.0, 0.0, 0.0, 1.0]
        info.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
        info.p = [focal, 0.0, width / 2.0, tx, 0.0, focal, height / 2.0, 0.0, 0.0, 0.0, 1.0, 0.0]
        messages[f'{side}_info'] = info
    return messages


_STAMP_STEP_NS = 1_000_000_000


def _stamps() -> Iterator[int]:
    # Whole milliseconds from now on, a second apart: unique within a run, and far enough
    # apart that a node with max_rate_hz ≥ 1 takes every timed frame.
    start = time.time_ns() // 1_000_000 * 1_000_000
    return itertools.count(start, _STAMP_STEP_NS)


def _check_frames(client: _Client, node: NodeProcess) -> None:
    if client.counter('frames_invalid') or client.counter('frames_failed'):
        raise node.fail(f'the node rejected a frame: {client.diagnostics()}')


def _warm_up(
    client: _Client,
    node: NodeProcess,
    pair: tuple[np.ndarray, np.ndarray],
    stamps: Iterator[int],
    timeout: float,
) -> None:
    """Get one answer, then wait until the node is idle.

    Endpoints that look matched may not yet deliver; the pair is sent again every few seconds
    while the node's diagnostics show that none reached it.
    """
    sent: list[int] = []
    deadline = time.monotonic() + timeout
    last_send = -float('inf')
    while True:
        reached = client.counter('frames_received') > 0
        if not reached and time.monotonic() - last_send > _RESEND_S:
            sent.append(next(stamps))
            client.publish(frame_messages(*pair, sent[-1]))
            last_send = time.monotonic()
        if client.wait(
            lambda: any(client.answer_time(s) is not None for s in sent), 0.5, node.alive
        ):
            break
        _check_frames(client, node)
        if not node.alive():
            raise node.fail('the node died during the warm-up frame')
        if time.monotonic() > deadline:
            raise node.fail(f'no answer to the warm-up frame within {timeout:.0f} s')
    if not client.wait(lambda: client.idle_after(1), timeout, node.alive):
        raise node.fail('the node did not become idle after the warm-up frame')


def _stage_times(values: dict[str, str] | None) -> dict[str, float]:
    if not values:
        return {}
    return {
        key[len('last_'):-len('_ms')]: float(value)
        for key, value in values.items()
        if key.startswith('last_') and key.endswith('_ms')
    }


def _burst(
    client: _Client,
    node: NodeProcess,
    pair: tuple[np.ndarray, np.ndarray],
    stamps: Iterator[int],
    settings: NodeBenchSettings,
) -> dict[str, Any]:
    assert settings.rate_hz is not None
    # Stamped as a camera at the burst's rate would stamp them (what max_rate_hz reads); the
    # stamps handed out after the burst lie beyond its last one.
    base, period = next(stamps), round(1e9 / settings.rate_hz)
    frames = [base + index * period for index in range(settings.burst_frames)]
    while next(stamps) <= frames[-1]:
        pass
    messages = [frame_messages(*pair, stamp) for stamp in frames]
    received = client.counter('frames_received')
    processed = client.counter('frames_processed')
    dropped = client.counter('frames_dropped')
    throttled = client.counter('frames_throttled')
    cpu_start = node.cpu_seconds()
    start = time.perf_counter()
    for index, message in enumerate(messages):
        pause = start + index / settings.rate_hz - time.perf_counter()
        if pause > 0:
            time.sleep(pause)
        client.publish(message)
    published_s = time.perf_counter() - start
    target = received + len(frames)
    client.wait(
        lambda: client.counter('frames_received') >= target and client.idle_after(processed + 1),
        settings.timeout_s,
        node.alive,
    )
    wall_s = time.perf_counter() - start
    cpu_end = node.cpu_seconds()
    if not node.alive():
        raise node.fail('the node died during the burst')
    times = sorted(t for t in (client.answer_time(s) for s in frames) if t is not None)
    dropped_now = client.counter('frames_dropped') - dropped
    throttled_now = client.counter('frames_throttled') - throttled
    output_hz = (len(times) - 1) / (times[-1] - times[0]) if len(times) >= 2 else None
    cpu_cores = (
        (cpu_end - cpu_start) / wall_s
        if cpu_start is not None and cpu_end is not None and wall_s > 0
        else None
    )
    return {
        'burst_rate_hz': settings.rate_hz,
        'burst_sent': len(frames),
        'burst_publish_hz': (len(frames) - 1) / published_s if published_s > 0 else None,
        'burst_answered': len(times),
        'burst_dropped': dropped_now,
        'burst_throttled': throttled_now,
        # neither answered nor dropped / skipped by the node's policy: lost on the way, unpaired,
        # invalid, failed, or not answered within the timeout
        'burst_lost': max(len(frames) - len(times) - dropped_now - throttled_now, 0),
        'burst_output_hz': output_hz,
        'burst_cpu_cores': cpu_cores,
    }


def measure_node(
    settings: NodeBenchSettings,
    matcher: str,
    method: str,
    pair: tuple[np.ndarray, np.ndarray],
    stamps: Iterator[int] | None = None,
    model_path: str = '',
    dds_profile_file: str | None = None,
) -> dict[str, Any]:
    """Start ``cva-node`` for one configuration and time it over DDS.

    Args:
        settings: Sizes, repeat, device and the rest.
        matcher: The node's ``matcher``.
        method: The node's ``confidence_method``.
        pair: (left, right) (H, W, 3) uint8 RGB input pair at the input size.
        stamps: Source of unique stamps (ns); None = a fresh one.
        model_path: The node's ``model_path`` (CVA-Net weights), '' = its default.
        dds_profile_file: Fast DDS XML profiles for the node and this client (see
            :data:`FASTDDS_LARGE_MESSAGES_XML`); None = the environment's DDS settings.

    Returns:
        A record with :data:`RECORD_KEYS` plus ``matcher``, ``method``, ``downsample``,
        ``latencies_ms`` (every timed frame), ``node_frames_ms`` (the node's own time of each,
        message in → outputs published), ``stages_ms`` (medians of the node's stage times),
        ``rss_ready_mb`` and, with a burst, the ``burst_*`` values.

    Raises:
        ConfigError: The node did not start, rejected the frames or did not answer in time.
    """
    stamps = stamps or _stamps()
    dds_env = {'ROS_DOMAIN_ID': str(settings.domain), 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}
    if dds_profile_file:
        dds_env.update(profile_environment(dds_profile_file))
    env = {**_package_env(settings.threads), **dds_env}
    # The client's participant reads these when its context starts (Fast DDS loads the XML
    # profiles once per process, at its first participant).
    previous = {name: os.environ.get(name) for name in dds_env}
    os.environ.update(dds_env)
    try:
        client = _Client(settings.domain, settings.outputs)
    finally:
        for name, saved in previous.items():
            if saved is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = saved
    with client, _stop_on_sigterm():
        command = [*node_command(), '--ros-args']
        command += node_parameters(settings, matcher, method, model_path)
        node = NodeProcess(command, env)
        try:
            node.wait_ready(_START_TIMEOUT_S)
            rss_ready = node.memory_mb('VmRSS')
            if not client.wait(client.matched, 60.0, node.alive):
                raise node.fail('the node and the benchmark client did not discover each other')
            _warm_up(client, node, pair, stamps, settings.timeout_s)
            done = client.counter('frames_processed')
            latencies: list[float] = []
            stages: dict[str, list[float]] = {}
            for _ in range(settings.repeat):
                stamp = next(stamps)
                messages = frame_messages(*pair, stamp)
                start = client.publish(messages)
                if not client.wait(
                    cast('Callable[[], bool]',
                         lambda stamp=stamp: client.answer_time(stamp) is not None),
                    settings.timeout_s,
                    node.alive,
                ):
                    _check_frames(client, node)
                    if not node.alive():
                        raise node.fail('the node died during a timed frame')
                    raise node.fail(f'no answer within {settings.timeout_s:.0f} s')
                answered = client.answer_time(stamp)
                assert answered is not None
                latencies.append((answered - start) * 1e3)
                done += 1
                # The diagnostics after this frame carry its stage times; waiting for them also
                # keeps the node idle before the next frame.
                if client.wait(
                    cast('Callable[[], bool]', lambda done=done: client.idle_after(done)),
                    50 * _DIAGNOSTICS_PERIOD_S,  # 10 s: a loaded machine may be slow to send
                    node.alive,
                ):
                    for stage, value in _stage_times(client.diagnostics()).items():
                        stages.setdefault(stage, []).append(value)
            _check_frames(client, node)
            peak = node.memory_mb('VmHWM')
            burst = _burst(client, node, pair, stamps, settings) if settings.rate_hz else {}
        finally:
            node.stop()
    latency = statistics.median(latencies)
    fps = 1000.0 / latency
    record: dict[str, Any] = {
        'config': f'node:{matcher}+{method}' + ''.join(
            f' {name}={value}' for name, value in settings.params
        ),
        'device': settings.device,
        'width': settings.width,
        'height': settings.height,
        'max_disparity': settings.max_disparity,
        'ms_per_frame': latency,
        'peak_mem_mb': peak,
        'network_gflops': None,
        'gemm_gflops': None,
        'auc_rel': None,
        'latency_ms_median': latency,
        'fps': fps,
        'online': fps >= ONLINE_HZ,
        'extrapolated': False,
        'matcher': matcher,
        'method': method,
        'downsample': settings.downsample,
        'latencies_ms': latencies,
        'node_frames_ms': stages.get('frame', []),
        'stages_ms': {stage: statistics.median(values) for stage, values in stages.items()},
        'rss_ready_mb': rss_ready,
        'dds_profile': settings.dds_profile,
        'params': dict(settings.params),
        'outputs': list(settings.outputs),
        'note': '',
    }
    record.update(burst)
    return record


# CVA-Net: weights, operation count, crop measurement, extrapolation --------------------------


def cva_net_weights(matcher: str, max_disparity: int, folder: Path) -> tuple[str, str]:
    """The shipped weights for (matcher, D), else random ones saved under ``folder``.

    Returns:
        (path, what it is: ``shipped <name>`` or ``random init``).
    """
    import torch

    from cva_confidence_ros.model import CVANet, default_weights_path, save_weights

    try:
        path = default_weights_path(matcher, max_disparity)
        return str(path), f'shipped {path.name}'
    except ModelError:
        pass
    torch.manual_seed(0)
    path = folder / f'random_cvanet_{matcher}_d{max_disparity}.pt'
    meta = {'matcher': matcher, 'max_disparity': max_disparity, 'note': 'random, for timing'}
    save_weights(CVANet(max_disparity), path, meta=meta)
    return str(path), f'random init (no shipped weights for {matcher}, D = {max_disparity})'


def network_flops(
    height: int, width: int, max_disparity: int, tile_budget_mb: float = 512.0
) -> float:
    """Floating-point operations of CVA-Net on a whole (D, H, W) cost volume.

    Counted by :class:`torch.utils.flop_counter.FlopCounterMode` (2 per multiply-add) on
    tensors without data, for the tiles that :func:`~cva_confidence_ros.model.
    predict_confidence` cuts under ``tile_budget_mb`` (each padded by 6 px, so that small
    tiles cost more per pixel).

    Returns:
        Operations per frame (float).
    """
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    from cva_confidence_ros.model import PAD, CVANet, fold_batchnorm, tile_shape

    rows, columns = tile_shape(height, width, max_disparity, tile_budget_mb)
    tiles: Counter[tuple[int, int]] = Counter()
    for y0 in range(0, height, rows):
        for x0 in range(0, width, columns):
            tiles[(min(height, y0 + rows) - y0, min(width, x0 + columns) - x0)] += 1
    net = fold_batchnorm(CVANet(max_disparity)).to('meta')
    total = 0.0
    for (tile_rows, tile_columns), count in tiles.items():
        volume = torch.empty(
            (1, 1, max_disparity, tile_rows + 2 * PAD, tile_columns + 2 * PAD), device='meta'
        )
        with FlopCounterMode(display=False) as counter, torch.inference_mode():
            net(volume)
        total += count * float(counter.get_total_flops())
    return total


def _reset_own_peak() -> bool:
    try:
        with open('/proc/self/clear_refs', 'w', encoding='ascii') as clear:
            clear.write('5')  # VmHWM := VmRSS (Linux ≥ 4.0)
        return True
    except OSError:
        return False


def _gemm_gflops(size: int = 1024, repeat: int = 5) -> float:
    """Best float32 matrix-product rate of torch on this device's CPU, GFLOP/s."""
    import torch

    a = torch.rand(size, size)
    b = torch.rand(size, size)
    torch.mm(a, b)
    best = float('inf')
    for _ in range(repeat):
        start = time.perf_counter()
        torch.mm(a, b)
        best = min(best, time.perf_counter() - start)
    return 2.0 * size**3 / best / 1e9


def measure_network_crop(
    settings: NodeBenchSettings, matcher: str, weights: str
) -> dict[str, Any]:
    """CVA-Net's speed on a crop of the frame's cost volume (in this process).

    The volume is computed by the matcher on a band of full-width rows, as many as the crop
    has, in the middle of the pair (so that every crop column has all its disparities), cut to
    the crop's middle columns, and then goes through what the pipeline's confidence stage
    runs: the ``cva_net`` method of the registry and its map to [0, 1].

    Returns:
        ``crop`` (rows, columns at the processed resolution), ``crop_confidence_ms`` (the
        confidence stage: the network plus its padding and checks), ``crop_pixels_per_s``,
        ``crop_flops``, ``frame_flops`` (the whole processed frame), ``crop_gflop_per_s``,
        ``crop_peak_delta_mb`` (peak resident memory of the network call above what was
        resident before it, None where the peak mark cannot be reset), ``gemm_gflops``
        (torch's matrix-product rate, a ceiling) and ``threads``.
    """
    import torch

    from cva_confidence_ros.confidence import CONFIDENCE_METHODS, ConfidenceInputs
    from cva_confidence_ros.datasets.resize import resize_image
    from cva_confidence_ros.matching import compute_cost_volume, wta_disparity
    from cva_confidence_ros.model import resolve_device, tile_shape
    from cva_confidence_ros.pipeline import PipelineConfig

    if settings.threads is not None:
        torch.set_num_threads(settings.threads)
    config = PipelineConfig(
        matcher=matcher,
        max_disparity=settings.max_disparity,
        confidence_method=_NETWORK,
        model_path=weights,
        device=settings.device,
        downsample=settings.downsample,
    )
    full_rows, full_columns = settings.processed_size
    rows, columns = settings.crop or tile_shape(
        full_rows, full_columns, config.max_disparity, config.tile_budget_mb
    )
    rows, columns = min(rows, full_rows), min(columns, full_columns)
    left, right = benchmark_pair(settings.width, settings.height)
    left, right = resize_image(left, config.downsample), resize_image(right, config.downsample)
    top = (full_rows - rows) // 2
    band = slice(top, top + rows)
    params: dict[str, Any] = {}
    if matcher == 'mccnn_fast':
        params['device'] = str(resolve_device(config.device))
    volume = compute_cost_volume(
        np.ascontiguousarray(left[band]),
        np.ascontiguousarray(right[band]),
        matcher,
        config.max_disparity,
        **params,
    )
    first = (full_columns - columns) // 2
    window = slice(first, first + columns)
    volume = np.ascontiguousarray(volume[:, :, window])
    inputs = ConfidenceInputs(
        cost_volume=volume,
        disparity=wta_disparity(volume),
        image=np.ascontiguousarray(left[band, window]),
        matcher=matcher,
    )
    method = CONFIDENCE_METHODS.get(_NETWORK)(
        matcher=matcher,
        max_disparity=config.max_disparity,
        weights=weights,
        device=config.device,
        tile_budget_mb=config.tile_budget_mb,
    )
    # An untimed run on a few pixels loads torch's kernels.
    tiny = ConfidenceInputs(
        cost_volume=np.ascontiguousarray(volume[:, :2, :2]),
        disparity=inputs.disparity[:2, :2],
        image=np.ascontiguousarray(inputs.image[:2, :2]),
        matcher=matcher,
    )
    method(tiny)
    rss_before = memory_kb('VmRSS')
    peak_reset = _reset_own_peak()
    start = time.perf_counter()
    method.to_unit_interval(np.asarray(method(inputs), dtype=np.float32))
    seconds = time.perf_counter() - start
    peak = memory_kb('VmHWM') if peak_reset else None
    crop_flops = network_flops(rows, columns, config.max_disparity, config.tile_budget_mb)
    frame_flops = network_flops(
        full_rows, full_columns, config.max_disparity, config.tile_budget_mb
    )
    return {
        'crop': [rows, columns],
        'crop_confidence_ms': seconds * 1e3,
        'crop_pixels_per_s': rows * columns / seconds,
        'crop_flops': crop_flops,
        'frame_flops': frame_flops,
        'crop_gflop_per_s': crop_flops / seconds / 1e9,
        'crop_peak_delta_mb': (
            None if peak is None or rss_before is None else (peak - rss_before) / 1024.0
        ),
        'gemm_gflops': _gemm_gflops(),
        'threads': torch.get_num_threads(),
    }


def _settings_args(settings: NodeBenchSettings) -> list[str]:
    args = [
        '--width', str(settings.width),
        '--height', str(settings.height),
        '--max-disparity', str(settings.max_disparity),
        '--downsample', str(settings.downsample),
        '--device', settings.device,
    ]  # fmt: skip
    if settings.crop is not None:
        args += ['--crop', str(settings.crop[0]), str(settings.crop[1])]
    if settings.threads is not None:
        args += ['--threads', str(settings.threads)]
    return args


def _crop_in_subprocess(settings: NodeBenchSettings, matcher: str, weights: str) -> dict[str, Any]:
    # A process of its own: torch's threads and memory, as in the node, not in this client.
    command = [
        sys.executable, '-m', 'cva_confidence_ros.node_benchmark',
        _CROP_WORKER_FLAG, matcher, '--weights', weights, *_settings_args(settings),
    ]  # fmt: skip
    with _stop_on_sigterm():  # subprocess.run kills the worker when this ends by an exception
        result = subprocess.run(
            command,
            capture_output=True,
            text=True,
            env=_package_env(settings.threads),
            check=False,
        )
    for line in reversed(result.stdout.splitlines()):
        if line.startswith(_RECORD_PREFIX):
            return json.loads(line[len(_RECORD_PREFIX):])
    raise ConfigError(
        f'CVA-Net crop measurement for {matcher!r} failed (exit code {result.returncode}); '
        f'expected a record, got stderr:\n{result.stderr[-2000:]}'
    )


def extrapolate_cva_net(
    base: dict[str, Any], crop: dict[str, Any], weights_note: str
) -> dict[str, Any]:
    """A CVA-Net row from a measured node row of the same matcher and a crop measurement.

    latency = base latency − base confidence stage + crop network time × frame FLOPs / crop
    FLOPs. Peak memory is not extrapolated (None); ``crop_peak_delta_mb`` says what one
    network call on the crop added.

    Args:
        base: A :func:`measure_node` record of ``node:<matcher>+pkrn`` (``stages_ms`` with
            ``confidence`` if the node's diagnostics came; otherwise nothing is taken out).
        crop: A :func:`measure_network_crop` record.
        weights_note: What weights were timed (shipped or random).

    Returns:
        A record with :data:`RECORD_KEYS` (``extrapolated`` True) and the crop values.
    """
    network_ms = crop['crop_confidence_ms'] * crop['frame_flops'] / crop['crop_flops']
    base_stages = dict(base.get('stages_ms') or {})
    base_confidence = base_stages.get('confidence', 0.0)
    latency = base['latency_ms_median'] - base_confidence + network_ms
    stages = dict(base_stages)
    stages['confidence'] = network_ms
    for stage in ('total', 'frame'):
        if stage in stages:
            stages[stage] += network_ms - base_confidence
    fps = 1000.0 / latency
    matcher = base['matcher']
    rows, columns = crop['crop']
    note = (
        f'extrapolated: network {crop["crop_pixels_per_s"]:.0f} px/s '
        f'({crop["crop_gflop_per_s"]:.1f} GFLOP/s) on a {rows}×{columns} crop, scaled by '
        f'FLOPs ({crop["frame_flops"] / 1e9:.0f} GFLOP/frame); rest = {base["config"]} '
        f'minus its confidence stage; {weights_note}'
    )
    return {
        **{key: base[key] for key in ('device', 'width', 'height', 'max_disparity')},
        'config': f'node:{matcher}+{_NETWORK}',
        'ms_per_frame': latency,
        'peak_mem_mb': None,
        'network_gflops': crop['frame_flops'] / 1e9,
        'gemm_gflops': crop['gemm_gflops'],
        'auc_rel': None,
        'latency_ms_median': latency,
        'fps': fps,
        'online': fps >= ONLINE_HZ,
        'extrapolated': True,
        'matcher': matcher,
        'method': _NETWORK,
        'downsample': base.get('downsample', 1),
        'latencies_ms': [],
        'node_frames_ms': [],
        'stages_ms': stages,
        'rss_ready_mb': None,
        'dds_profile': base.get('dds_profile'),
        'outputs': base.get('outputs'),
        'base_config': base['config'],
        'base_latency_ms': base['latency_ms_median'],
        'network_ms': network_ms,
        **{key: crop[key] for key in crop if key.startswith('crop')},
        'weights': weights_note,
        'note': note,
    }


# The suite ------------------------------------------------------------------------------------


def _log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def run_suite(
    settings: NodeBenchSettings,
    matchers: Sequence[str] = DEFAULT_MATCHERS,
    methods: Sequence[str] = DEFAULT_METHODS,
    log: Callable[[str], None] = _log,
) -> list[dict[str, Any]]:
    """Measure every matcher × method, one node process each.

    CVA-Net rows run through the node when ``settings.full_cva_net`` or the device is not
    the CPU, else they are extrapolated (see the module docstring); the ``pkrn`` run they build
    on is made for them if ``pkrn`` is not among ``methods`` (and then not returned).

    Returns:
        The records, matcher-major, in the order of ``methods``.

    Raises:
        ConfigError: Unknown names, or a configuration that failed.
    """
    from cva_confidence_ros.confidence import CONFIDENCE_METHODS
    from cva_confidence_ros.matching import MATCHERS

    for option, names, registry in (
        ('matchers', matchers, MATCHERS),
        ('methods', methods, CONFIDENCE_METHODS),
    ):
        if not names:
            raise ConfigError(f'--{option} needs at least one name')
        for name in names:
            registry.get(name)
        repeated = sorted(name for name, count in Counter(names).items() if count > 1)
        if repeated:
            raise ConfigError(f'--{option} names {repeated} more than once')
    full = settings.full_cva_net or settings.device != 'cpu'
    if settings.params and _NETWORK in methods and not full:
        raise ConfigError(
            f'--param with {_NETWORK} on the CPU needs --full-cva-net: the extrapolated row '
            f'times the exact network on a crop and would ignore the parameters'
        )
    pair = benchmark_pair(settings.width, settings.height)
    stamps = _stamps()
    records: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix='cva_node_bench_') as folder:
        profile = None if settings.dds_profile == _INHERIT else settings.dds_profile
        if settings.dds_profile == _LARGE_SHM:
            profile = str(write_profile(folder))

        def measure(method: str, model_path: str = '') -> dict[str, Any]:
            return measure_node(settings, matcher, method, pair, stamps, model_path, profile)

        for matcher in matchers:
            base: dict[str, Any] | None = None
            by_method: dict[str, dict[str, Any]] = {}
            # CVA-Net last: its extrapolation builds on the pkrn run.
            for method in sorted(methods, key=lambda name: name == _NETWORK):
                if method != _NETWORK:
                    log(f'measuring node:{matcher}+{method} …')
                    by_method[method] = measure(method)
                    if method == BASE_METHOD:
                        base = by_method[method]
                    continue
                weights, weights_note = cva_net_weights(
                    matcher, settings.max_disparity, Path(folder)
                )
                if full:
                    log(f'measuring node:{matcher}+{method} (full network; {weights_note}) …')
                    record = measure(method, weights)
                    record['weights'] = weights_note
                    record['note'] = weights_note
                    by_method[method] = record
                    continue
                if base is None:
                    log(f'measuring node:{matcher}+{BASE_METHOD} (base of the CVA-Net row) …')
                    base = measure(BASE_METHOD)
                log(f'measuring CVA-Net on a crop ({matcher}; {weights_note}) …')
                crop = _crop_in_subprocess(settings, matcher, weights)
                by_method[method] = extrapolate_cva_net(base, crop, weights_note)
                log(f'node:{matcher}+{method}: EXTRAPOLATED from the crop, not run whole')
            records.extend(by_method[method] for method in methods)
    return records


def _cell(value: float | None, digits: int = 1) -> str:
    if value is None:
        return '–'
    return f'{value:.{digits}f}'


def format_table(records: Sequence[dict[str, Any]], threads: int) -> str:
    """Markdown table of the records, with what was measured how."""
    first = records[0]
    lines = [
        f"Node end to end: {first['width']}×{first['height']} input, D = "
        f"{first['max_disparity']}, downsample {first.get('downsample', 1)}, device "
        f"{first['device']}, {threads} CPU cores, DDS profile {first.get('dds_profile')}",
        '',
        '| config | latency ms | fps | online (≥ 5 Hz) | matching ms | confidence ms '
        '| node frame ms | peak RSS MiB |',
        '|---|---:|---:|:---:|---:|---:|---:|---:|',
    ]
    awaited = ' and '.join(first.get('outputs') or NodeBenchSettings().outputs)
    for record in records:
        stages = record.get('stages_ms') or {}
        mark = ' *' if record['extrapolated'] else ''
        lines.append(
            f"| {record['config']}{mark} | {_cell(record['latency_ms_median'])} "
            f"| {_cell(record['fps'], 2)} | {'yes' if record['online'] else 'no'} "
            f"| {_cell(stages.get('matching'))} | {_cell(stages.get('confidence'))} "
            f"| {_cell(stages.get('frame'))} | {_cell(record['peak_mem_mb'], 0)} |"
        )
    lines += [
        '',
        'latency = median over the timed frames of: publish of the pair + camera infos → '
        f'{awaited} received (one frame at a time, reliable QoS); fps = 1000 / '
        "latency; matching, confidence, node frame = the node's own stage times (from "
        '/diagnostics; node frame = message in → outputs published); peak RSS = VmHWM of the '
        'node process.',
    ]
    bursts = [r for r in records if r.get('burst_rate_hz')]
    if bursts:
        lines += [
            '',
            '| config | burst in Hz | sent | answered | dropped | throttled | lost | out Hz '
            '| node CPU cores |',
            '|---|---:|---:|---:|---:|---:|---:|---:|---:|',
        ]
        lines += [
            f"| {r['config']} | {_cell(r['burst_publish_hz'])} | {r['burst_sent']} "
            f"| {r['burst_answered']} | {r['burst_dropped']} | {r['burst_throttled']} "
            f"| {r.get('burst_lost', '–')} | {_cell(r['burst_output_hz'], 2)} "
            f"| {_cell(r['burst_cpu_cores'], 2)} |"
            for r in bursts
        ]
        lines.append(
            'burst: pairs published at a fixed rate without waiting; the node works on the '
            'newest pending pair and drops the ones it had no time for, or skips them under '
            'max_rate_hz (throttled); lost = neither answered nor dropped nor throttled (never '
            'paired, invalid, failed or no answer in time); node CPU cores = its user + system '
            "CPU time over the burst's wall time (publish of the first pair → the node idle "
            'again).'
        )
    extrapolated = [r for r in records if r['extrapolated']]
    if extrapolated:
        lines.append('* EXTRAPOLATED, not run whole (pass --full-cva-net to run it):')
        lines += [f"  - {r['config']}: {r['note']}" for r in extrapolated]
    noted = [r for r in records if r.get('note') and not r['extrapolated']]
    lines += [f"- {r['config']}: {r['note']}" for r in noted]
    return '\n'.join(lines)


def _parser() -> argparse.ArgumentParser:
    defaults = NodeBenchSettings()
    parser = argparse.ArgumentParser(
        prog=_PROG,
        description='End-to-end latency, throughput and peak memory of cva-node over DDS, '
        'for every matcher and confidence method (one node process each).',
        epilog=EXIT_CODES,
    )
    parser.add_argument('--width', type=int, default=defaults.width)
    parser.add_argument('--height', type=int, default=defaults.height)
    parser.add_argument('--max-disparity', type=int, default=defaults.max_disparity)
    parser.add_argument('--repeat', type=int, default=defaults.repeat,
                        help='timed frames per configuration (after one warm-up frame)')
    parser.add_argument('--downsample', type=int, default=defaults.downsample)
    parser.add_argument('--device', default=defaults.device, choices=_DEVICES)
    parser.add_argument('--matchers', nargs='+', default=list(DEFAULT_MATCHERS), metavar='NAME')
    parser.add_argument('--methods', nargs='+', default=list(DEFAULT_METHODS), metavar='NAME')
    parser.add_argument('--full-cva-net', action='store_true',
                        help='run CVA-Net through the node on the CPU too (tens of minutes a '
                        'frame at 640×480, D = 128) instead of extrapolating from a crop')
    parser.add_argument('--crop', type=int, nargs=2, default=None, metavar=('ROWS', 'COLUMNS'),
                        help='crop that CVA-Net is timed on when extrapolating (default: one '
                        'network tile of the frame, 90×90 at D = 128)')
    parser.add_argument('--threads', type=int, default=None,
                        help='CPU threads of the node (default: all cores)')
    parser.add_argument('--rate', type=float, default=None, metavar='HZ',
                        help='also publish a burst of frames at HZ without waiting')
    parser.add_argument('--burst-frames', type=int, default=defaults.burst_frames)
    parser.add_argument('--outputs', nargs='+', default=list(defaults.outputs),
                        choices=_OUTPUTS, help='output topics awaited per frame')
    parser.add_argument('--timeout', type=float, default=defaults.timeout_s,
                        help='longest wait for one answer, s')
    parser.add_argument('--domain-id', type=int, default=None)
    parser.add_argument('--dds-profile', default=defaults.dds_profile,
                        metavar='large-shm|inherit|PATH',
                        help='Fast DDS settings of the node and the client: large-shm (default; a '
                        '16 MB shared-memory segment, without which 640×480 frames stall for '
                        "seconds), inherit (the environment's) or an XML profiles file")
    parser.add_argument('--param', action='append', default=[], metavar='NAME=VALUE',
                        help='extra node parameter, passed as -p NAME:=VALUE to every node '
                        'started (repeatable), e.g. --param cva_stride=4')
    parser.add_argument('--json', type=Path, default=None, metavar='PATH',
                        help='write the records as a JSON list to PATH')
    parser.add_argument(_CROP_WORKER_FLAG, default=None, help=argparse.SUPPRESS)
    parser.add_argument('--weights', default='', help=argparse.SUPPRESS)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``cva-benchmark --suite node``; returns the process exit code."""
    parser = _parser()
    args = parser.parse_args(argv)
    try:
        settings = NodeBenchSettings(
            width=args.width,
            height=args.height,
            max_disparity=args.max_disparity,
            repeat=args.repeat,
            downsample=args.downsample,
            device=args.device,
            full_cva_net=args.full_cva_net,
            crop=None if args.crop is None else (args.crop[0], args.crop[1]),
            threads=args.threads,
            rate_hz=args.rate,
            burst_frames=args.burst_frames,
            outputs=tuple(args.outputs),
            timeout_s=args.timeout,
            domain_id=args.domain_id,
            dds_profile=args.dds_profile,
            params=parse_params(args.param),
        )
        if args.crop_worker is not None:
            record = measure_network_crop(settings, args.crop_worker, args.weights)
            print(_RECORD_PREFIX + json.dumps(record), flush=True)
            return 0
        if args.json is not None:  # a folder or an unwritable place: refused before the run
            check_output_file(args.json, '--json')
        records = run_suite(settings, args.matchers, args.methods)
    except CVAError as error:
        parser.exit(2, f'{_PROG}: error: {error}\n')
    host = host_summary()
    # The records are saved before anything is printed, as the other suites do: a table that
    # fails to print (`| head -1`, exit 141) lost a run of minutes.
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        rows = [{**record, 'host': host} for record in records]
        args.json.write_text(strict_json.dumps(rows, indent=2) + '\n', encoding='utf-8')
        _log(f'wrote {args.json}')
    print(format_table(records, os.cpu_count() or 1))
    print(f'host: {host}')
    return 0


if __name__ == '__main__':
    sys.exit(main())

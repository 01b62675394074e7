"""What the package's nodes share: start-up and spinning with clean exits, throttled logs.

:func:`run_node` is the body of every node's ``main``: ``rclpy.init`` with the command line, the
node, a single-threaded executor, and the exit codes a shell expects (0 on Ctrl-C or SIGTERM
once running, 2 for bad ``--ros-args`` or a configuration the node refuses, 130 when interrupted
before the node is up). :class:`ReasonThrottle` keeps one steady fault from hiding the others in
the log.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Sequence
import re
import signal
import sys
import threading
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import (
    Executor,
    ExternalShutdownException,
    ShutdownException,
    SingleThreadedExecutor,
)
from rclpy.impl.rcutils_logger import RcutilsLogger
import rclpy.logging
from rclpy.logging import LoggingSeverity
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import QoSProfile, qos_profile_sensor_data

from cva_confidence_ros.errors import CVAError, reason
from cva_confidence_ros.ros import interrupt

__all__ = [
    'EXIT_BAD_START',
    'EXIT_INTERRUPTED',
    'LOG_THROTTLE_S',
    'READY',
    'ReasonThrottle',
    'diagnostic_status',
    'publish_status',
    'qos_profile',
    'run_node',
    'spin_until_shutdown',
]

LOG_THROTTLE_S = 5.0
#: First word of the line a node logs once it is up; scripts wait for it.
READY = 'ready'
EXIT_BAD_START = 2
EXIT_INTERRUPTED = 130  # 128 + SIGINT, as a shell reports a Ctrl-C


def diagnostic_status(
    node: Node, what: str, level: bytes, message: str, values: dict[str, object]
) -> DiagnosticStatus:
    """A node's ``DiagnosticStatus``: named ``<node name>: <what>``, the node's full name as
    hardware id, every value as a string."""
    return DiagnosticStatus(
        level=level,
        name=f'{node.get_name()}: {what}',
        message=message,
        hardware_id=node.get_fully_qualified_name(),
        values=[KeyValue(key=key, value=str(value)) for key, value in values.items()],
    )


def publish_status(node: Node, publisher: Publisher, status: DiagnosticStatus) -> None:
    """Publish ``status`` alone in a ``DiagnosticArray`` stamped with the node's clock."""
    array = DiagnosticArray(status=[status])
    array.header.stamp = node.get_clock().now().to_msg()
    publisher.publish(array)


def qos_profile(name: str) -> QoSProfile:
    """The QoS of a preset name: ``sensor_data`` (best effort, keep last 5) or ``reliable``
    (keep last 10)."""
    if name == 'sensor_data':
        return qos_profile_sensor_data
    return QoSProfile(depth=10)


class ReasonThrottle:
    """Throttle log messages per reason: the first of each is let through, repeats once a period.

    rclpy throttles per call site, so one steady fault (a wrong encoding on every frame) would
    hide every other one behind it.

    Args:
        period_s: Least time between two messages of one reason, seconds.
        max_reasons: Reasons remembered; the one logged longest ago is forgotten first.
    """

    def __init__(self, period_s: float = LOG_THROTTLE_S, max_reasons: int = 64) -> None:
        self.period_s = period_s
        self.max_reasons = max_reasons
        self._lock = threading.Lock()
        # reason → [monotonic time it was last logged, repeats held back since]
        self._reasons: OrderedDict[str, list[float]] = OrderedDict()

    @staticmethod
    def key(reason: str) -> str:
        """The reason without its numbers: sizes, steps and stamps vary, the fault does not."""
        return re.sub(r'\d+', '#', reason)

    def admit(self, reason: str) -> int | None:
        """Whether to log a message of ``reason`` now.

        Returns:
            None to stay silent; else how many of this reason were held back since it was last
            logged (0 the first time).
        """
        key = self.key(reason)
        now = time.monotonic()
        with self._lock:
            entry = self._reasons.get(key)
            if entry is None:
                self._reasons[key] = [now, 0]
                if len(self._reasons) > self.max_reasons:
                    self._reasons.popitem(last=False)
                return 0
            if now - entry[0] < self.period_s:
                entry[1] += 1
                return None
            held_back = int(entry[1])
            entry[0], entry[1] = now, 0
            self._reasons.move_to_end(key)
            return held_back

    def log(self, logger: RcutilsLogger, why: str, message: str, *, error: bool = False) -> None:
        """Log ``message`` as a warning (an error with ``error``) unless one for the same ``why``
        was logged within the period."""
        held_back = self.admit(why)
        if held_back is None:
            return
        if held_back:
            message += f' ({held_back} more like it held back since the last one logged)'
        # rclpy fixes the severity of each calling line at its first call: one line a severity.
        if error:
            logger.error(message)
        else:
            logger.warning(message)


def spin_until_shutdown(executor: Executor, stop: threading.Event | None = None) -> None:
    """Spin ``executor`` until ``stop`` is set, the executor is shut down or its context is.

    For background spin threads. A context shut down during a spin (Ctrl-C, or the owner
    closing it) ends the spin quietly, whichever way rclpy reports it: as
    ``ExternalShutdownException`` after the wait, or as rcl's ``RCLError`` when the shutdown
    lands between the executor's check of the context and the wait set that needs it.
    """
    context = executor.context
    while context.ok() and not (stop is not None and stop.is_set()):
        try:
            executor.spin_once(timeout_sec=0.05)
        except ShutdownException:
            return
        except Exception:
            if context.ok():
                raise
            return


def _init(args: list[str]) -> None:
    """``rclpy.init`` without rcl's own log line on a bad argument: the exception says more."""
    rclpy.logging.set_logger_level('rcl', LoggingSeverity.FATAL)
    try:
        rclpy.init(args=args)
    finally:
        # Back to the default, unless ``--log-level rcl:=…`` has just set a level of its own.
        if rclpy.logging.get_logger_level('rcl') == LoggingSeverity.FATAL:
            rclpy.logging.set_logger_level('rcl', LoggingSeverity.UNSET)


def run_node(factory: Callable[[], Node], name: str, argv: Sequence[str] | None = None) -> int:
    """Run the node ``factory()`` builds until Ctrl-C or SIGTERM.

    Once the node is up, ``ready: <node.summary()>`` is logged; a Ctrl-C after that line is a
    clean stop (0), one before it an interrupted start (130). Through
    :func:`cva_confidence_ros.node.run_entry`, a Ctrl-C is noted rather than raised
    (:mod:`cva_confidence_ros.ros.interrupt`) and the start stops once the node is built.

    Args:
        factory: Builds the node once rclpy is initialised; may raise :class:`CVAError` or
            rclpy's ``ParameterException`` for a configuration it refuses.
        name: Logger name for start-up failures (the node's name).
        argv: Command line including ROS arguments; None = ``sys.argv``.

    Returns:
        0 on a clean stop, :data:`EXIT_BAD_START` when the ROS arguments or the start-up
        configuration are invalid, :data:`EXIT_INTERRUPTED` when interrupted before the node
        is up.
    """
    args = list(sys.argv if argv is None else argv)
    logger = rclpy.logging.get_logger(name)
    node: Node | None = None
    up = False
    code = 0
    try:
        try:
            _init(args)
        except RuntimeError as error:
            # rcl's RCLError and UnknownROSArgsError: an unreadable --params-file, a bad flag.
            logger.fatal(f'cannot start: {reason(error, limit=300)}')
            return EXIT_BAD_START
        node = factory()
        if interrupt.requested():
            # A Ctrl-C before rclpy.init installed its handler (which would have shut the
            # context down under the constructor) was only noted: the start was interrupted.
            return EXIT_INTERRUPTED
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        # Up before the ready line is written: whoever reacts to the line with a Ctrl-C must get
        # a clean stop (0), even if the signal lands before the logging call has returned.
        up = True
        summary = getattr(node, 'summary', None)
        node.get_logger().info(f'{READY}: {summary() if summary else node.get_name()}')
        # Until Ctrl-C or SIGTERM: rclpy's handler shuts the context down, which ends the spin.
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        # Ctrl-C stops a running node cleanly; before its ready line, it interrupts the start.
        # (KeyboardInterrupt only reaches here when the caller did not go through run_entry.)
        code = 0 if up else EXIT_INTERRUPTED
    except (CVAError, ParameterException) as error:
        logger.fatal(f'cannot start: {error}')
        code = EXIT_BAD_START
    except Exception:
        # A signal during start-up shuts the context down under the constructor; the error
        # that follows is that interruption, not a fault worth a traceback.
        if rclpy.ok():
            raise
        code = 0 if up else EXIT_INTERRUPTED
    finally:
        # A second Ctrl-C while a worker finishes its frame must not print a traceback.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return code

"""What the package's nodes share: start-up and spinning with clean exits, throttled logs.

:func:`run_node` is the body of every node's ``main``: ``rclpy.init`` with the command line, the
node, a single-threaded executor, and the exit codes a shell expects (0 on Ctrl-C or SIGTERM
once running, 2 for bad ``--ros-args`` or a configuration the node refuses, 130 when interrupted
before the node is up). :func:`check_arguments` answers the rest of a node's command line first:
``-h``/``--help`` prints :func:`usage_text`, anything else outside ``--ros-args`` is refused.
:class:`ReasonThrottle` keeps one steady fault from hiding the others in the log.
"""

from __future__ import annotations

import atexit
from collections import OrderedDict
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
import os
import re
import signal
import sys
import textwrap
import threading
import time
import warnings

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import SetParametersResult
import rclpy
from rclpy.exceptions import InvalidParameterTypeException, ParameterException
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
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)
from rclpy.qos_overriding_options import InvalidQosOverridesError, QoSOverridingOptions
from rclpy.utilities import remove_ros_args

from cva_confidence_ros.errors import ConfigError, CVAError, end_process, reason
from cva_confidence_ros.ros import interrupt
from cva_confidence_ros.ros.dds_profile import PROFILE_VARIABLES

__all__ = [
    'EXIT_BAD_START',
    'EXIT_INTERRUPTED',
    'LARGE_MESSAGES_HINT',
    'LOG_THROTTLE_S',
    'PROFILE_VARIABLES',
    'QOS_OVERRIDES',
    'READY',
    'ReasonThrottle',
    'check_arguments',
    'diagnostic_status',
    'large_messages_unset',
    'publish_status',
    'qos_override_errors',
    'qos_profile',
    'run_node',
    'spin_until_shutdown',
    'usage_text',
    'warn_unknown_parameters',
]

LOG_THROTTLE_S = 5.0
#: First word of the line a node logs once it is up; scripts wait for it.
READY = 'ready'
EXIT_BAD_START = 2
EXIT_INTERRUPTED = 130  # 128 + SIGINT, as a shell reports a Ctrl-C


def diagnostic_status(
    node: Node, what: str, level: bytes, message: str, values: dict[str, object]
) -> DiagnosticStatus:
    """A node's ``DiagnosticStatus``: named ``<namespace/node name>: <what>`` (the namespace
    without its leading slash, none in the root one), the node's full name as hardware id,
    every value as a string."""
    # Named with the namespace: two cameras' nodes of one name in their own namespaces would
    # otherwise give one status name, which diagnostic_aggregator and rqt_robot_monitor key
    # by, so that one camera's warning is overwritten by the other's OK.
    return DiagnosticStatus(
        level=level,
        name=f'{node.get_fully_qualified_name().lstrip("/")}: {what}',
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
    (keep last 10). A new profile on every call: rclpy writes a topic's QoS overrides into
    the profile it is given, which must not reach the next topic.

    Raises:
        ConfigError: For any other name (a misspelt preset must not become ``reliable``).
    """
    if name not in ('sensor_data', 'reliable'):
        raise ConfigError(f'QoS preset must be sensor_data or reliable; got {name!r}')
    if name == 'sensor_data':
        return QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=qos_profile_sensor_data.depth,
            reliability=ReliabilityPolicy.BEST_EFFORT,
            durability=DurabilityPolicy.VOLATILE,
        )
    return QoSProfile(depth=10)


#: The values a QoS override may take, for the messages about one that it may not.
_QOS_OVERRIDE_VALUES = (
    'expected reliability reliable | best_effort, history keep_last | keep_all, depth >= 1'
)


def _check_overridden_qos(qos: QoSProfile) -> SetParametersResult:
    # ``unknown`` is a name rclpy's enums have but rmw refuses, with a bare "invalid allocator".
    for policy, value in (('reliability', qos.reliability), ('history', qos.history)):
        if value.name == 'UNKNOWN':
            reason = f'{policy} unknown is not one rmw takes; {_QOS_OVERRIDE_VALUES}'
            return SetParametersResult(successful=False, reason=reason)
    if qos.history == HistoryPolicy.KEEP_LAST and qos.depth < 1:
        return SetParametersResult(
            successful=False, reason=f'depth must be >= 1 with history keep_last; got {qos.depth}'
        )
    return SetParametersResult(successful=True)


#: ROS 2's standard per-topic QoS overrides (as rclcpp's ``with_default_policies``): read-only
#: parameters ``qos_overrides.<topic>.<publisher|subscription>.<history|depth|reliability>``,
#: declared with the preset's values, that a parameter file or ``-p`` sets at start-up.
QOS_OVERRIDES = QoSOverridingOptions.with_default_policies(callback=_check_overridden_qos)


@contextmanager
def qos_override_errors(topic: str) -> Iterator[None]:
    """Turn rclpy's errors for a bad ``qos_overrides.<topic>.*`` value into :class:`ConfigError`
    (rclpy raises a bare ``RuntimeError`` for an unknown policy name, and its
    ``InvalidParameterTypeException`` for a value of the wrong type: ``depth:=five``).

    ``topic`` is named as given: pass the resolved name (``node.resolve_topic_name``), the one
    the ``qos_overrides.<topic>`` parameters are keyed by. rclpy's warning about a zero depth
    is left out: the refusal that follows says it in one line."""
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings('ignore', message='A zero depth with KEEP_LAST',
                                    category=UserWarning)
            yield
    except InvalidQosOverridesError as error:
        raise ConfigError(f'QoS override of {topic}: {error}') from None
    except InvalidParameterTypeException as error:
        if not str(error).startswith("Trying to set parameter 'qos_overrides."):
            raise
        raise ConfigError(f'QoS override of {topic}: {error}; {_QOS_OVERRIDE_VALUES}') from None
    except RuntimeError as error:
        if 'QoS override' not in str(error):
            raise
        raise ConfigError(f'QoS override of {topic}: {error}; {_QOS_OVERRIDE_VALUES}') from None


def warn_unknown_parameters(node: Node) -> list[str]:
    """Log one warning naming the start-up parameters (``-p``, ``--params-file``) that ``node``
    does not have, each with the nearest name it has (a misspelt ``confidence_treshold`` is
    otherwise ignored without a word, and the node runs with the default).

    A warning, not a refusal: a parameter file's ``/**`` section applies to every node, so
    other nodes' names there are expected. ``qos_overrides.*`` are left out (declared only
    when the topics are made, which for the managed node is later). Call it once every
    parameter is declared.

    Returns:
        The names warned about.
    """
    from difflib import get_close_matches

    # rclpy keeps the start-up values in a private attribute; there is no public accessor.
    overrides = getattr(node, '_parameter_overrides', None) or {}
    declared = list(node.list_parameters([], 0).names)
    unknown = sorted(
        name for name in overrides
        if not name.startswith('qos_overrides.') and not node.has_parameter(name)
    )
    if unknown:
        named = []
        for name in unknown:
            near = get_close_matches(name, declared, n=1, cutoff=0.75)
            named.append(f'{name} (did you mean {near[0]}?)' if near else name)
        node.get_logger().warning(
            f'start-up parameters this node does not have, ignored: {", ".join(named)}; '
            "its --help lists its parameters (a parameter file's /** section applies to every "
            'node, so names of other nodes there are expected)'
        )
    return unknown


#: What a message about images that never arrive adds while no profile is set.
LARGE_MESSAGES_HINT = (
    'images over 512 kB (640×480 colour) are lost on the way by Fast DDS without '
    'config/fastdds_large_messages.xml in FASTRTPS_DEFAULT_PROFILES_FILE on both ends (README: '
    'Images of 640×480 and more over DDS)'
)


def large_messages_unset() -> bool:
    """Whether no Fast DDS profile file is set: then an image over Fast DDS's 512 kB
    shared-memory segment goes by UDP in fragments, and with best-effort QoS one lost fragment
    loses it (``config/fastdds_large_messages.xml`` lets it through)."""
    return not any(os.environ.get(name) for name in PROFILE_VARIABLES)


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
        # rclpy's spin_once returns at once, quietly, once the executor is shut down (it
        # swallows its own ShutdownException): without this check the loop would spin hot.
        if getattr(executor, '_is_shutdown', False):
            return
        try:
            executor.spin_once(timeout_sec=0.05)
        except ShutdownException:
            return
        except Exception:
            if context.ok():
                raise
            return


#: ROS flags that, given without ``--ros-args`` in front, are a forgotten ``--ros-args``.
_ROS_FLAGS = frozenset(
    {'-p', '--param', '-r', '--remap', '--params-file', '-e', '--enclave', '--log-level'}
)
_WIDTH = 99


def _ros_value(value: object) -> str:
    """``value`` as written after ``-p name:=``: YAML's true/false, '' for an empty string."""
    if isinstance(value, bool):
        return str(value).lower()
    if value == '':
        return "''"
    return str(value)


def usage_text(
    prog: str,
    summary: str,
    topics: Sequence[tuple[str, str, str, str]] = (),
    parameters: Sequence[tuple[str, object, str, str]] = (),
    example: str = 'name:=value',
    qos_topic: str = '',
) -> str:
    """A node's ``--help``: how to call it, its topics and its parameters with their defaults.

    Args:
        prog: The program's name as called (``cva-node``, ``node``).
        summary: One sentence on what the node does.
        topics: ``(direction, name, type, note)`` a topic, direction ``in`` or ``out``.
        parameters: ``(name, default, limits, description)`` a parameter; ``limits`` is a short
            note for the parameter's line (a range, ``(start-up only)``), may be empty.
        example: A ``name:=value`` for the examples.
        qos_topic: An input topic for the example of the per-topic QoS overrides
            (:data:`QOS_OVERRIDES`); ``''`` = no such section.
    """
    lines = [
        f'usage: {prog} [-h] [--ros-args [-p NAME:=VALUE] [--params-file FILE] '
        '[-r FROM:=TO] ...]',
    ]
    if summary:
        lines += ['', *textwrap.wrap(summary, _WIDTH)]
    if topics:
        lines += ['', 'topics (rename with --ros-args -r NAME:=NEW_NAME):']
        name_width = max(len(name) for _, name, _, _ in topics)
        type_width = max(len(kind) for _, _, kind, _ in topics)
        for direction, name, kind, note in topics:
            line = f'  {direction:<3}  {name:<{name_width}}  {kind:<{type_width}}  {note}'
            lines.append(line.rstrip())
    if parameters:
        lines += [
            '',
            'parameters (defaults shown; set with --ros-args -p NAME:=VALUE or --params-file '
            'FILE):',
        ]
        for name, default, limits, description in parameters:
            lines.append(f'  {name}:={_ros_value(default)}  {limits}'.rstrip())
            lines += textwrap.wrap(
                description, _WIDTH, initial_indent=' ' * 6, subsequent_indent=' ' * 6
            )
    if qos_topic:
        lines += [
            '',
            *textwrap.wrap(
                'per-topic QoS (ROS 2 QoS overrides, start-up only; they refine input_qos / '
                'output_qos): qos_overrides.<topic>.<publisher|subscription>.<policy>:=<value>, '
                'policy reliability (reliable, best_effort), history (keep_last, keep_all) or '
                'depth, topic as resolved (namespace and remaps applied), e.g.',
                _WIDTH,
            ),
            f'  -p qos_overrides./{qos_topic}.subscription.reliability:=reliable',
        ]
    lines += [
        '',
        'examples:',
        f'  {prog} --ros-args -p {example}',
        f'  {prog} --ros-args -r __ns:=/stereo --params-file params.yaml',
    ]
    return '\n'.join(lines) + '\n'


def check_arguments(
    args: Sequence[str],
    usage: Callable[[str], str] | None = None,
    example: str = 'name:=value',
) -> int | None:
    """Answer a node's command line outside its ROS arguments, before anything starts.

    ``-h``/``--help`` prints ``usage(prog)`` to stdout; any other argument outside ``--ros-args
    … [--]`` is refused with one line on stderr, as argparse would. ROS arguments that rcl cannot
    parse are left to ``rclpy.init`` (:func:`run_node`), which says what is wrong with them.

    Args:
        args: The command line, program name first (``sys.argv``).
        usage: The help text for a program name; None = only how to pass ROS arguments.
        example: A ``name:=value`` of the node's, for the hint that ROS arguments go after
            ``--ros-args``.

    Returns:
        None to go on and start the node; else the exit status: 0 after the help,
        :data:`EXIT_BAD_START` for an argument the node does not take.
    """
    args = list(args)
    prog = os.path.basename(args[0]) if args else 'node'
    try:
        extra = remove_ros_args(args)[1:]
    except RuntimeError:
        # rcl's RCLError and UnknownROSArgsError: run_node reports them as it starts.
        return None
    if not extra:
        return None
    if '-h' in extra or '--help' in extra:
        text = usage(prog) if usage is not None else usage_text(prog, '', example=example)
        sys.stdout.write(text)
        sys.stdout.flush()
        return 0
    if extra[0] in _ROS_FLAGS:
        # ``-p threshold:=0.8`` without ``--ros-args`` in front: the line it should have been.
        hint = f': --ros-args {" ".join(extra)}'
    else:
        hint = f', e.g. --ros-args -p {example}'
    print(
        f'{prog}: error: unrecognised argument(s): {" ".join(extra)} '
        f'(ROS arguments go after --ros-args{hint})',
        file=sys.stderr,
        flush=True,
    )
    return EXIT_BAD_START


def _init(args: list[str]) -> None:
    """``rclpy.init`` without rcl's own log line on a bad argument: the exception says more."""
    rclpy.logging.set_logger_level('rcl', LoggingSeverity.FATAL)
    try:
        rclpy.init(args=args)
    finally:
        # Back to the default, unless ``--log-level rcl:=…`` has just set a level of its own.
        if rclpy.logging.get_logger_level('rcl') == LoggingSeverity.FATAL:
            rclpy.logging.set_logger_level('rcl', LoggingSeverity.UNSET)


def params_file_problems(args: Sequence[str]) -> list[str]:
    """What is wrong with each ``--params-file FILE`` in the ROS arguments of ``args``.

    rcl answers a missing, unreadable or directory path as it answers bad YAML ("Couldn't parse
    params file"); this names the path and what is wrong with it. ``[]`` when each one can be
    opened (whether its YAML is good is left to rcl).
    """
    problems = []
    inside = False
    items = list(args)
    for index, item in enumerate(items):
        if item == '--ros-args':
            inside = True
        elif item == '--':
            inside = False
        elif inside and item == '--params-file' and index + 1 < len(items):
            path = items[index + 1]
            if not os.path.exists(path):
                problems.append(f'--params-file {path}: no such file')
            elif os.path.isdir(path):
                problems.append(f'--params-file {path}: is a folder, not a YAML file')
            elif not os.access(path, os.R_OK):
                problems.append(f'--params-file {path}: not readable (permission denied)')
    return problems


def run_node(factory: Callable[[], Node], name: str, argv: Sequence[str] | None = None) -> int:
    """Run the node ``factory()`` builds until Ctrl-C or SIGTERM.

    Once the node is up, ``ready: <node.summary()>`` is logged; a Ctrl-C after that line is a
    clean stop (0), one before it an interrupted start (130). Through
    :func:`cva_confidence_ros.node.run_entry`, a Ctrl-C is noted rather than raised
    (:mod:`cva_confidence_ros.ros.interrupt`) and the start stops once the node is built.

    A node whose ``destroy_node`` leaves a frame running (its ``frame_left_running`` is True)
    ends the process here with the code, without finalising the interpreter: a worker thread
    still inside torch would otherwise abort it. Run it as a process's body, not in-process.

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
    problems = params_file_problems(args)
    if problems:
        logger.fatal(f'cannot start: {"; ".join(problems)}')
        return EXIT_BAD_START
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
        # A second Ctrl-C while a worker finishes its frame must not print a traceback. A
        # SIGTERM now is ros2 launch's next step after its SIGINT (SIGKILL follows 5 s later):
        # the stop waits no longer for a long frame (interrupt.hurry). Both stay ignored up to
        # the end of the process (_ignore_stop_signals): a terminal's Ctrl-C reaches the node
        # and then ros2 launch's own SIGINT, and one that came while the interpreter shut down
        # killed the node (exit -2) or printed a KeyboardInterrupt traceback.
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, signal.SIG_IGN)
            signal.signal(signal.SIGTERM, interrupt.hurry)
            _ignore_stop_signals_at_exit()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    if getattr(node, 'frame_left_running', False):
        # Finalising the interpreter under a worker thread that is inside torch's C++ ends a
        # thread there that cannot be ended (std::terminate: the process aborts, SIGABRT).
        end_process(code)
    return code


_ignoring_at_exit = False  # _ignore_stop_signals registered with atexit


def _ignore_stop_signals() -> None:
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)


def _ignore_stop_signals_at_exit() -> None:
    """Ignore SIGINT and SIGTERM from the interpreter's exit on (once registered).

    Registered last, it runs among the first exit handlers; set to "ignore", the two stay so
    through the interpreter's shutdown, which otherwise puts the default action back (a signal
    then kills the process) before the slow part of it (torch, rclpy).
    """
    global _ignoring_at_exit
    if not _ignoring_at_exit:
        _ignoring_at_exit = True
        atexit.register(_ignore_stop_signals)


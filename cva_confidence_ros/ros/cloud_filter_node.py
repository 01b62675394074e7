"""The rclpy node behind :mod:`cva_confidence_ros.cloud_filter`: a point cloud cut at a threshold.

Subscribes to ``points2`` (any little-endian ``sensor_msgs/PointCloud2`` with x, y, z and a
confidence field, e.g. the confidence node's with ``points_confidence: true``) and republishes on
``points2_filtered`` the points whose confidence is at least ``threshold``, every other field
(rgb, intensity, …) carried along, with the input's header. ``threshold`` can be changed at run
time, so one confidence stream serves consumers with different needs: a mapper that wants only
sure points and an obstacle layer that would rather see everything but the worst.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields, replace
import threading
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
import numpy as np
from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor, SetParametersResult
from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile
from sensor_msgs.msg import PointCloud2

from cva_confidence_ros.checks import is_real
from cva_confidence_ros.errors import ConfigError, CVAError
from cva_confidence_ros.pointcloud import filter_cloud
from cva_confidence_ros.ros.common import (
    QOS_OVERRIDES,
    ReasonThrottle,
    diagnostic_status,
    publish_status,
    qos_override_errors,
    qos_profile,
    run_node,
    warn_unknown_parameters,
)
from cva_confidence_ros.ros.convert import point_cloud_to_records, records_to_point_cloud
from cva_confidence_ros.ros.params import (
    QOS_CHOICES,
    double_overrides,
    double_value,
    keep_doubles,
    restore_types,
)

__all__ = [
    'NODE_NAME',
    'PARAMETER_DESCRIPTIONS',
    'READ_ONLY_PARAMETERS',
    'CloudFilterConfig',
    'CloudFilterNode',
    'run',
]

NODE_NAME = 'cva_cloud_filter'

# rclpy's timers take whole nanoseconds in an int64: a shorter period is 0 (a timer that fires
# without pause), a longer one overflows (OverflowError, TypeError) when the timer is made.
_MIN_PERIOD_S = 1e-9
_MAX_PERIOD_S = float((2**63 - 1) // 10**9)


@dataclass(frozen=True)
class CloudFilterConfig:
    """The filter's parameters (one ROS parameter each, same names).

    Attributes:
        threshold: Points with confidence ≥ it are kept, in [0, 1].
        organized: Keep the input's grid and set x, y, z of dropped points to NaN; false = a
            dense cloud of the kept points only.
        confidence_field: Name of the confidence field of the input cloud.
        input_qos: QoS of the subscription, one of :data:`QOS_CHOICES` (start-up only); the
            default best-effort subscription receives from reliable and best-effort publishers
            alike.
        output_qos: QoS of the publisher (start-up only).
        diagnostics_period_seconds: Period of ``/diagnostics`` messages (start-up only).
    """

    threshold: float = 0.5
    organized: bool = True
    confidence_field: str = 'confidence'
    input_qos: str = 'sensor_data'
    output_qos: str = 'reliable'
    diagnostics_period_seconds: float = 1.0

    def __post_init__(self) -> None:
        if not is_real(self.threshold) or not 0.0 <= self.threshold <= 1.0:
            raise ConfigError(f'threshold must be a number in [0, 1]; got {self.threshold!r}')
        if not isinstance(self.organized, bool):
            raise ConfigError(f'organized must be a bool; got {self.organized!r}')
        if not isinstance(self.confidence_field, str) or not self.confidence_field:
            raise ConfigError(
                f'confidence_field must name a point field; got {self.confidence_field!r}'
            )
        for name in ('input_qos', 'output_qos'):
            if getattr(self, name) not in QOS_CHOICES:
                raise ConfigError(
                    f'{name} must be one of {QOS_CHOICES}; got {getattr(self, name)!r}'
                )
        if not is_real(self.diagnostics_period_seconds) or not (
            _MIN_PERIOD_S <= self.diagnostics_period_seconds <= _MAX_PERIOD_S
        ):
            raise ConfigError(
                f'diagnostics_period_seconds must be in [{_MIN_PERIOD_S:g}, {_MAX_PERIOD_S:g}] '
                f'(a timer counts whole nanoseconds in an int64); got '
                f'{self.diagnostics_period_seconds}'
            )


#: Parameter name → its description (declared with it; ``cva-cloud-filter --help`` lists them).
PARAMETER_DESCRIPTIONS = {
    'threshold': 'Points with confidence >= threshold are kept.',
    'organized': 'Keep the input grid with NaN for dropped points; false = kept points only.',
    'confidence_field': 'Name of the confidence field of the input cloud.',
    'input_qos': 'QoS of the points2 subscription: sensor_data (best effort) or reliable.',
    'output_qos': 'QoS of points2_filtered: sensor_data (best effort) or reliable.',
    'diagnostics_period_seconds': 'Period of /diagnostics messages, seconds.',
}
#: Parameters fixed at start-up.
READ_ONLY_PARAMETERS = frozenset({'input_qos', 'output_qos', 'diagnostics_period_seconds'})


def _values(values: dict[str, Any]) -> dict[str, Any]:
    """Parameter values for :class:`CloudFilterConfig`, the doubles as floats through
    :func:`~cva_confidence_ros.ros.params.double_value` (an integer literal taken as its
    number; the config checks the ranges).

    Raises:
        ConfigError: A double that is no number.
    """
    doubles = {spec.name for spec in fields(CloudFilterConfig) if isinstance(spec.default, float)}
    return {
        name: double_value(name, value) if name in doubles else value
        for name, value in values.items()
    }


@dataclass
class _Counts:
    clouds_received: int = 0
    clouds_published: int = 0
    clouds_invalid: int = 0
    points_received: int = 0
    points_kept: int = 0
    last_error: str = ''


class CloudFilterNode(Node):
    """rclpy node that keeps the points of ``points2`` with confidence ≥ ``threshold``.

    Args:
        context: rclpy context (tests use one per node); None = the global one.
        parameter_overrides: Start-up parameter values, as with ``--ros-args -p``.
        **kwargs: Passed on to :class:`rclpy.node.Node`.

    Raises:
        ConfigError: The start-up parameters are invalid.
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
            doubles = [f.name for f in fields(CloudFilterConfig) if isinstance(f.default, float)]
            double_overrides(self, doubles)
            for spec in fields(CloudFilterConfig):
                descriptor = ParameterDescriptor(
                    description=PARAMETER_DESCRIPTIONS[spec.name],
                    read_only=spec.name in READ_ONLY_PARAMETERS,
                    # threshold:=1 (an integer to ROS 2) is a number too; _values converts it.
                    dynamic_typing=isinstance(spec.default, float),
                )
                if spec.name == 'threshold':
                    descriptor.floating_point_range = [
                        FloatingPointRange(from_value=0.0, to_value=1.0, step=0.0)
                    ]
                self.declare_parameter(spec.name, spec.default, descriptor)
            keep_doubles(self, doubles)
            warn_unknown_parameters(self)
            names = [spec.name for spec in fields(CloudFilterConfig)]
            self._config = CloudFilterConfig(
                **_values({name: self.get_parameter(name).value for name in names})
            )
            self._lock = threading.Lock()
            self._counts = _Counts()
            self._window_invalid = 0  # since the last /diagnostics message
            self._throttle = ReasonThrottle()
            self.add_on_set_parameters_callback(self._on_set_parameters)
            # ROS 2's per-topic QoS overrides refine the presets (``qos_overrides./points2.
            # subscription.depth``, …); a bad value stops the start with the topic named.
            with qos_override_errors(self.resolve_topic_name('points2_filtered')):
                self._publisher = self.create_publisher(
                    PointCloud2, 'points2_filtered', qos_profile(self._config.output_qos),
                    qos_overriding_options=QOS_OVERRIDES,
                )
            with qos_override_errors(self.resolve_topic_name('points2')):
                self.create_subscription(
                    PointCloud2, 'points2', self._on_cloud, qos_profile(self._config.input_qos),
                    qos_overriding_options=QOS_OVERRIDES,
                )
            self._diagnostics = self.create_publisher(
                DiagnosticArray, '/diagnostics', QoSProfile(depth=10)
            )
            self.create_timer(self._config.diagnostics_period_seconds, self._publish_diagnostics)
        except BaseException:
            # Refused (a bad value, a bad qos_overrides one): destroyed here, as the confidence
            # node is, not left to the garbage collector, which would unregister the /rosout
            # publisher of its name, by then perhaps a later node's (whose log lines are lost).
            self.destroy_node()
            raise

    def summary(self) -> str:
        """One line on the filter's settings, for its ready line."""
        config = self.config
        return (
            f'threshold={config.threshold} organized={config.organized} '
            f'confidence_field={config.confidence_field}'
        )

    @property
    def config(self) -> CloudFilterConfig:
        """The configuration the next cloud is filtered with."""
        with self._lock:
            return self._config

    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        changes = {p.name: p.value for p in params if p.name in PARAMETER_DESCRIPTIONS}
        if not changes:
            return SetParametersResult(successful=True)
        with self._lock:
            try:
                self._config = replace(self._config, **_values(changes))
            except (ConfigError, TypeError) as error:
                restore_types(self, params)
                return SetParametersResult(successful=False, reason=str(error))
        self.get_logger().info(
            'parameters set: ' + ', '.join(f'{name}={value!r}' for name, value in changes.items())
        )
        return SetParametersResult(successful=True)

    def _on_cloud(self, msg: PointCloud2) -> None:
        config = self.config
        if msg.height * msg.width == 0:
            # "Nothing seen": passed on as it came, whatever its (possibly empty) fields.
            self._publisher.publish(msg)
            with self._lock:
                self._counts.clouds_received += 1
                self._counts.clouds_published += 1
            return
        try:
            records = point_cloud_to_records(msg)
            kept = filter_cloud(
                records, config.threshold, config.organized, config.confidence_field
            )
            out = records_to_point_cloud(kept, msg.header)
        except CVAError as error:
            self._dropped(str(error))
            return
        except Exception as error:  # noqa: BLE001  (the node must outlive any one cloud)
            self._dropped(f'{type(error).__name__}: {error}', error=True)
            return
        self._publisher.publish(out)
        with self._lock:
            counts = self._counts
            counts.clouds_received += 1
            counts.clouds_published += 1
            counts.points_received += _finite_points(records)
            counts.points_kept += _finite_points(kept)

    def _dropped(self, why: str, error: bool = False) -> None:
        with self._lock:
            self._counts.clouds_received += 1
            self._counts.clouds_invalid += 1
            self._window_invalid += 1
            self._counts.last_error = why
        self._throttle.log(self.get_logger(), why, f'dropped cloud: {why}', error=error)

    def stats(self) -> dict[str, int]:
        """Counters since start: clouds received, published and invalid; finite points in and
        kept."""
        with self._lock:
            counts = asdict(self._counts)
        counts.pop('last_error')
        return counts

    def _publish_diagnostics(self) -> None:
        with self._lock:
            counts = asdict(self._counts)
            config = self._config
            window_invalid, self._window_invalid = self._window_invalid, 0
        level, message = DiagnosticStatus.OK, f'threshold {config.threshold}'
        if window_invalid:
            level = DiagnosticStatus.WARN
            message = f'{window_invalid} cloud(s) dropped: {counts["last_error"]}'
        values = {**counts, 'threshold': config.threshold, 'organized': config.organized}
        status = diagnostic_status(self, 'point cloud confidence filter', level, message, values)
        publish_status(self, self._diagnostics, status)


def _finite_points(records: np.ndarray) -> int:
    finite = np.isfinite(records['x']) & np.isfinite(records['y']) & np.isfinite(records['z'])
    return int(finite.sum())


def run(argv: Sequence[str] | None = None) -> int:
    """Run the filter until Ctrl-C or SIGTERM: the body of
    :func:`cva_confidence_ros.cloud_filter.main`."""
    return run_node(CloudFilterNode, NODE_NAME, argv)

"""The node's ROS parameters: declarations with descriptions and ranges, and their configs.

Every parameter maps one to one onto a field of :class:`~cva_confidence_ros.pipeline.
PipelineConfig` (what is computed) or of :class:`NodeConfig` (how the node talks to ROS). The
defaults are those of the two dataclasses, so there is one source of truth; the shipped
``config/cva_confidence.yaml`` lists the same names.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import MISSING, dataclass, fields
import math
from typing import Any

from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    ParameterType,
)
from rclpy.node import Node
from rclpy.parameter import Parameter

from cva_confidence_ros.checks import is_int, is_real
from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.pipeline import PipelineConfig
from cva_confidence_ros.ros.convert import DEPTH_ENCODINGS
from cva_confidence_ros.scan import ScanConfig

__all__ = [
    'NODE_PARAMETERS',
    'PARAMETERS',
    'PIPELINE_PARAMETERS',
    'QOS_CHOICES',
    'NodeConfig',
    'ParamSpec',
    'build_configs',
    'change_fault',
    'check_declared_ranges',
    'scan_parameters',
    'declare_parameters',
    'double_overrides',
    'keep_doubles',
    'restore_types',
    'double_value',
    'parameter_values',
]

#: QoS presets: ``sensor_data`` (best effort, keep last 5) or ``reliable`` (keep last 10).
QOS_CHOICES = ('sensor_data', 'reliable')
#: Image transports the node subscribes with (``image_transport`` names).
TRANSPORT_CHOICES = ('raw', 'compressed')


@dataclass(frozen=True)
class NodeConfig:
    """How the node subscribes, synchronises and publishes (not what it computes).

    Attributes:
        publish_points: Publish ``points2``.
        points_organized: Organised cloud (H×W, NaN for dropped points) instead of a dense one.
        points_confidence: ``points2`` holds every point that can be triangulated, with a fifth
            float32 field ``confidence``, for consumers that filter with their own threshold
            (``cloud_filter``); false = only the points with confidence ≥ threshold.
        publish_depth: Publish ``depth``, the depth of the kept pixels (REP 118).
        depth_encoding: ``32FC1`` (metres, NaN = no depth) or ``16UC1`` (millimetres, 0 = no
            depth), one of :data:`~cva_confidence_ros.ros.convert.DEPTH_ENCODINGS`.
        image_transport: ``raw`` (``sensor_msgs/Image`` on ``left/image_rect``, …) or
            ``compressed`` (``sensor_msgs/CompressedImage``, JPEG or PNG, on
            ``left/image_rect/compressed``, …, as ``image_transport`` publishes them).
        input_qos: QoS of the four subscriptions, one of :data:`QOS_CHOICES`.
        output_qos: QoS of the outputs; ``reliable`` serves reliable and best-effort readers.
        approximate_sync: Pair messages whose stamps differ by up to the tolerance.
        approximate_sync_tolerance_seconds: Largest stamp spread of one set (≥ 0).
        queue_size: Messages held per topic while waiting for their partners (≥ 1).
        diagnostics_period_seconds: Period of ``/diagnostics`` messages and of the status log.
        max_rate_hz: Process at most this many frames per second of input time: a set whose
            stamp is less than 0.98 / max_rate_hz after the last one taken is skipped
            (``frames_throttled``), so the node leaves the rest of the CPU to the robot; 0 =
            every frame it can.
        min_kept_fraction: ``/diagnostics`` warns when the share of the pixels kept (finite
            disparity, confidence ≥ threshold, not in a speckle), averaged over a diagnostics
            period, is below it; 0 = never.
        max_expected_kept_error: ``/diagnostics`` warns when the error rate the confidence
            predicts for the kept pixels (``expected_kept_error``: mean of 1 − confidence over
            them, averaged over a diagnostics period; only for the networks, whose confidence
            is a probability) is above it; 1 = never.
        publish_scan: Publish ``scan``, a ``sensor_msgs/LaserScan`` of the kept pixels
            (:mod:`cva_confidence_ros.scan`), for obstacle layers.
        scan_frame_id: Frame of ``scan`` (x forward); ``''`` = the camera's body frame named
            after its optical frame (:func:`~cva_confidence_ros.scan.scan_frame_id`); no
            leading ``/`` (tf2 refuses such frames).
        scan_min_height: Lowest point in the scan, metres above the camera (negative = below).
        scan_max_height: Highest point in the scan.
        scan_range_min: Nearest range of the scan, metres.
        scan_range_max: Farthest range of the scan, metres.
        scan_pitch: How far the camera looks down from level, radians.
        overlay_jpeg_quality: JPEG quality (1–100) of ``confidence_overlay/compressed``.
        compressed_depth_max: Largest depth sent on ``depth/compressedDepth``, metres (> 0);
            deeper pixels travel as no depth (:mod:`cva_confidence_ros.ros.transport`).
        compressed_depth_quantization: Inverse-depth quantisation of a 32FC1
            ``depth/compressedDepth`` (> 0): larger = finer near depths.
        compressed_depth_png_level: zlib level (0–9) of the ``depth/compressedDepth`` PNG.

    Raises:
        ConfigError: A value the node refuses, named by its parameter (also in ``fields``).
    """

    publish_points: bool = True
    points_organized: bool = True
    points_confidence: bool = False
    publish_depth: bool = True
    depth_encoding: str = '32FC1'
    image_transport: str = 'raw'
    input_qos: str = 'sensor_data'
    output_qos: str = 'reliable'
    approximate_sync: bool = False
    approximate_sync_tolerance_seconds: float = 0.01
    queue_size: int = 10
    diagnostics_period_seconds: float = 1.0
    max_rate_hz: float = 0.0
    min_kept_fraction: float = 0.0
    max_expected_kept_error: float = 1.0
    publish_scan: bool = True
    scan_frame_id: str = ''
    scan_min_height: float = -0.25
    scan_max_height: float = 0.25
    scan_range_min: float = 0.1
    scan_range_max: float = 20.0
    scan_pitch: float = 0.0
    overlay_jpeg_quality: int = 95
    compressed_depth_max: float = 10.0
    compressed_depth_quantization: float = 100.0
    compressed_depth_png_level: int = 3

    def __post_init__(self) -> None:
        # A quoted YAML 'false' or a 0/1 would pass for a switch (truthy) or fail later, in
        # the synchroniser; the switches take booleans only, as PipelineConfig's do. Likewise a
        # 2.5 or a True for a count, a '0.1' for a number (a TypeError below), a 5 for a frame.
        for item in fields(self):
            value = getattr(self, item.name)
            if isinstance(item.default, bool):
                if not isinstance(value, bool):
                    raise ConfigError(
                        f'{item.name} must be True or False; got {value!r}', item.name
                    )
            elif isinstance(item.default, int):
                if not is_int(value):
                    raise ConfigError(f'{item.name} must be an integer; got {value!r}', item.name)
            elif isinstance(item.default, float):
                # (the scan_* numbers: ScanConfig checks them, below)
                if not is_real(value) and not item.name.startswith('scan_'):
                    raise ConfigError(f'{item.name} must be a number; got {value!r}', item.name)
            elif not isinstance(value, str):
                raise ConfigError(f'{item.name} must be a string; got {value!r}', item.name)
        if self.depth_encoding not in DEPTH_ENCODINGS:
            raise ConfigError(
                f'depth_encoding must be one of {DEPTH_ENCODINGS}; got {self.depth_encoding!r}',
                'depth_encoding',
            )
        if self.image_transport not in TRANSPORT_CHOICES:
            raise ConfigError(
                f'image_transport must be one of {TRANSPORT_CHOICES}; got '
                f'{self.image_transport!r}', 'image_transport',
            )
        for name in ('input_qos', 'output_qos'):
            if getattr(self, name) not in QOS_CHOICES:
                raise ConfigError(
                    f'{name} must be one of {QOS_CHOICES}; got {getattr(self, name)!r}', name
                )
        if not (
            math.isfinite(self.approximate_sync_tolerance_seconds)
            and self.approximate_sync_tolerance_seconds >= 0
        ):
            # (inf made tolerance_ns raise OverflowError on the first message)
            raise ConfigError(
                'approximate_sync_tolerance_seconds must be a finite number >= 0; '
                f'got {self.approximate_sync_tolerance_seconds}',
                'approximate_sync_tolerance_seconds',
            )
        if self.queue_size < 1:
            raise ConfigError(f'queue_size must be >= 1; got {self.queue_size}', 'queue_size')
        if not (math.isfinite(self.max_rate_hz) and self.max_rate_hz >= 0):
            raise ConfigError(
                f'max_rate_hz must be a finite number >= 0 (0 = no limit); got {self.max_rate_hz}',
                'max_rate_hz',
            )
        if self.max_rate_hz and not 0.98e9 / self.max_rate_hz < 2**63:
            # A period beyond int64 nanoseconds (inf for 1e-300 Hz) made min_period_ns raise
            # OverflowError on the first set of messages.
            raise ConfigError(
                f'max_rate_hz must be 0 (no limit) or at least {0.98e9 / 2**63:.3g} Hz (a '
                f'period that int64 nanoseconds hold); got {self.max_rate_hz}', 'max_rate_hz',
            )
        if not 0.0 <= self.min_kept_fraction <= 1.0:
            raise ConfigError(
                f'min_kept_fraction must be in [0, 1]; got {self.min_kept_fraction}',
                'min_kept_fraction',
            )
        if not 0.0 <= self.max_expected_kept_error <= 1.0:
            raise ConfigError(
                f'max_expected_kept_error must be in [0, 1]; got {self.max_expected_kept_error}',
                'max_expected_kept_error',
            )
        if not (
            math.isfinite(self.diagnostics_period_seconds) and self.diagnostics_period_seconds > 0
        ):
            raise ConfigError(
                'diagnostics_period_seconds must be a finite number > 0; '
                f'got {self.diagnostics_period_seconds}', 'diagnostics_period_seconds',
            )
        self.scan_config()  # building it checks the scan_* values
        if self.scan_frame_id.startswith('/'):
            # tf2 refuses such a frame ('frame_ids cannot start with a /'): no costmap could
            # place the scan.
            raise ConfigError(
                f"scan_frame_id must not start with '/' (tf2 refuses such frames); got "
                f'{self.scan_frame_id!r}', 'scan_frame_id',
            )
        if not 1 <= self.overlay_jpeg_quality <= 100:
            raise ConfigError(
                f'overlay_jpeg_quality must be in [1, 100]; got {self.overlay_jpeg_quality}',
                'overlay_jpeg_quality',
            )
        for name in ('compressed_depth_max', 'compressed_depth_quantization'):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f'{name} must be a finite number > 0; got {value}', name)
        if self.depth_encoding == '32FC1':
            # A pair float32 cannot hold in the header would drop every frame once a
            # compressedDepth subscriber came: refused here, at start-up.
            import numpy as np

            from cva_confidence_ros.ros.transport import compressed_depth_values

            try:
                compressed_depth_values(
                    np.zeros((1, 1), np.float32),
                    self.compressed_depth_max,
                    self.compressed_depth_quantization,
                )
            except InputError as error:
                raise ConfigError(
                    f'compressed_depth_quantization and compressed_depth_max: {error}',
                    'compressed_depth_quantization', 'compressed_depth_max',
                ) from None
        if not 0 <= self.compressed_depth_png_level <= 9:
            raise ConfigError(
                'compressed_depth_png_level must be in [0, 9]; '
                f'got {self.compressed_depth_png_level}', 'compressed_depth_png_level',
            )

    def scan_config(self) -> ScanConfig:
        """The ``scan_*`` parameters as a :class:`~cva_confidence_ros.scan.ScanConfig`.

        Raises:
            ConfigError: A band, range or pitch that the scan cannot take.
        """
        return ScanConfig(**{f.name: getattr(self, f'scan_{f.name}') for f in fields(ScanConfig)})

    @property
    def min_period_ns(self) -> int:
        """The smallest stamp spacing of the frames taken under ``max_rate_hz`` (0 = none):
        98 % of the period, so that a camera at exactly the limit is not halved by jitter."""
        return 0 if self.max_rate_hz == 0 else round(0.98e9 / self.max_rate_hz)

    @property
    def tolerance_ns(self) -> int:
        """The approximate-sync tolerance in integer nanoseconds."""
        return round(self.approximate_sync_tolerance_seconds * 1e9)


@dataclass(frozen=True)
class ParamSpec:
    """One declared parameter.

    Attributes:
        name: Parameter name, equal to the config field it maps onto.
        target: ``'pipeline'`` or ``'node'``: which config holds the field.
        default: Default value; its Python type fixes the parameter type.
        description: What it does, for ``ros2 param describe``.
        constraints: Free text on allowed values (choices), for ``ros2 param describe``.
        low: Lower end of the allowed range (int or float parameters), or None.
        high: Upper end of the allowed range, or None.
        read_only: Only settable at start-up (e.g. QoS, which is fixed per subscription).
    """

    name: str
    target: str
    default: Any
    description: str
    constraints: str = ''
    low: float | None = None
    high: float | None = None
    read_only: bool = False

    def descriptor(self) -> ParameterDescriptor:
        """The ``ParameterDescriptor`` with type, description, range and read-only flag."""
        descriptor = ParameterDescriptor(
            name=self.name,
            type=_parameter_type(self.default),
            description=self.description,
            additional_constraints=self.constraints,
            read_only=self.read_only,
            # A double also takes an integer literal (-p max_rate_hz:=2, a YAML 1), which
            # ROS 2 types as an integer and would refuse; double_value checks and converts it.
            dynamic_typing=isinstance(self.default, float),
        )
        if self.low is not None and self.high is not None:
            if isinstance(self.default, int) and not isinstance(self.default, bool):
                descriptor.integer_range = [
                    IntegerRange(from_value=int(self.low), to_value=int(self.high), step=1)
                ]
            else:
                descriptor.floating_point_range = [
                    FloatingPointRange(
                        from_value=float(self.low), to_value=float(self.high), step=0.0
                    )
                ]
        return descriptor


def _parameter_type(value: Any) -> int:
    if isinstance(value, bool):
        return ParameterType.PARAMETER_BOOL
    if isinstance(value, int):
        return ParameterType.PARAMETER_INTEGER
    if isinstance(value, float):
        return ParameterType.PARAMETER_DOUBLE
    return ParameterType.PARAMETER_STRING


def _default(config: type, name: str) -> Any:
    for item in fields(config):
        if item.name == name:
            if item.default is MISSING:
                raise ConfigError(f'{config.__name__}.{name} has no default')
            return item.default
    raise ConfigError(f'{config.__name__} has no field {name!r}')


def _pipeline(name: str, description: str, **extra: Any) -> ParamSpec:
    return ParamSpec(name, 'pipeline', _default(PipelineConfig, name), description, **extra)


def _node(name: str, description: str, **extra: Any) -> ParamSpec:
    return ParamSpec(name, 'node', _default(NodeConfig, name), description, **extra)


PIPELINE_PARAMETERS: tuple[ParamSpec, ...] = (
    _pipeline(
        'matcher',
        'Cost-volume matcher.',
        constraints='one of census_bm, census_sgm, mccnn_fast',
    ),
    _pipeline(
        'max_disparity',
        'Cost-volume depth D (disparities 0 … D−1) at the processed resolution.',
        low=1,
        high=1024,
    ),
    _pipeline(
        'confidence_method',
        'Confidence method: cva_net, cva_net_lite or cva_net_fast (learned cost-volume '
        'networks), a learned baseline or a hand-crafted measure.',
        constraints='cva_net, cva_net_lite, cva_net_fast, a learned baseline (ccnn, lfn, '
        'lgc_net) or a hand-crafted measure (pkrn, mlm, lrd, lrc, score)',
    ),
    _pipeline(
        'model_path',
        'Weights file of the learned method; empty = the shipped weights for the matcher and '
        'max_disparity.',
    ),
    _pipeline(
        'device',
        'Where the network runs; auto = CUDA when available.',
        constraints='one of cpu, cuda, auto',
    ),
    _pipeline(
        'confidence_threshold',
        'Pixels with confidence below it are dropped from points2, depth, scan, '
        'disparity_filtered and the overlay.',
        low=0.0,
        high=1.0,
    ),
    _pipeline(
        'downsample',
        'Process and publish at 1/downsample of the input resolution (camera infos scaled).',
        constraints='1, 2 or 4',
        low=1,
        high=4,
    ),
    _pipeline('lr_check', 'Invalidate pixels that fail a left-right consistency check.'),
    _pipeline(
        'subpixel',
        'Sub-pixel disparity: the curve through the costs around the winner-takes-all minimum '
        '(equiangular, parabola); none = integer disparities (depth in layers).',
        constraints='one of equiangular, parabola, none',
    ),
    _pipeline(
        'speckle_size',
        'Speckle filter: kept pixels in a connected region of at most this many pixels '
        '(4-neighbours whose disparities differ by at most speckle_range) are dropped from '
        'points2, depth and disparity_filtered too; 0 = off.',
        low=0,
        high=1000000,
    ),
    _pipeline(
        'speckle_range',
        'Largest disparity step between neighbouring pixels of one speckle-filter region, in '
        'pixels at the processed resolution.',
        low=0.0,
        high=1024.0,
    ),
    _pipeline(
        'tile_budget_mb',
        'Memory budget of one network tile at inference, MB.',
        low=1.0,
        high=1048576.0,
    ),
    _pipeline(
        'cva_stride',
        'CVA-Net on every stride-th pixel per axis, the rest filled by joint-bilateral '
        'interpolation guided by image and disparity; 1 = every pixel (exact).',
        constraints='1, 2, 4 or 8',
        low=1,
        high=8,
    ),
    _pipeline(
        'cva_cascade',
        'Cheap measure that decides the pixels it is sure of before CVA-Net; none = no cascade '
        '(lrd also computes the right-view cost volume).',
        constraints='one of none, pkrn, lrd',
    ),
    _pipeline(
        'cva_cascade_fraction',
        'Share of the pixels the cascade leaves to CVA-Net (the least confident by its measure).',
        low=0.01,
        high=1.0,
    ),
    _pipeline(
        'cva_precision',
        'Arithmetic of CVA-Net: fp32, bf16 (autocast) or fp16 (CUDA only).',
        constraints='one of fp32, bf16, fp16',
    ),
    _pipeline(
        'cva_backend',
        'Runtime of the cost-volume networks (cva_net, cva_net_lite, cva_net_fast): torch, or '
        'onnxruntime (exported to ONNX at start, run by ONNX Runtime on the CPU, float32).',
        constraints='one of torch, onnxruntime',
    ),
    _pipeline(
        'roi_top',
        'Share of the image height, from the top, that is not processed (sky, a ceiling out of '
        'range); smaller than roi_bottom. Time scales with roi_bottom - roi_top; outside, '
        'nothing is kept (disparity invalid, confidence 0).',
        low=0.0,
        high=1.0,
    ),
    _pipeline(
        'roi_bottom',
        "Share of the image height at which processing stops (the robot's own hood or bumper "
        'below it); 1 = to the last row.',
        low=0.0,
        high=1.0,
    ),
    _pipeline(
        'mask_path',
        "Ignore mask: an image of the input size, black where the camera sees the robot's own "
        'body (nothing published there; rows black from edge to edge at the top and bottom '
        "are not processed); '' = none.",
    ),
)

NODE_PARAMETERS: tuple[ParamSpec, ...] = (
    _node('publish_points', 'Publish the confidence-filtered point cloud on points2.'),
    _node(
        'points_organized',
        'points2 keeps the image grid with NaN for dropped points; false = only kept points.',
    ),
    _node(
        'points_confidence',
        'points2 holds every point that can be triangulated with a float32 confidence field, '
        'for consumers that filter with their own threshold (cloud_filter; no speckle filter '
        'then); false = only the kept points (confidence >= confidence_threshold, not in a '
        'speckle), x y z rgb as stereo_image_proc.',
    ),
    _node(
        'publish_depth',
        'Publish depth: the depth of the kept pixels (confidence >= confidence_threshold, not '
        'in a speckle) in the left camera frame (REP 118), for depth-image consumers; pair it '
        'with camera_info.',
    ),
    _node(
        'depth_encoding',
        'Encoding of depth: 32FC1 (float metres, NaN = no depth) or 16UC1 (uint16 millimetres, '
        '0 = no depth, at most 65.535 m).',
        constraints='32FC1 or 16UC1',
    ),
    _node(
        'image_transport',
        'How the images arrive: raw (sensor_msgs/Image on left/image_rect, right/image_rect) or '
        'compressed (sensor_msgs/CompressedImage, JPEG or PNG, on left/image_rect/compressed, '
        'right/image_rect/compressed, as image_transport publishes them).',
        constraints='raw or compressed',
        read_only=True,
    ),
    _node(
        'input_qos',
        'QoS of the image and camera-info subscriptions.',
        constraints='sensor_data (best effort) or reliable',
        read_only=True,
    ),
    _node(
        'output_qos',
        'QoS of the published topics; reliable also serves best-effort subscribers.',
        constraints='sensor_data (best effort) or reliable',
        read_only=True,
    ),
    _node('approximate_sync', 'Pair messages with close, not only equal, stamps.'),
    _node(
        'approximate_sync_tolerance_seconds',
        'Largest stamp difference within one pair when approximate_sync is true, seconds.',
        low=0.0,
        high=10.0,
    ),
    _node(
        'queue_size',
        'Messages held per topic while waiting for their partners.',
        low=1,
        high=1000,
    ),
    _node(
        'diagnostics_period_seconds',
        'Period of the /diagnostics status and of the throttled status log, seconds.',
        low=0.01,
        high=3600.0,
        read_only=True,
    ),
    _node(
        'max_rate_hz',
        'Process at most this many frames per second of input (stamp) time; the frames in '
        'between are skipped (frames_throttled in /diagnostics), leaving the CPU to the rest '
        'of the robot; 0 = every frame the node can.',
        low=0.0,
        high=1000.0,
    ),
    _node(
        'min_kept_fraction',
        '/diagnostics warns when the share of pixels kept (valid disparity, confidence >= '
        'confidence_threshold, not in a speckle), averaged over a diagnostics period, falls '
        'below it: a blinded or covered camera, a texture-less view, a broken calibration; '
        '0 = never.',
        low=0.0,
        high=1.0,
    ),
    _node(
        'max_expected_kept_error',
        '/diagnostics warns when the error rate the confidence predicts for the kept pixels '
        '(mean of 1 - confidence over them, averaged over a diagnostics period; the networks '
        'only, whose confidence is a probability) rises above it: blur, fog, a rectification '
        'gone wrong; 1 = never.',
        low=0.0,
        high=1.0,
    ),
    _node(
        'publish_scan',
        'Publish scan: a sensor_msgs/LaserScan of the kept pixels (confidence >= '
        'confidence_threshold, not in a speckle) in a height band, for obstacle layers (Nav2 '
        'costmaps); each beam the nearest point, its confidence as intensity; NaN = no kept '
        'pixel (unknown, not free), +inf = all beyond scan_range_max (REP 117).',
    ),
    _node(
        'scan_frame_id',
        "Frame of scan, which needs x forward and z up; '' = the camera's body frame named "
        'after the left optical frame (<name>_optical_frame -> <name>_frame, <name>_optical '
        '-> <name>).',
    ),
    _node(
        'scan_min_height',
        'Lowest point taken into scan, metres above the left camera (negative = below), '
        'measured in the level frame of scan_pitch.',
        low=-1000.0,
        high=1000.0,
    ),
    _node(
        'scan_max_height',
        'Highest point taken into scan, metres above the left camera (> scan_min_height).',
        low=-1000.0,
        high=1000.0,
    ),
    _node('scan_range_min', 'Nearest range of scan, metres.', low=0.0, high=1e6),
    _node(
        'scan_range_max',
        'Farthest range of scan, metres (> scan_range_min).',
        low=0.0,
        high=1e6,
    ),
    _node(
        'scan_pitch',
        'How far the camera looks down from level, radians (negative = up): heights and '
        'ranges of scan are measured level.',
        low=-1.57,
        high=1.57,
    ),
    _node(
        'overlay_jpeg_quality',
        'JPEG quality of confidence_overlay/compressed (image_transport compressed, encoded '
        'only while subscribed), 1-100.',
        low=1,
        high=100,
    ),
    _node(
        'compressed_depth_max',
        'Largest depth on depth/compressedDepth (image_transport compressedDepth, encoded only '
        'while subscribed), metres: deeper pixels travel as no depth (its depth_max).',
        low=0.001,
        high=1e6,
    ),
    _node(
        'compressed_depth_quantization',
        'Inverse-depth quantisation of a 32FC1 depth/compressedDepth (its depth_quantization): '
        'depth error about depth^2 / (q * (q + 1)) metres.',
        low=0.001,
        high=1e6,
    ),
    _node(
        'compressed_depth_png_level',
        'zlib level of the depth/compressedDepth PNG, 0-9 (its png_level; image_transport '
        'defaults to 9, which takes about 11 times as long as 3 for 18 % fewer bytes).',
        low=0,
        high=9,
    ),
)

#: Every declared parameter, pipeline ones first.
PARAMETERS: tuple[ParamSpec, ...] = PIPELINE_PARAMETERS + NODE_PARAMETERS


def double_value(
    name: str, value: object, low: float | None = None, high: float | None = None
) -> float:
    """The value of a double parameter as a float.

    ROS 2 types ``-p name:=2`` or a YAML ``2`` as an integer; such a value is taken as the
    number it is. The parameters are declared with dynamic typing for that, so rclpy checks
    neither their type nor their range: this does.

    Raises:
        ConfigError: Not a number (a string, a bool, an array), NaN, or outside
            [``low``, ``high``]; ``fields`` is ``(name,)``.
    """
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f'{name} must be a number; got {value!r}', name)
    number = float(value)
    if math.isnan(number) or (low is not None and number < low) or (
        high is not None and number > high
    ):
        bounds = f'[{low:g}, {high:g}]' if low is not None and high is not None else 'range'
        raise ConfigError(f'{name} must be a number in {bounds}; got {value!r}', name)
    return number


def scan_parameters(config: ScanConfig) -> dict[str, Any]:
    """The ``scan_*`` fields of :class:`NodeConfig` for ``config`` (the inverse of
    :meth:`NodeConfig.scan_config`)."""
    return {f'scan_{f.name}': getattr(config, f.name) for f in fields(config)}


def check_declared_ranges(values: Mapping[str, Any]) -> None:
    """Refuse values outside the ranges the node declares, before a node is started with
    them (``-p`` overrides outside its range end the node's start-up).

    Raises:
        ConfigError: The first value outside its range, named with the range (and in
            ``fields``).
    """
    for spec in PARAMETERS:
        value = values.get(spec.name)
        if spec.low is None or spec.high is None or isinstance(value, bool):
            continue
        if isinstance(value, (int, float)) and not spec.low <= value <= spec.high:
            raise ConfigError(
                f'{spec.name} must be in [{spec.low:g}, {spec.high:g}] (the range the node '
                f'declares); got {value!r}', spec.name,
            )


def declare_parameters(node: Node) -> None:
    """Declare every parameter of :data:`PARAMETERS` on ``node`` with its descriptor, and keep
    the double ones doubles (:func:`keep_doubles`)."""
    doubles = [spec.name for spec in PARAMETERS if isinstance(spec.default, float)]
    double_overrides(node, doubles)
    node.declare_parameters(
        namespace='',
        parameters=[(spec.name, spec.default, spec.descriptor()) for spec in PARAMETERS],
    )
    keep_doubles(node, doubles)


def double_overrides(node: Node, names: Iterable[str]) -> None:
    """Turn start-up values of the double parameters ``names`` given as whole numbers
    (``-p diagnostics_period_seconds:=2``, an integer to rcl) into doubles; call it before
    declaring them. Read-only ones would otherwise stay integers for good (nothing may set
    them after the declaration), and ``ros2 param describe`` would say so.

    rclpy keeps the start-up values in ``Node._parameter_overrides`` and offers no public
    way to them; without that attribute this does nothing (:func:`keep_doubles` still
    converts the settable ones).
    """
    overrides = getattr(node, '_parameter_overrides', None)
    if not isinstance(overrides, dict):
        return
    for name in names:
        given = overrides.get(name)
        if isinstance(given, Parameter) and given.type_ == Parameter.Type.INTEGER:
            overrides[name] = Parameter(name, Parameter.Type.DOUBLE, float(given.value))


def keep_doubles(node: Node, names: Iterable[str]) -> None:
    """Keep the double parameters ``names`` (declared with dynamic typing, see
    :meth:`ParamSpec.descriptor`) doubles in what ``ros2 param describe`` and ``get`` say.

    A whole number given at start-up (``-p max_rate_hz:=2``) or later is stored as the double
    it stands for (a pre-set callback; read-only ones by :func:`double_overrides` before
    the declaration, since rclpy lets nothing change them after it). Call
    :func:`restore_types` when the on-set callback refuses a change: rclpy retypes a
    dynamically typed parameter to the value offered before the callback runs, refused or
    not (a refused ``max_rate_hz abc`` left it a string parameter).

    rclpy checks the parameters of one change in turn and stops at the first it refuses (out of
    range, wrong type, read-only), before any on-set callback, after retyping the ones it passed:
    an atomic ``max_rate_hz abc`` + ``queue_size 0`` left max_rate_hz described as a string. So
    the changes rclpy retypes without a check of their own (a settable double offered as
    anything but a double) go last: rclpy refuses before them, or passes them on to the on-set
    callback, which refuses them and calls :func:`restore_types`.
    """
    doubles = frozenset(names)
    settable = frozenset(name for name in doubles if not node.describe_parameter(name).read_only)

    def as_doubles(params: list[Parameter]) -> list[Parameter]:
        converted = [
            Parameter(p.name, Parameter.Type.DOUBLE, float(p.value))
            if p.name in doubles and p.type_ == Parameter.Type.INTEGER else p
            for p in params
        ]
        return sorted(  # stable: the order of the rest is kept
            converted, key=lambda p: p.name in settable and p.type_ != Parameter.Type.DOUBLE
        )

    node.add_pre_set_parameters_callback(as_doubles)
    whole = [
        node.get_parameter(name) for name in sorted(settable)
        if node.get_parameter(name).type_ == Parameter.Type.INTEGER
    ]
    if whole:
        node.set_parameters(whole)  # before any on-set callback: converted by as_doubles


def restore_types(node: Node, params: Iterable[Parameter]) -> None:
    """Type the descriptors of ``params`` by the values kept, after a refused change (see
    :func:`keep_doubles`)."""
    for param in params:
        if node.has_parameter(param.name):
            descriptor = node.describe_parameter(param.name)
            if descriptor.dynamic_typing:
                descriptor.type = node.get_parameter(param.name).type_.value


def parameter_values(node: Node) -> dict[str, Any]:
    """Current values of the declared parameters, by name."""
    return {spec.name: node.get_parameter(spec.name).value for spec in PARAMETERS}


def build_configs(
    values: Mapping[str, Any], changes: Iterable[Parameter] = ()
) -> tuple[PipelineConfig, NodeConfig]:
    """Build both configs from parameter values, with pending ``changes`` applied on top.

    Args:
        values: name → value for every parameter of :data:`PARAMETERS`.
        changes: Parameters about to be set (from an on-set-parameters callback).

    Returns:
        ``(pipeline_config, node_config)``, both validated.

    Raises:
        ConfigError: An unknown parameter name or a value the configs reject.
    """
    merged = dict(values)
    known = {spec.name for spec in PARAMETERS}
    for param in changes:
        if param.name not in known:
            raise ConfigError(f'unknown parameter {param.name!r}; expected one of {sorted(known)}')
        merged[param.name] = param.value
    for spec in PARAMETERS:
        if isinstance(spec.default, float):
            merged[spec.name] = double_value(spec.name, merged[spec.name], spec.low, spec.high)
    pipeline = {spec.name: merged[spec.name] for spec in PIPELINE_PARAMETERS}
    node = {spec.name: merged[spec.name] for spec in NODE_PARAMETERS}
    return PipelineConfig(**pipeline), NodeConfig(**node)


def change_fault(values: Mapping[str, Any], changes: Iterable[Parameter]) -> ConfigError | None:
    """The fault of ``changes`` themselves on top of ``values``, or None.

    For a node that is not configured (the managed one before ``configure``), whose values may
    already hold faults: start-up values are only checked at ``configure``. A fault that names
    none of the changed parameters is such an earlier one; it is taken at its parameters'
    defaults for the check, so that faults in two parameters can be fixed one ``param set`` at a
    time (each used to be refused for the other's fault, and only a restart got out).

    Raises:
        ConfigError: An unknown parameter name (as :func:`build_configs`).
    """
    changes = list(changes)
    changed = {param.name for param in changes}
    defaults = {spec.name: spec.default for spec in PARAMETERS}
    merged = dict(values)
    for _ in range(len(PARAMETERS) + 1):
        try:
            build_configs(merged, changes)
        except ConfigError as error:
            earlier = [name for name in error.fields if name in defaults and name not in changed]
            if not earlier or len(earlier) < len(error.fields):
                return error  # the changes' own fault (or one naming no parameter)
            merged.update((name, defaults[name]) for name in earlier)
            continue
        return None
    return None

"""A laser scan of the confident pixels: the ROS-free half of the node's ``scan`` output.

Mobile robots feed obstacle layers (Nav2's costmap, slam) with ``sensor_msgs/LaserScan``;
``depthimage_to_laserscan`` and ``pointcloud_to_laserscan`` turn a depth camera into one. A
wrong disparity there is a phantom obstacle that stops the robot or a wall it does not see,
so this scan is built only from the pixels the node keeps (finite disparity, confidence ≥
threshold, not in a speckle), and each beam carries the confidence of its point.

Geometry (left camera frame x right, y down, z forward; :mod:`.pointcloud`): every kept pixel
is triangulated, turned by ``pitch`` (the camera looking down by that angle) into a level
frame, and kept if its height above the camera, ``−y_level``, lies in ``[min_height,
max_height]``. Its beam is the bearing ``atan2(−x, z_level)`` (counter-clockwise from forward,
REP 103 for a frame with x forward, y left, z up), its range the horizontal distance
``√(x² + z_level²)``. Beams are spaced evenly between the extreme bearings of the image's
pixels (for a level camera the last and first column's centres; pitched, the corners nearer
the ground see wider), ``1 / fx`` radians or a little more apart: one per column at the image
centre, where columns are farthest apart in bearing, so no beam there falls between two columns (an
increment of the mean column spacing would leave some centre beams empty on a wide lens: every
fifth or so at 90° of view); each beam takes its nearest point. That holds for a level camera:
pitched, the rows whose rays point most steeply (the bottom ones of a camera looking down) see
their columns farther apart in bearing, ``1 / (fx · f)`` at the centre (``f`` the ray's forward
part, :func:`bearing_range`), so a thin height band that only such rows reach can leave some
beams between two columns NaN (a 1 cm band 1 m below a camera pitched down 0.4 rad, fx 300: 9
of the 523 beams across a wall).

Beams follow REP 117: a range where the nearest point lies in ``[range_min, range_max]``;
``+inf`` where the kept points in the band all lie beyond ``range_max`` (nothing within range);
``−inf`` where none lies in range and one or more lie closer than ``range_min`` (too close,
whatever lies beyond ``range_max``); NaN where no kept point
of the band falls in the beam at all (no measurement: the camera saw nothing it trusts there,
or only above or below the band, which is not free space — consumers should not clear along
it).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
import math

import numpy as np

from cva_confidence_ros.checks import is_real
from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.pointcloud import StereoGeometry, _check_disparity, _confidence_fraction

__all__ = [
    'Scan',
    'ScanConfig',
    'ScanScore',
    'bearing_range',
    'disparity_to_scan',
    'scan_frame_id',
    'score_scan',
]


def bearing_range(
    geometry: StereoGeometry, width: int, height: int, pitch: float = 0.0
) -> tuple[float, float]:
    """Smallest and largest bearing (radians, counter-clockwise from forward) of a pixel of a
    ``width × height`` image seen by a camera looking down by ``pitch``.

    A pixel's points all lie on its ray, so they share its bearing ``atan2(cx − u,
    fx · f)``, where ``f = cos(pitch) − (v − cy) / fy · sin(pitch)`` is the ray's forward
    part in the level frame. The bearing grows with the column's distance from ``cx`` and as
    ``f`` shrinks, so the extremes are at the image corners: for a level camera the last and
    first column's centres; pitched down, the bottom corners, wider. A ray that does not
    point forward (``f ≤ 0``: a steep pitch) bounds the range at ±π/2, since no point behind
    the camera is taken.
    """
    sin_p, cos_p = math.sin(pitch), math.cos(pitch)
    bearings = []
    for u in (0, width - 1):
        for v in (0, height - 1):
            forward = cos_p - (v - geometry.cy) / geometry.fy * sin_p
            bearings.append(math.atan2(geometry.cx - u, geometry.fx * max(forward, 1e-12)))
    return min(bearings), max(bearings)


@dataclass(frozen=True)
class ScanConfig:
    """Which points make the scan (metres and radians, like ``pointcloud_to_laserscan``).

    The node's parameters are these names with ``scan_`` in front (``scan_min_height``, …);
    errors name the values by them (in the message and :attr:`ConfigError.fields`).

    Attributes:
        min_height: Lowest point taken, metres above the camera's centre (negative = below).
        max_height: Highest point taken (> ``min_height``).
        range_min: Nearest range reported (≥ 0); nearer points make a beam ``−inf`` only when
            nothing in range is behind them.
        range_max: Farthest range reported (> ``range_min``, finite).
        pitch: How far the camera looks down from level, radians (negative = up), in
            (−π/2, π/2): heights and ranges are measured in the level frame.
    """

    min_height: float = -0.25
    max_height: float = 0.25
    range_min: float = 0.1
    range_max: float = 20.0
    pitch: float = 0.0

    def __post_init__(self) -> None:
        for field in fields(self):
            value = getattr(self, field.name)
            if not is_real(value) or not math.isfinite(value):
                raise ConfigError(
                    f'scan_{field.name} must be a finite number; '
                    f'got {type(value).__name__} {value!r}', f'scan_{field.name}',
                )
        if not self.min_height < self.max_height:
            raise ConfigError(
                f'scan_min_height must be < scan_max_height; got {self.min_height} and '
                f'{self.max_height}', 'scan_min_height', 'scan_max_height',
            )
        if not 0.0 <= self.range_min < self.range_max:
            raise ConfigError(
                f'scan ranges must satisfy 0 <= scan_range_min < scan_range_max; got '
                f'{self.range_min} and {self.range_max}', 'scan_range_min', 'scan_range_max',
            )
        if not abs(self.pitch) < math.pi / 2:
            raise ConfigError(
                f'scan_pitch must be in (-pi/2, pi/2) radians; got {self.pitch}', 'scan_pitch'
            )


@dataclass(frozen=True)
class Scan:
    """One scan, the fields of ``sensor_msgs/LaserScan`` that depend on the image.

    Attributes:
        ranges: (N,) float32, metres; NaN / ±inf as the module says (REP 117).
        intensities: (N,) float32, the confidence of each beam's point in [0, 1]; 0 where the
            range is not finite.
        angle_min: Bearing of beam 0 (the centre of the last image column for a level
            camera; see :func:`bearing_range`), radians.
        angle_max: Bearing of beam N − 1 (the centre of the first column, likewise).
        angle_increment: ``(angle_max − angle_min) / (N − 1)`` (> 0).
        range_min: From the config.
        range_max: From the config.
    """

    ranges: np.ndarray
    intensities: np.ndarray
    angle_min: float
    angle_max: float
    angle_increment: float
    range_min: float
    range_max: float


def disparity_to_scan(
    disparity: np.ndarray,
    geometry: StereoGeometry,
    mask: np.ndarray | None = None,
    confidence: np.ndarray | None = None,
    config: ScanConfig | None = None,
) -> Scan:
    """The laser scan of a left-reference disparity map's kept pixels.

    Args:
        disparity: (H, W) real array, raw disparity ``x_left − x_right`` in pixels; NaN =
            invalid.
        geometry: Intrinsics at the disparity map's resolution.
        mask: Optional (H, W) bool, True = keep (the node passes ``PipelineResult.valid``).
        confidence: Optional (H, W) real array in [0, 1], the beams' intensities (clipped to
            it, NaN = 0; an integer array is a fraction of its type's full scale, uint8 255 =
            1, as :func:`~cva_confidence_ros.pointcloud.filter_cloud` reads it); None = 0.
        config: Height band, ranges and pitch; None = :class:`ScanConfig` defaults.

    Returns:
        A :class:`Scan`, ``floor(fx · (angle_max − angle_min)) + 1`` beams (at least 2)
        between the extreme bearings of :func:`bearing_range` (≤ W for a level camera; a
        pitched one sees wider at the bottom (or top) corners, and its scan has more beams).

    Raises:
        InputError: ``disparity``, ``geometry`` or ``mask`` as
            :func:`~cva_confidence_ros.pointcloud.disparity_to_points` says, a ``confidence``
            of another shape, or an image narrower than 2 columns or without a row.
        ConfigError: ``config`` is not a :class:`ScanConfig`.
    """
    disparity, mask = _check_disparity(disparity, geometry, mask)
    config = ScanConfig() if config is None else config
    if not isinstance(config, ScanConfig):
        raise ConfigError(f'config must be a ScanConfig; got {type(config).__name__}')
    height, width = disparity.shape
    if width < 2 or height < 1:
        # A 0-row image used to give a scan of NaN beams, its bearings taken at row −1.
        raise InputError(
            f'a scan needs an image at least 2 columns wide and 1 row high; got {width}×{height}'
        )
    if confidence is None:
        confidence = np.zeros(disparity.shape, np.float32)
    else:
        confidence = np.asarray(confidence)
        if confidence.shape != disparity.shape or confidence.dtype.kind not in 'fiu':
            raise InputError(
                f'confidence must be a real array of the disparity shape {disparity.shape}; '
                f'got {confidence.dtype} {confidence.shape}'
            )
        confidence = _confidence_fraction(confidence)
    keep = np.ones(disparity.shape, np.bool_) if mask is None else mask
    # Beam 0 looks right of the last column: bearings grow to the left (counter-clockwise).
    angle_min, angle_max = bearing_range(geometry, width, height, config.pitch)
    beams = max(2, int(math.floor((angle_max - angle_min) * geometry.fx)) + 1)
    increment = (angle_max - angle_min) / (beams - 1)
    params = np.array(
        [
            geometry.fx, geometry.fy, geometry.cx, geometry.cy, geometry.disparity_offset,
            geometry.fx * geometry.baseline, math.sin(config.pitch), math.cos(config.pitch),
            config.min_height, config.max_height, config.range_min, config.range_max,
            angle_min, 1.0 / increment,
        ],
        dtype=np.float64,
    )
    from cva_confidence_ros._scan_kernel import scan_kernel  # numba: not for --help's imports

    best = np.full(beams, np.inf)
    intensity = np.zeros(beams, np.float32)
    state = np.zeros(beams, np.uint8)
    scan_kernel(
        np.ascontiguousarray(disparity, dtype=np.float32),
        np.ascontiguousarray(keep),
        np.ascontiguousarray(confidence, dtype=np.float32),
        params, best, intensity, state,
    )
    ranges = np.full(beams, np.nan, np.float32)
    ranges[state == 1] = np.inf
    ranges[state == 2] = -np.inf
    ranges[state == 3] = best[state == 3]
    intensity[state != 3] = 0.0
    return Scan(
        ranges=ranges,
        intensities=np.clip(np.nan_to_num(intensity, nan=0.0), 0.0, 1.0),
        angle_min=angle_min,
        angle_max=angle_max,
        angle_increment=increment,
        range_min=float(config.range_min),
        range_max=float(config.range_max),
    )


@dataclass(frozen=True)
class ScanScore:
    """How a scan's beams compare with a reference scan (the ground truth's).

    Attributes:
        beams: Beams where the reference has a return in range (the ones scored).
        phantom: Of those, beams whose range is wrong and nearer than the reference (an
            obstacle that is not there), ``−inf`` (too close) included.
        far: Beams whose range is wrong and farther (the nearest thing missed), ``+inf``
            (nothing within range) included.
        none: Beams with no return at all (NaN: nothing kept there).
    """

    beams: int
    phantom: int
    far: int
    none: int

    def rate(self, outcome: str) -> float | None:
        """``phantom``, ``far`` or ``none`` as a share of :attr:`beams` (None without beams)."""
        return getattr(self, outcome) / self.beams if self.beams else None


def score_scan(
    estimate: Scan, truth: Scan, geometry: StereoGeometry, config: ScanConfig | None = None
) -> ScanScore:
    """Score the beams of ``estimate`` against ``truth`` by the KITTI criterion in disparity.

    A beam is scored where ``truth`` has a finite range. Both ranges are turned back into
    disparities along the beam's bearing θ: the point's depth in the camera is
    ``r·cos θ·cos(pitch) − h·sin(pitch)`` with its height h taken at the band's centre (exact
    for ``pitch`` 0, and off by ``(h − centre)·sin(pitch)`` otherwise); a beam is wrong when the
    two disparities differ by ≥ 3 px and ≥ 5 % of the true one.

    Args:
        estimate: The scan to judge (e.g. of the node's kept pixels that have ground truth).
        truth: The scan of the ground-truth disparity over the same pixels, same config.
        geometry: Intrinsics at the disparity maps' resolution.
        config: The config both scans were made with (pitch and band); None = defaults.

    Raises:
        InputError: Scans with different beams, a scan that is not a :class:`Scan`, or a
            ``geometry`` that is not a :class:`StereoGeometry`.
        ConfigError: ``config`` is not a :class:`ScanConfig`.
    """
    for name, scan in (('estimate', estimate), ('truth', truth)):
        if not isinstance(scan, Scan):
            raise InputError(f'{name} must be a Scan; got {type(scan).__name__}')
    if not isinstance(geometry, StereoGeometry):
        raise InputError(f'geometry must be a StereoGeometry; got {type(geometry).__name__}')
    config = ScanConfig() if config is None else config
    if not isinstance(config, ScanConfig):
        raise ConfigError(f'config must be a ScanConfig; got {type(config).__name__}')
    if (estimate.ranges.shape != truth.ranges.shape
            or not math.isclose(estimate.angle_min, truth.angle_min, abs_tol=1e-9)
            or not math.isclose(estimate.angle_increment, truth.angle_increment, abs_tol=1e-9)):
        raise InputError(
            f'scans with different beams cannot be compared: {estimate.ranges.size} beams from '
            f'{estimate.angle_min:.6f} rad against {truth.ranges.size} from '
            f'{truth.angle_min:.6f} rad'
        )
    bearing = truth.angle_min + truth.angle_increment * np.arange(truth.ranges.size)
    centre = 0.5 * (config.min_height + config.max_height)

    def disparity(ranges: np.ndarray) -> np.ndarray:
        with np.errstate(divide='ignore', invalid='ignore', over='ignore'):
            depth = (ranges.astype(np.float64) * np.cos(bearing) * math.cos(config.pitch)
                     - centre * math.sin(config.pitch))
            return geometry.fx * geometry.baseline / depth - geometry.disparity_offset

    scored = np.isfinite(truth.ranges)
    got = estimate.ranges
    d_true, d_est = disparity(truth.ranges), disparity(got)
    off = np.abs(d_est - d_true)
    with np.errstate(invalid='ignore'):
        wrong_near = np.isfinite(got) & (off >= 3.0) & (off >= 0.05 * d_true) & (d_est > d_true)
        wrong_far = np.isfinite(got) & (off >= 3.0) & (off >= 0.05 * d_true) & (d_est < d_true)
    phantom = scored & (wrong_near | (got == -np.inf))
    far = scored & (wrong_far | (got == np.inf))
    return ScanScore(
        beams=int(scored.sum()),
        phantom=int(phantom.sum()),
        far=int(far.sum()),
        none=int((scored & np.isnan(got)).sum()),
    )


_OPTICAL_SUFFIXES = (('_optical_frame', '_frame'), ('_optical', ''))


def scan_frame_id(camera_frame: str, configured: str = '') -> str:
    """The frame of the scan: ``configured``, or the body frame beside the camera's optical one.

    A ``LaserScan`` turns about its frame's z axis with x forward (REP 103), an optical frame
    has z forward: the scan belongs in the camera's body frame. Drivers name the pair
    ``<name>_optical_frame`` / ``<name>_frame`` (ZED, RealSense's ``camera_color_*``) or
    ``<name>_optical`` / ``<name>``, so those suffixes are swapped; any other frame is returned
    as it is (the caller warns: set ``scan_frame_id``). The scan's bearings and ranges are
    level (``pitch`` taken out), so with a pitch other than 0 the body frame of a camera
    mounted at that pitch is tilted with it: name a level frame in ``scan_frame_id`` then.

    Args:
        camera_frame: ``header.frame_id`` of the left image.
        configured: The node's ``scan_frame_id``; non-empty wins.
    """
    if configured:
        return configured
    for suffix, replacement in _OPTICAL_SUFFIXES:
        if camera_frame.endswith(suffix) and len(camera_frame) > len(suffix):
            return camera_frame[: -len(suffix)] + replacement
    return camera_frame

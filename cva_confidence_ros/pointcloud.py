"""Disparity → depth, 3D points and colour packing: the ROS-free half of ``depth`` and ``points2``.

Geometry follows ``image_geometry.StereoCameraModel`` (what ``stereo_image_proc`` uses) for a
rectified pair with projection matrices ``P_left`` and ``P_right`` (3×4)::

    B  = −P_right[0, 3] / P_right[0, 0]            (baseline, world units)
    Δ  = cx_right − cx_left                        (principal-point offset, pixels)
    Z  = fx · B / (d + Δ)
    X  = (u − cx_left) · Z / fx
    Y  = (v − cy_left) · Z / fy

where ``d = x_left − x_right`` is the matcher's disparity at left pixel ``(v, u)``. Points with
``d + Δ ≤ 0`` lie at or beyond infinity and are invalid. ``image_geometry`` uses fx for Y as well;
fy is the same for a rectified pair, and the general form is kept here.

Colours are packed like ``stereo_image_proc``/PCL: the bits of ``0x00RRGGBB`` reinterpreted as a
float32 field called ``rgb``. A cloud may carry each point's confidence in a fifth float32 field,
``confidence`` (:data:`CLOUD_CONFIDENCE_DTYPE`), so that a consumer can choose its own threshold
(:func:`filter_cloud`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields

import numpy as np

from cva_confidence_ros.checks import is_real
from cva_confidence_ros.errors import ConfigError, InputError

__all__ = [
    'CLOUD_CONFIDENCE_DTYPE',
    'CLOUD_DTYPE',
    'StereoGeometry',
    'disparity_to_depth',
    'disparity_to_points',
    'filter_cloud',
    'make_cloud',
    'pack_rgb',
    'stereo_cloud',
    'unit_projection',
    'unpack_rgb',
]

#: One point as ``stereo_image_proc`` lays it out: x, y, z, rgb, all float32, 16 bytes.
CLOUD_DTYPE = np.dtype([('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('rgb', '<f4')])

#: :data:`CLOUD_DTYPE` and the point's confidence in [0, 1] as a fifth float32, 20 bytes.
CLOUD_CONFIDENCE_DTYPE = np.dtype(CLOUD_DTYPE.descr + [('confidence', '<f4')])

#: Largest relative difference between the left and right fx of a rectified pair (P[0, 0]).
FX_TOLERANCE = 1e-3

_FLOAT32_MAX = float(np.finfo(np.float32).max)


def _confidence_fraction(values: np.ndarray) -> np.ndarray:
    """Confidence values as fractions in [0, 1]: an integer array is read as a fraction of its
    type's full scale, like a ``mono8`` / ``mono16`` image (uint8 255 or uint16 65535 = 1, so a
    uint8 200 is 200 / 255 ≈ 0.78); a float array is returned as it is."""
    values = np.asarray(values)
    if values.dtype.kind in 'iu':
        return values.astype(np.float64) / float(np.iinfo(values.dtype).max)
    return values


def _projection(matrix: Sequence[float] | np.ndarray, name: str) -> np.ndarray:
    array = np.asarray(matrix, dtype=np.float64)
    if array.size != 12:
        raise InputError(f'{name} must be a 3×4 projection matrix (12 values); got {array.size}')
    # 12 values in another grid (a transposed 4×3 P) would be read row-major as garbage, and
    # refused, if at all, as a focal length ≤ 0.
    if array.shape != (3, 4) and array.squeeze().ndim != 1:
        raise InputError(
            f'{name} must be a 3×4 projection matrix or its 12 values in a row; got shape '
            f'{array.shape}'
        )
    array = array.reshape(3, 4)
    if not np.all(np.isfinite(array)):
        raise InputError(f'{name} must be finite; got {array.tolist()}')
    return array


def unit_projection(array: np.ndarray) -> np.ndarray:
    """A 3×4 projection P (or 3×3 intrinsics K) scaled to ``[2, 2] = 1`` where its third row
    is ``(0, 0, w, 0)`` (``(0, 0, w)``) with ``w > 0`` (homogeneous: ``w·P`` projects as P
    does, but fx, cx and Tx are read off it as its entries); any other as it is, for the
    caller's checks to name."""
    w = float(array[2, 2])
    if w > 0 and w != 1 and not np.delete(array[2], 2).any():
        return array / w
    return array


@dataclass(frozen=True)
class StereoGeometry:
    """Rectified stereo intrinsics at one resolution.

    Attributes:
        fx: Focal length along x of the rectified left camera, pixels (> 0).
        fy: Focal length along y, pixels (> 0).
        cx: Principal point x of the left camera, pixels.
        cy: Principal point y of the left camera, pixels.
        cx_right: Principal point x of the right camera, pixels.
        baseline: Distance between the camera centres, world units (> 0), the ``T`` of
            ``stereo_msgs/DisparityImage``.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    cx_right: float
    baseline: float

    def __post_init__(self) -> None:
        for field in fields(self):
            value = getattr(self, field.name)
            if not is_real(value):
                raise InputError(
                    f'stereo geometry field {field.name} must be a real number; '
                    f'got {type(value).__name__} {value!r}'
                )
        values = (self.fx, self.fy, self.cx, self.cy, self.cx_right, self.baseline)
        if not all(np.isfinite(values)):
            raise InputError(f'stereo geometry must be finite; got {self}')
        # The outputs are float32 (DisparityImage.f and .t, the points): a value or a depth
        # scale fx·B beyond float32 would publish inf.
        if not all(abs(value) < _FLOAT32_MAX for value in (*values, self.fx * self.baseline)):
            raise InputError(f'stereo geometry must fit float32 (fx·B included); got {self}')
        if self.fx <= 0 or self.fy <= 0:
            raise InputError(f'focal lengths must be > 0; got fx={self.fx}, fy={self.fy}')
        if self.baseline <= 0:
            raise InputError(
                f'baseline must be > 0 (P_right[0, 3] < 0 for a right camera); got {self.baseline}'
            )

    @classmethod
    def from_projections(
        cls,
        p_left: Sequence[float] | np.ndarray,
        p_right: Sequence[float] | np.ndarray,
    ) -> StereoGeometry:
        """Build from the two rectified projection matrices (``CameraInfo.p``).

        Args:
            p_left: 3×4 (or 12 values, row-major) projection matrix of the left camera.
            p_right: Same for the right camera; ``P_right[0, 3] − P_left[0, 3] = −fx · B``
                (``P_left[0, 3]`` is 0 where the left camera is the rectified frame's origin).

        P is homogeneous: one whose third row is ``(0, 0, w, 0)`` is read as ``P / w``.

        Raises:
            InputError: Wrong size or shape (a 4×3 P, say), non-finite values, a third row
                other than ``(0, 0, w > 0, 0)``, fx ≤ 0, or a baseline ≤ 0.
        """
        left = _projection(p_left, 'P_left')
        right = _projection(p_right, 'P_right')
        if right[0, 0] <= 0:
            raise InputError(f'P_right[0, 0] (fx) must be > 0; got {right[0, 0]}')
        if left[0, 0] <= 0 or left[1, 1] <= 0:  # (an unset P, all zeros) before its third row
            raise InputError(f'focal lengths must be > 0; got fx={left[0, 0]}, fy={left[1, 1]}')
        for name, matrix in (('P_left', left), ('P_right', right)):
            # Read as entries, a P of third row (0, 0, 2, 0) gave twice the depth; one with
            # other entries there is no rectified pinhole camera at all.
            row = matrix[2]
            if not (row[2] > 0 and row[0] == row[1] == row[3] == 0):
                raise InputError(
                    f'{name} must have the third row (0, 0, w, 0) of a rectified camera, '
                    f'w > 0 (1 as calibrated); got {row.tolist()}'
                )
        left, right = unit_projection(left), unit_projection(right)
        # Rectification gives both cameras one focal length; images with two are not a
        # rectified pair, and the baseline (read with the right fx) would be wrong too.
        if left[0, 0] > 0 and abs(right[0, 0] - left[0, 0]) > FX_TOLERANCE * left[0, 0]:
            raise InputError(
                f'left and right projection matrices must share fx (a rectified pair); got '
                f'P_left[0, 0] = {left[0, 0]:g} and P_right[0, 0] = {right[0, 0]:g}'
            )
        baseline = float((left[0, 3] - right[0, 3]) / right[0, 0])
        if not baseline > 0:
            # The message of __post_init__ names P_right[0, 3] alone: with the left camera
            # off the origin that one may well be < 0, as asked, for a baseline ≤ 0.
            raise InputError(
                f'baseline (P_left[0, 3] − P_right[0, 3]) / fx must be > 0 (Tx = −fx·x of '
                f'each camera: the right one right of the left one; left and right swapped?); '
                f'got P_left[0, 3] = {left[0, 3]:g} and P_right[0, 3] = {right[0, 3]:g}, '
                f'{baseline:g}'
            )
        return cls(
            fx=float(left[0, 0]),
            fy=float(left[1, 1]),
            cx=float(left[0, 2]),
            cy=float(left[1, 2]),
            cx_right=float(right[0, 2]),
            # Tx = −fx · (position of the camera along x in the rectified frame): the baseline
            # is their difference, which −Tx_right alone gives only for a left camera at the
            # origin (P_left[0, 3] = 0, the usual case).
            baseline=baseline,
        )

    @property
    def disparity_offset(self) -> float:
        """Δ = cx_right − cx_left, added to a raw disparity before triangulation (pixels)."""
        return self.cx_right - self.cx

    def scaled(self, factor: float, factor_y: float | None = None) -> StereoGeometry:
        """The geometry of the images resized by ``factor`` (e.g. 0.5 for half size).

        Pixel centres are kept aligned (the convention of ``cv2.resize``): a coordinate ``x``
        becomes ``(x + 0.5) · factor − 0.5``. The baseline does not change.

        Args:
            factor: New width / old width (> 0).
            factor_y: New height / old height (> 0); ``None`` = ``factor``. Differs from
                ``factor`` when a size does not divide evenly (e.g. 375 rows halved to 187).

        Raises:
            InputError: A factor that is not a real number, or one ≤ 0.
        """
        factor_y = factor if factor_y is None else factor_y
        for name, value in (('factor', factor), ('factor_y', factor_y)):
            if not is_real(value):
                raise InputError(
                    f'scale {name} must be a real number; got {type(value).__name__} {value!r}'
                )
        if not (factor > 0 and factor_y > 0):
            raise InputError(f'scale factors must be > 0; got {factor} and {factor_y}')

        def centre(value: float, scale: float) -> float:
            return (value + 0.5) * scale - 0.5

        return StereoGeometry(
            fx=self.fx * factor,
            fy=self.fy * factor_y,
            cx=centre(self.cx, factor),
            cy=centre(self.cy, factor_y),
            cx_right=centre(self.cx_right, factor),
            baseline=self.baseline,
        )


def _check_disparity(
    disparity: np.ndarray, geometry: StereoGeometry, mask: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray | None]:
    if not isinstance(geometry, StereoGeometry):
        raise InputError(f'geometry must be a StereoGeometry; got {type(geometry).__name__}')
    disparity = np.asarray(disparity)
    if disparity.dtype.kind not in 'fiu':
        raise InputError(
            f'disparity must hold real numbers (float or int); got dtype {disparity.dtype}'
        )
    if disparity.ndim != 2:
        raise InputError(f'disparity must be (H, W); got shape {disparity.shape}')
    if mask is not None:
        mask = np.asarray(mask)
        if mask.shape != disparity.shape:
            raise InputError(
                f'mask must have the disparity shape {disparity.shape}; got {mask.shape}'
            )
        if mask.dtype != np.bool_:
            raise InputError(f'mask must be a bool array (True = keep); got dtype {mask.dtype}')
    return disparity, mask


def _depth(disparity: np.ndarray, geometry: StereoGeometry, mask: np.ndarray | None) -> np.ndarray:
    """Z = fx·B / (d + Δ) in float64, NaN where invalid or masked out (inputs checked).

    A ``d + Δ`` so near 0 that X, Y or Z of a pixel of the image would not fit float32 (the
    outputs' type) is invalid too: it would be published as inf, and off-axis (``|u − cx| >
    fx``) as an infinite X beside a finite Z.
    """
    height, width = disparity.shape
    # The largest |X| / Z and |Y| / Z of any pixel of the image (at least 1, for Z itself).
    spread = max(
        1.0,
        abs(geometry.cx) / geometry.fx,
        abs(width - 1 - geometry.cx) / geometry.fx,
        abs(geometry.cy) / geometry.fy,
        abs(height - 1 - geometry.cy) / geometry.fy,
    )
    shifted = disparity.astype(np.float64) + geometry.disparity_offset
    with np.errstate(invalid='ignore', over='ignore'):
        keep = np.isfinite(shifted) & (
            shifted * _FLOAT32_MAX > geometry.fx * geometry.baseline * spread
        )
    if mask is not None:
        keep &= mask
    depth = np.full(disparity.shape, np.nan)
    np.divide(geometry.fx * geometry.baseline, shifted, out=depth, where=keep)
    return depth


def disparity_to_depth(
    disparity: np.ndarray,
    geometry: StereoGeometry,
    mask: np.ndarray | None = None,
) -> np.ndarray:
    """The depth ``Z`` of every pixel of a left-reference disparity map (REP 118 float form).

    Args:
        disparity: (H, W) real array, raw disparity ``x_left − x_right`` in pixels; NaN =
            invalid.
        geometry: Intrinsics at the disparity map's resolution.
        mask: Optional (H, W) bool, True = keep (e.g. confidence ≥ threshold).

    Returns:
        (H, W) float32 depth along the left camera's optical axis, in the baseline's units
        (metres in ROS). NaN where the disparity is NaN, where ``d + Δ ≤ 0`` (at or beyond
        infinity) or so near 0 that a coordinate of the image's points would not fit float32,
        or where ``mask`` is False. The ``Z`` of :func:`disparity_to_points`.

    Raises:
        InputError: As :func:`disparity_to_points`.
    """
    disparity, mask = _check_disparity(disparity, geometry, mask)
    return _depth(disparity, geometry, mask).astype(np.float32)


def disparity_to_points(
    disparity: np.ndarray,
    geometry: StereoGeometry,
    mask: np.ndarray | None = None,
) -> np.ndarray:
    """Triangulate every pixel of a left-reference disparity map.

    Args:
        disparity: (H, W) float32 (any real dtype) raw disparity ``x_left − x_right`` in
            pixels; NaN = invalid.
        geometry: Intrinsics at the disparity map's resolution.
        mask: Optional (H, W) bool, True = keep. Pixels outside it become NaN. Only a bool
            array is accepted: a float mask (a confidence map, say) would make every non-zero
            value, NaN included, True.

    Returns:
        (H, W, 3) float32 points (X, Y, Z) in the left camera frame (x right, y down, z
        forward), world units of the baseline. NaN in all three where the disparity is NaN,
        where ``d + Δ ≤ 0`` or so near 0 that a coordinate of the image's points would not
        fit float32, or where ``mask`` is False: a point is finite in all three or in none.

    Raises:
        InputError: ``disparity`` is not a 2-D real array, ``geometry`` is not a
            :class:`StereoGeometry`, or ``mask`` is not bool or has another shape.
    """
    disparity, mask = _check_disparity(disparity, geometry, mask)
    height, width = disparity.shape
    depth = _depth(disparity, geometry, mask)
    columns = np.arange(width, dtype=np.float64)[None, :]
    rows = np.arange(height, dtype=np.float64)[:, None]
    points = np.empty((height, width, 3), dtype=np.float32)
    points[..., 0] = (columns - geometry.cx) * depth / geometry.fx
    points[..., 1] = (rows - geometry.cy) * depth / geometry.fy
    points[..., 2] = depth
    return points


def pack_rgb(image: np.ndarray) -> np.ndarray:
    """Pack colours into float32 ``rgb`` values (bits of ``0x00RRGGBB``).

    Args:
        image: (H, W) uint8 gray (used for all three channels) or (H, W, 3) uint8 RGB.

    Returns:
        (H, W) float32 whose bit patterns are the packed colours.

    Raises:
        InputError: Not uint8, or not (H, W) / (H, W, 3).
    """
    image = np.asarray(image)
    if image.dtype != np.uint8:
        raise InputError(f'colour image must be uint8; got {image.dtype}')
    if image.ndim == 2:
        # Gray in all three bytes, g·0x010101 = g << 16 | g << 8 | g, without the (H, W, 3)
        # copy that np.repeat made (twice the time of a colour image's packing).
        grey = image.astype(np.uint32) * np.uint32(0x010101)
        return grey.astype('<u4', copy=False).view('<f4')
    if image.ndim != 3 or image.shape[2] != 3:
        raise InputError(f'colour image must be (H, W) or (H, W, 3); got {image.shape}')
    channels = image.astype(np.uint32)
    packed = (channels[..., 0] << 16) | (channels[..., 1] << 8) | channels[..., 2]
    return packed.astype('<u4').view('<f4')


def unpack_rgb(packed: np.ndarray) -> np.ndarray:
    """Inverse of :func:`pack_rgb`: (...) float32 → (..., 3) uint8 RGB.

    An integer array holds the packed ``0x00RRGGBB`` (or PCL's ``0xAARRGGBB``) as a number,
    as a ``PointCloud2`` field ``rgb`` / ``rgba`` of datatype UINT32 decodes; its bits are read
    as they are, not converted to float32 first.

    Raises:
        InputError: Neither a float nor an integer array.
    """
    packed = np.asarray(packed)
    if packed.dtype.kind in 'iu':
        bits = packed.astype('<u4')
    elif packed.dtype.kind == 'f':
        bits = np.ascontiguousarray(packed, dtype='<f4').view('<u4')
    else:
        raise InputError(
            f'packed colours must be float32 (pack_rgb) or integer 0x00RRGGBB; '
            f'got dtype {packed.dtype}'
        )
    return np.stack([(bits >> 16) & 0xFF, (bits >> 8) & 0xFF, bits & 0xFF], axis=-1).astype(
        np.uint8
    )


def make_cloud(
    points: np.ndarray,
    colours: np.ndarray,
    organized: bool = True,
    confidence: np.ndarray | None = None,
) -> np.ndarray:
    """Assemble XYZ and packed colours (and confidence) into a structured point array.

    Args:
        points: (H, W, 3) float32 (any float dtype) from :func:`disparity_to_points`; NaN rows
            are dropped points.
        colours: (H, W) float32 from :func:`pack_rgb`: packed bits, not intensities, so a
            uint8 image (or any other dtype) is refused rather than stored as a number.
        organized: Keep the (H, W) grid with NaN points (``stereo_image_proc`` style); if False,
            return only the finite points, row-major, as (N,).
        confidence: Optional (H, W) real confidence map in [0, 1] (NaN allowed where the point
            is NaN; an integer map is a fraction of its type's full scale, uint8 255 = 1, as
            :func:`filter_cloud` reads it); given, each point carries its value in a
            ``confidence`` field.

    Returns:
        (H, W) or (N,) structured array of :data:`CLOUD_DTYPE`, or of
        :data:`CLOUD_CONFIDENCE_DTYPE` when ``confidence`` is given.

    Raises:
        InputError: Not numpy arrays, points not float or a finite point beyond float32,
            colours not float32, confidence not real or outside [0, 1] at a kept point, or
            shapes that do not fit together.
        ConfigError: ``organized`` is not a bool.
    """
    if not isinstance(organized, (bool, np.bool_)):
        raise ConfigError(
            f'organized must be a bool; got {type(organized).__name__} {organized!r}'
        )
    arrays = [('points', points), ('colours', colours)]
    if confidence is not None:
        arrays.append(('confidence', confidence))
    for name, array in arrays:
        if not isinstance(array, np.ndarray):
            raise InputError(f'{name} must be a numpy array; got {type(array).__name__}')
    if points.dtype.kind != 'f':
        raise InputError(f'points must be a float array (NaN = dropped); got dtype {points.dtype}')
    if colours.dtype.kind != 'f' or colours.dtype.itemsize != 4:
        raise InputError(
            'colours must be float32 packed by pack_rgb (bits of 0x00RRGGBB); '
            f'got dtype {colours.dtype}'
        )
    if points.ndim != 3 or points.shape[2] != 3:
        raise InputError(f'points must be (H, W, 3); got {points.shape}')
    if colours.shape != points.shape[:2]:
        raise InputError(f'colours must be {points.shape[:2]}; got {colours.shape}')
    # One plane at a time: numpy's all(axis=2) over an axis of 3 took 9 ms of a 640×480
    # frame's 10 ms cloud, this 0.2 ms.
    finite = np.isfinite(points[..., 0])
    finite &= np.isfinite(points[..., 1])
    finite &= np.isfinite(points[..., 2])
    if points.dtype.itemsize > 4:  # the fields are float32: a wider point could become ±inf
        with np.errstate(over='ignore', invalid='ignore'):
            too_far = finite & ~np.isfinite(points.astype(np.float32)).all(axis=2)
        if too_far.any():
            raise InputError(
                f'points must fit float32 (the x, y, z fields); {int(too_far.sum())} do not '
                f'(e.g. {points[too_far][0].tolist()})'
            )
    if confidence is not None:
        confidence = _check_confidence(confidence, points.shape[:2], finite)
    cloud = np.empty(
        points.shape[:2], dtype=CLOUD_DTYPE if confidence is None else CLOUD_CONFIDENCE_DTYPE
    )
    cloud['x'] = points[..., 0]
    cloud['y'] = points[..., 1]
    cloud['z'] = points[..., 2]
    cloud['rgb'] = colours
    if confidence is not None:
        cloud['confidence'] = confidence
    if organized:
        return cloud
    return cloud[finite]


def _check_confidence(
    confidence: np.ndarray, shape: tuple[int, ...], kept: np.ndarray
) -> np.ndarray:
    """The confidence as fractions (:func:`_confidence_fraction`), checked."""
    if confidence.dtype.kind not in 'fiu':
        raise InputError(f'confidence must hold real numbers; got dtype {confidence.dtype}')
    if confidence.shape != shape:
        raise InputError(f'confidence must be {shape}; got {confidence.shape}')
    confidence = _confidence_fraction(confidence)
    values = confidence[kept]
    with np.errstate(invalid='ignore'):
        bad = ~((values >= 0) & (values <= 1))
    if bad.any():
        raise InputError(
            f'confidence must lie in [0, 1] at every kept point; {int(bad.sum())} do not '
            f'(e.g. {values[bad][0]})'
        )
    return confidence


def stereo_cloud(
    disparity: np.ndarray,
    confidence: np.ndarray,
    left: np.ndarray,
    geometry: StereoGeometry,
    kept: np.ndarray,
    *,
    organized: bool = True,
    with_confidence: bool = False,
) -> np.ndarray:
    """The node's ``points2`` for one frame: triangulated, coloured, filtered or annotated.

    Args:
        disparity: (H, W) raw disparity (NaN = invalid), see :func:`disparity_to_points`.
        confidence: (H, W) confidence in [0, 1].
        left: (H, W) or (H, W, 3) uint8 left image, the points' colours.
        geometry: Intrinsics at the disparity map's resolution.
        kept: (H, W) bool, the pixels the node keeps (finite disparity, confidence ≥ its
            threshold, not in a speckle: ``PipelineResult.valid``); without ``with_confidence``
            only their points are in the cloud, with it every point is and ``kept`` is not
            used.
        organized: (H, W) grid with NaN points, or only the valid points as (N,).
        with_confidence: Keep every point that can be triangulated and carry its confidence
            (:data:`CLOUD_CONFIDENCE_DTYPE`), so that consumers filter with their own threshold
            (:func:`filter_cloud`).

    Returns:
        The structured point array.

    Raises:
        InputError: ``left`` of another size than ``disparity`` (or arrays that the functions
            called refuse).
    """
    shape, image = np.shape(disparity), np.shape(left)
    if len(shape) != 2 or tuple(image) not in (tuple(shape), (*shape, 3)):
        raise InputError(
            f"the left image must have the disparity map's size {shape} (+ 3 colours); "
            f'got {image}'
        )
    if with_confidence:
        points = disparity_to_points(disparity, geometry)
        return make_cloud(points, pack_rgb(left), organized, confidence=confidence)
    points = disparity_to_points(disparity, geometry, kept)
    return make_cloud(points, pack_rgb(left), organized)


def filter_cloud(
    cloud: np.ndarray,
    threshold: float,
    organized: bool = True,
    field: str = 'confidence',
) -> np.ndarray:
    """Keep the points of a cloud whose confidence is at least ``threshold``.

    Works on any structured point array with float ``x``, ``y``, ``z`` and a real confidence
    field (other fields, e.g. ``rgb`` or ``intensity``, are carried along unchanged), such as
    :func:`make_cloud` builds with ``confidence`` or
    :func:`cva_confidence_ros.ros.convert.point_cloud_to_records` decodes from a
    ``PointCloud2``. A point is kept where its x, y, z are finite and its confidence is
    ≥ ``threshold`` (a NaN confidence is never kept). A float field holds the confidence in
    [0, 1] as it is; an integer field is a fraction of its type's full scale, like a ``mono8``
    or ``mono16`` image: a uint8 200 is 200 / 255 ≈ 0.78, uint8 255 and uint16 65535 are 1.

    Args:
        cloud: (H, W) organised or (N,) structured point array.
        threshold: In [0, 1], compared in the precision of the field (a float32 0.7 is
            ≥ 0.7); 0 keeps every finite point whose confidence is not NaN.
        organized: Keep the input's shape and set x, y, z of the dropped points to NaN
            (``stereo_image_proc`` style); if False, return only the kept points as (N,).
        field: Name of the confidence field.

    Returns:
        The filtered structured array, a new array (the input is not changed).

    Raises:
        InputError: ``cloud`` is not a structured array with float x, y, z and a real
            ``field``, or a point with finite x, y, z has a confidence outside [0, 1] (NaN is
            allowed: never kept).
        ConfigError: ``threshold`` is not a real number in [0, 1], ``organized`` not a bool.
    """
    if not is_real(threshold) or not 0.0 <= threshold <= 1.0:
        raise ConfigError(f'threshold must be a real number in [0, 1]; got {threshold!r}')
    if not isinstance(organized, (bool, np.bool_)):
        raise ConfigError(
            f'organized must be a bool; got {type(organized).__name__} {organized!r}'
        )
    if not isinstance(cloud, np.ndarray) or cloud.dtype.names is None:
        raise InputError(
            'cloud must be a structured numpy array of points; '
            f'got {getattr(cloud, "dtype", type(cloud).__name__)}'
        )
    if cloud.ndim not in (1, 2):
        raise InputError(f'cloud must be (H, W) or (N,); got shape {cloud.shape}')
    names = cloud.dtype.names
    for name in ('x', 'y', 'z'):
        if name not in names or cloud.dtype[name].kind != 'f' or cloud.dtype[name].shape:
            raise InputError(f'cloud needs a float field {name!r}; its fields are {list(names)}')
    if field not in names:
        raise InputError(
            f'cloud has no confidence field {field!r}; its fields are {list(names)} '
            '(the node writes it with points_confidence: true)'
        )
    if cloud.dtype[field].kind not in 'fiu' or cloud.dtype[field].shape:
        raise InputError(
            f'confidence field {field!r} must be one real number a point; '
            f'got {cloud.dtype[field]}'
        )
    values = _confidence_fraction(cloud[field])
    finite = np.isfinite(cloud['x']) & np.isfinite(cloud['y']) & np.isfinite(cloud['z'])
    with np.errstate(invalid='ignore'):
        outside = finite & ((values < 0) | (values > 1))
    if outside.any():
        # Another producer's scale (a confidence in percent, say) passed every point above 1
        # at any threshold: the cut did nothing, silently.
        wrong = values[outside]
        hint = ': another scale, such as percent?' if wrong.max() > 1 else ''
        raise InputError(
            f'confidence field {field!r} must hold fractions in [0, 1] (an integer field: of '
            f'its full scale); {int(outside.sum())} points with finite x, y, z do not (from '
            f'{float(wrong.min()):g} to {float(wrong.max()):g}){hint}'
        )
    # Compare in the field's own precision, whatever type the threshold has: a float32 0.7
    # is the closest float32 to 0.7 and counts as equal to a threshold of 0.7 (np.float64 or
    # Python float alike), as in the node's own confidence ≥ threshold test.
    limit = values.dtype.type(threshold)
    with np.errstate(invalid='ignore'):
        keep = (values >= limit) & finite
    if not organized:
        return cloud[keep]
    filtered = cloud.copy()
    for name in ('x', 'y', 'z'):
        filtered[name][~keep] = np.nan
    return filtered

"""``rosbags`` message types (ROS 2 Jazzy) ⇄ numpy arrays.

The functions here build and read the messages of ``sensor_msgs`` and ``stereo_msgs`` as the
``rosbags`` typestore defines them, so that bags are written and read without a ROS install.
Readers are duck-typed on the field names, so they accept rclpy messages as well.

Conventions (docs/ARCHITECTURE.md): camera images are uint8 (H, W) or (H, W, 3) in RGB order;
disparities are float32 (H, W) with NaN where invalid or unknown.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np

from cva_confidence_ros.camera_info import check_rows, image_projection
from cva_confidence_ros.checks import is_int, is_real
from cva_confidence_ros.errors import InputError
from cva_confidence_ros.pointcloud import StereoGeometry

__all__ = [
    'COMPRESSED_IMAGE',
    'DISPARITY_IMAGE',
    'IMAGE',
    'LASER_SCAN',
    'POINT_CLOUD2',
    'CAMERA_INFO',
    'camera_geometry',
    'camera_info_msgs',
    'disparity_from_msg',
    'disparity_to_msg',
    'float_image_to_msg',
    'image_to_msg',
    'jazzy_typestore',
    'make_header',
    'stamp_to_ns',
]

IMAGE = 'sensor_msgs/msg/Image'
COMPRESSED_IMAGE = 'sensor_msgs/msg/CompressedImage'
CAMERA_INFO = 'sensor_msgs/msg/CameraInfo'
DISPARITY_IMAGE = 'stereo_msgs/msg/DisparityImage'
POINT_CLOUD2 = 'sensor_msgs/msg/PointCloud2'
LASER_SCAN = 'sensor_msgs/msg/LaserScan'

_FLOAT_ENCODINGS: dict[str, tuple[str, int]] = {'32FC1': ('f4', 1), '64FC1': ('f8', 1)}

_NS = 1_000_000_000
#: First stamp a header cannot hold: ``builtin_interfaces/Time.sec`` is an int32.
_STAMP_LIMIT_NS = 2**31 * _NS


@lru_cache(maxsize=1)
def jazzy_typestore() -> Any:
    """The ``rosbags`` typestore of ROS 2 Jazzy (message classes, CDR (de)serialisation)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def stamp_to_ns(stamp: Any) -> int:
    """``builtin_interfaces/Time`` (``sec``, ``nanosec``) → integer nanoseconds."""
    return int(stamp.sec) * _NS + int(stamp.nanosec)


def make_header(stamp_ns: int, frame_id: str, typestore: Any | None = None) -> Any:
    """A ``std_msgs/Header`` with the given stamp (integer ns, ≥ 0) and frame id.

    Raises:
        InputError: A stamp below 0, not a number, or past the int32 seconds of a header
            (2038).
    """
    if not 0 <= stamp_ns < _STAMP_LIMIT_NS:  # NaN fails too
        raise InputError(
            f'stamps must be >= 0 ns and below {_STAMP_LIMIT_NS} ns (header stamps hold int32 '
            f'seconds); got {stamp_ns}'
        )
    types = (typestore or jazzy_typestore()).types
    sec, nanosec = divmod(int(stamp_ns), _NS)
    return types['std_msgs/msg/Header'](
        stamp=types['builtin_interfaces/msg/Time'](sec=sec, nanosec=nanosec), frame_id=frame_id
    )


def image_to_msg(
    image: np.ndarray, stamp_ns: int, frame_id: str, typestore: Any | None = None
) -> Any:
    """A ``sensor_msgs/Image`` holding a camera image.

    Args:
        image: (H, W) uint8 (``mono8``), (H, W) uint16 (``mono16``) or (H, W, 3) uint8 in RGB
            order (``rgb8``); a uint16 image of either byte order.
        stamp_ns: Header stamp in nanoseconds.
        frame_id: Header frame id.
        typestore: ``rosbags`` typestore; the Jazzy one by default.

    Returns:
        The message, little-endian, rows packed (``step`` = width × bytes per pixel).

    Raises:
        InputError: Any other shape or dtype, or an empty image (height or width 0).
    """
    array = np.asarray(image)
    # Either byte order (a 16-bit PGM or PNG read as big-endian '>u2'): written little-endian.
    kind = array.dtype.newbyteorder('=')
    if kind == np.uint8 and array.ndim == 2:
        encoding = 'mono8'
    elif kind == np.uint16 and array.ndim == 2:
        encoding = 'mono16'
    elif kind == np.uint8 and array.ndim == 3 and array.shape[2] == 3:
        encoding = 'rgb8'
    else:
        raise InputError(
            f'expected a (H, W) uint8/uint16 or (H, W, 3) uint8 image; got {array.shape} '
            f'{array.dtype}'
        )
    return _raw_image(array, encoding, stamp_ns, frame_id, typestore)


def float_image_to_msg(
    array: np.ndarray, stamp_ns: int, frame_id: str, typestore: Any | None = None
) -> Any:
    """A ``32FC1`` ``sensor_msgs/Image`` of a (H, W) float array (NaN kept as NaN).

    Raises:
        InputError: Any other shape or dtype, or an empty array (height or width 0).
    """
    values = np.asarray(array)
    if values.ndim != 2 or not np.issubdtype(values.dtype, np.floating):
        raise InputError(f'expected a (H, W) float array; got {values.shape} {values.dtype}')
    return _raw_image(values.astype('<f4'), '32FC1', stamp_ns, frame_id, typestore)


def _raw_image(
    array: np.ndarray, encoding: str, stamp_ns: int, frame_id: str, typestore: Any | None
) -> Any:
    store = typestore or jazzy_typestore()
    height, width = array.shape[:2]
    if height == 0 or width == 0:
        # Such a message is refused by every reader (the node's and disparity_from_msg).
        raise InputError(f'cannot write an empty {encoding} image ({height}×{width})')
    little = np.ascontiguousarray(array.astype(array.dtype.newbyteorder('<'), copy=False))
    data = little.reshape(-1).view(np.uint8)
    return store.types[IMAGE](
        header=make_header(stamp_ns, frame_id, store),
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=0,
        step=data.size // max(height, 1),
        data=data,
    )


def _pixels(msg: Any, layouts: dict[str, tuple[str, int]], what: str) -> np.ndarray:
    """Decode ``msg.data`` as (H, W) or (H, W, C) of the encoding's dtype (native order)."""
    encoding = str(msg.encoding)
    if encoding not in layouts:
        raise InputError(
            f'{what}: unknown image encoding {encoding!r}; expected one of {sorted(layouts)}'
        )
    kind, channels = layouts[encoding]
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    dtype = np.dtype(kind).newbyteorder('>' if msg.is_bigendian else '<')
    row_bytes = width * channels * dtype.itemsize
    data = np.frombuffer(msg.data, dtype=np.uint8)
    if height == 0 or width == 0:
        raise InputError(f'{what}: empty image ({height}×{width})')
    if step < row_bytes or data.size < step * (height - 1) + row_bytes:
        raise InputError(
            f'{what}: {encoding} image of {height}×{width} needs step ≥ {row_bytes} and '
            f'{step * (height - 1) + row_bytes} bytes; got step {step} and {data.size} bytes'
        )
    # The rows in place, by their stride: the last one may come without its padding, and a
    # step far beyond the data (one row, a damaged step) costs nothing.
    rows = np.lib.stride_tricks.as_strided(data, (height, row_bytes), (step, 1), writeable=False)
    pixels = np.ascontiguousarray(rows).view(dtype).astype(dtype.newbyteorder('='))
    shape = (height, width) if channels == 1 else (height, width, channels)
    return pixels.reshape(shape)


def disparity_to_msg(
    disparity: np.ndarray,
    stamp_ns: int,
    frame_id: str,
    geometry: StereoGeometry,
    *,
    delta_d: float = 0.0,
    typestore: Any | None = None,
) -> Any:
    """A ``stereo_msgs/DisparityImage`` of a raw disparity map, in stereo_image_proc's convention.

    The image holds ``d + Δ`` with Δ = cx_right − cx_left, so that ``Z = f·T / value`` for
    every valid value (what stereo_image_proc publishes and the node publishes too); unknown
    pixels stay NaN. ``min_disparity`` is Δ (raw d ≥ 0), ``max_disparity`` the largest value.

    Args:
        disparity: (H, W) float raw disparity ``x_left − x_right`` (≥ 0), NaN = unknown.
        stamp_ns: Header stamp (ns); the inner image carries the same header.
        frame_id: Frame of the left camera.
        geometry: Stereo geometry at the disparity's resolution (f, T and Δ).
        delta_d: Smallest disparity increment (0 for continuous values such as ground truth).
        typestore: ``rosbags`` typestore; the Jazzy one by default.

    Returns:
        The message; ``valid_window`` covers the whole image. A value that is no raw
        disparity (±inf, below 0) is written NaN, as unknown: an inf would be a valid value
        by the message's definition (≥ ``min_disparity``), a point at depth fT/inf = 0.

    Raises:
        InputError: Not a (H, W) array, or ``delta_d`` not a finite number ≥ 0.
    """
    if not is_real(delta_d) or not np.isfinite(delta_d) or delta_d < 0:
        raise InputError(f'delta_d must be a finite number >= 0; got {delta_d!r}')
    store = typestore or jazzy_typestore()
    offset = geometry.disparity_offset
    with np.errstate(over='ignore', invalid='ignore'):
        raw = np.asarray(disparity, dtype=np.float32)
        shifted = raw + np.float32(offset)
        shifted = np.where(np.isfinite(shifted) & (raw >= 0), shifted, np.float32(np.nan))
    finite = shifted[np.isfinite(shifted)]
    image = float_image_to_msg(shifted, stamp_ns, frame_id, store)
    roi = store.types['sensor_msgs/msg/RegionOfInterest'](
        x_offset=0, y_offset=0, height=image.height, width=image.width, do_rectify=False
    )
    return store.types[DISPARITY_IMAGE](
        header=make_header(stamp_ns, frame_id, store),
        image=image,
        f=float(geometry.fx),
        t=float(geometry.baseline),
        valid_window=roi,
        min_disparity=float(offset),
        max_disparity=float(finite.max()) if finite.size else float(offset),
        delta_d=float(delta_d),
    )


def disparity_from_msg(msg: Any, offset: float = 0.0, what: str = 'disparity') -> np.ndarray:
    """Read a raw disparity map from a ``DisparityImage`` or a ``32FC1`` / ``64FC1`` ``Image``.

    Args:
        msg: The message (``rosbags`` or rclpy).
        offset: Δ = cx_right − cx_left of the frame at the message's resolution, subtracted
            from a ``DisparityImage`` (whose values are ``d + Δ``); a plain image holds raw d.
        what: Name used in error messages (e.g. the topic).

    Returns:
        (H, W) float32 raw disparity ``x_left − x_right``; NaN where the value is not
        finite, below the ``DisparityImage``'s ``min_disparity`` (the message's definition of
        invalid), or, for a plain image, negative.

    Raises:
        InputError: Any other encoding, data too short for the declared size, or a
            ``DisparityImage`` whose ``min_disparity`` is not finite (NaN would make every
            pixel invalid).
    """
    inner = getattr(msg, 'image', None)
    is_disparity_image = inner is not None and hasattr(inner, 'encoding')
    image = inner if is_disparity_image else msg
    values = _pixels(image, _FLOAT_ENCODINGS, what).astype(np.float32)
    lowest = np.float32(msg.min_disparity) if is_disparity_image else np.float32(0.0)
    if not np.isfinite(lowest):
        raise InputError(
            f'{what}: the DisparityImage has min_disparity {float(msg.min_disparity)}; '
            f'expected a finite number (below it a pixel is invalid)'
        )
    with np.errstate(invalid='ignore'):
        invalid = ~np.isfinite(values) | ~(values >= lowest)
    if is_disparity_image:
        values -= np.float32(offset)
    values[invalid] = np.nan
    return values


def camera_geometry(
    left_info: Any, right_info: Any, image_size: tuple[int, int] | None = None
) -> tuple[StereoGeometry, int, int]:
    """Read the rectified stereo geometry from the left and right ``CameraInfo`` messages.

    Binning and region of interest are folded in as REP 104 and ``image_geometry`` (and the
    node, ``ros.convert.camera_info_to_geometry``) have them, by the node's own
    ``camera_info.image_projection``: the images are the ROI of the calibration size divided
    by the binning, the ROI offset is moved out of the principal point and rows 0 and 1 of P
    are divided by the binning. When the images' size is known (``image_size`` = (width,
    height)) it is checked as the node checks it, and images of the calibration size take P
    as it is.

    Returns:
        ``(geometry, width, height)``: intrinsics and baseline from the projection matrices
        (``pointcloud.StereoGeometry``) and the size of the images both infos describe.

    Raises:
        InputError: Sizes that differ (from each other or from ``image_size``), a region of
            interest outside the calibration size, a focal length ≤ 0, fx, fy or cy that
            differ between left and right (not a rectified pair), a vertical baseline (Ty
            of the two projections differing), or a right projection without a positive
            baseline (P_right[0, 3] must be −fx·B < 0).
    """
    size_left, p_left = image_projection(left_info, 'left camera info', image_size)
    size_right, p_right = image_projection(right_info, 'right camera info', image_size)
    if size_left != size_right:
        raise InputError(
            f'left and right camera infos must declare the same size; got {size_left[0]}×'
            f'{size_left[1]} and {size_right[0]}×{size_right[1]}'
        )
    geometry = StereoGeometry.from_projections(p_left, p_right)
    check_rows(p_left, p_right)
    return geometry, size_left[0], size_left[1]


def camera_info_msgs(
    geometry: StereoGeometry,
    width: int,
    height: int,
    stamp_ns: int,
    frame_ids: tuple[str, str],
    typestore: Any | None = None,
) -> tuple[Any, Any]:
    """Left and right ``sensor_msgs/CameraInfo`` of a rectified pair.

    Both cameras get K = [fx 0 cx; 0 fy cy; 0 0 1], R = I, no distortion (``plumb_bob``,
    zeros), and P = [fx 0 cx Tx; 0 fy cy 0; 0 0 1 0] with Tx = 0 on the left and −fx·baseline
    on the right, as the ROS ``CameraInfo`` definition asks for a rectified stereo pair.

    Args:
        geometry: Intrinsics and baseline (``pointcloud.StereoGeometry``).
        width: Image width in pixels. height: Image height in pixels.
        stamp_ns: Header stamp (ns) of both messages.
        frame_ids: Frame ids of the left and the right camera.
        typestore: ``rosbags`` typestore; the Jazzy one by default.

    Raises:
        InputError: A width or height that is not an integer > 0 (a uint32 of the message),
            or not two frame ids.
    """
    for name, value in (('width', width), ('height', height)):
        if not is_int(value) or not 0 < value < 2**32:
            raise InputError(
                f'camera info {name} must be an integer in 1 … 2^32 − 1; got {value!r}'
            )
    if isinstance(frame_ids, str) or len(frame_ids) != 2:
        raise InputError(f'expected two frame ids (left, right); got {frame_ids!r}')
    store = typestore or jazzy_typestore()
    messages = []
    for side, frame_id in zip(('left', 'right'), frame_ids, strict=True):
        cx = geometry.cx if side == 'left' else geometry.cx_right
        tx = 0.0 if side == 'left' else -geometry.fx * geometry.baseline
        k = np.array([geometry.fx, 0, cx, 0, geometry.fy, geometry.cy, 0, 0, 1], np.float64)
        p = np.array(
            [geometry.fx, 0, cx, tx, 0, geometry.fy, geometry.cy, 0, 0, 0, 1, 0], np.float64
        )
        messages.append(
            store.types[CAMERA_INFO](
                header=make_header(stamp_ns, frame_id, store),
                height=int(height),
                width=int(width),
                distortion_model='plumb_bob',
                d=np.zeros(5, np.float64),
                k=k,
                r=np.eye(3, dtype=np.float64).reshape(-1),
                p=p,
                binning_x=0,
                binning_y=0,
                roi=store.types['sensor_msgs/msg/RegionOfInterest'](
                    x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
                ),
            )
        )
    return messages[0], messages[1]

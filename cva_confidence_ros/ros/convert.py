"""rclpy messages ⇄ numpy arrays for the node (``sensor_msgs``, ``stereo_msgs``).

Conventions follow ``stereo_image_proc`` so that the node drops into existing pipelines:

* ``stereo_msgs/DisparityImage``: 32FC1 image of ``d − (cx_left − cx_right)`` (so that
  ``Z = f·T/d`` holds for every valid value), ``f`` and ``T`` (baseline) from the camera infos,
  ``min_disparity``/``max_disparity`` the searched range after that shift, invalid pixels set to
  ``min_disparity − 1`` (below the valid range, as ``stereo_image_proc`` does).
* ``sensor_msgs/PointCloud2``: fields x, y, z, rgb (float32, 16-byte points), optionally a
  fifth float32 ``confidence`` (20-byte points). Clouds of other producers, with any fields,
  padding and row step, are read by :func:`point_cloud_to_records` for filtering.
* depth ``sensor_msgs/Image`` as REP 118 lays it out, for depth consumers (``depth_image_proc``,
  nvblox, RTAB-Map): ``32FC1`` metres with NaN where there is no depth, or ``16UC1``
  millimetres with 0 there.
* ``sensor_msgs/LaserScan`` of the kept pixels (:mod:`cva_confidence_ros.scan`), with the
  confidence of each beam's point as its intensity.
"""

from __future__ import annotations

import math
from typing import Any

from builtin_interfaces.msg import Time
import numpy as np
from sensor_msgs.msg import (
    CameraInfo,
    Image,
    LaserScan,
    PointCloud2,
    PointField,
    RegionOfInterest,
)
from std_msgs.msg import Header
from stereo_msgs.msg import DisparityImage

from cva_confidence_ros.camera_info import check_rows, fold, image_projection
from cva_confidence_ros.checks import is_int
from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.pointcloud import (
    CLOUD_CONFIDENCE_DTYPE,
    CLOUD_DTYPE,
    StereoGeometry,
    unit_projection,
)
from cva_confidence_ros.ros.transport import MAX_PNG_PIXELS, png_header
from cva_confidence_ros.scan import Scan

__all__ = [
    'DEPTH_ENCODINGS',
    'SUPPORTED_ENCODINGS',
    'array_to_image',
    'camera_info_to_geometry',
    'cloud_to_array',
    'cloud_to_message',
    'compressed_image_to_array',
    'compressed_size',
    'depth_image_to_array',
    'depth_to_image',
    'disparity_from_message',
    'disparity_to_message',
    'float_image_to_array',
    'image_camera_info',
    'image_to_array',
    'ns_to_stamp',
    'pair_to_uint8',
    'point_cloud_to_records',
    'records_to_point_cloud',
    'rgb_to_image',
    'scale_camera_info',
    'scan_to_message',
    'stamp_to_ns',
    'stereo_pair_from_messages',
]

# encoding → (channels, bytes per channel, index order to RGB or None for gray)
_ENCODINGS: dict[str, tuple[int, int, tuple[int, ...] | None]] = {
    'mono8': (1, 1, None),
    'mono16': (1, 2, None),
    'rgb8': (3, 1, (0, 1, 2)),
    'bgr8': (3, 1, (2, 1, 0)),
    'rgba8': (4, 1, (0, 1, 2)),
    'bgra8': (4, 1, (2, 1, 0)),
    # The OpenCV spellings some camera drivers give their mono images (compared lower-cased).
    '8uc1': (1, 1, None),
    '16uc1': (1, 2, None),
}
#: Image encodings accepted on ``left/image_rect`` and ``right/image_rect``.
SUPPORTED_ENCODINGS: tuple[str, ...] = tuple(_ENCODINGS)
#: Encodings of the ``depth`` output (REP 118): float metres or integer millimetres.
DEPTH_ENCODINGS: tuple[str, ...] = ('32FC1', '16UC1')
#: The baselines camera infos are taken with, metres: from a stereo endoscope's few millimetres
#: to a wide vehicle rig. One outside is a Tx of another unit (B or B in mm instead of −fx·B).
MIN_BASELINE_M = 1e-3
MAX_BASELINE_M = 10.0
# 16UC1 holds 1 mm … 65.535 m; 0 means no depth.
_UINT16_MM_MAX = float(np.iinfo(np.uint16).max)


def stamp_to_ns(stamp: Time) -> int:
    """``builtin_interfaces/Time`` → integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def ns_to_stamp(stamp_ns: int) -> Time:
    """Integer nanoseconds → ``builtin_interfaces/Time``."""
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return Time(sec=sec, nanosec=nanosec)


def image_to_array(msg: Image, name: str = 'image') -> np.ndarray:
    """Decode a ``sensor_msgs/Image`` into the array layout of the core.

    A ``sensor_msgs/CompressedImage`` (it has ``format`` and no ``encoding``) goes to
    :func:`compressed_image_to_array`.

    Args:
        msg: An image with one of :data:`SUPPORTED_ENCODINGS`; row padding (``step`` larger
            than a row) and big-endian mono16 / 16UC1 are handled.
        name: What the error messages call the image (e.g. ``'left image'``).

    Returns:
        (H, W) uint8 for mono8 (and 8UC1), (H, W) uint16 for mono16 (and 16UC1; see
        :func:`pair_to_uint8`), or
        (H, W, 3) uint8 in RGB order for the colour encodings (alpha dropped). A fresh array
        that does not alias the message buffer.

    Raises:
        InputError: Unknown encoding, zero size, a ``step`` too short for a row, or ``data``
            that is not ``height`` rows of ``step`` bytes (the last row's padding may be
            missing).
    """
    if not hasattr(msg, 'encoding') and hasattr(msg, 'format'):
        return compressed_image_to_array(msg, name)
    encoding = msg.encoding.lower()
    if encoding not in _ENCODINGS:
        raise InputError(
            f'{name} encoding must be one of {SUPPORTED_ENCODINGS}; got {msg.encoding!r}'
            + _encoding_hint(encoding)
        )
    channels, depth, order = _ENCODINGS[encoding]
    height, width = int(msg.height), int(msg.width)
    rows = _pixel_rows(msg, name, encoding, channels * depth)
    if depth == 2:
        dtype = np.dtype('>u2' if msg.is_bigendian else '<u2')
        return rows.copy().view(dtype).reshape(height, width).astype(np.uint16)
    pixels = rows.reshape(height, width, channels)
    if order is None:
        return pixels[..., 0].copy()
    return np.ascontiguousarray(pixels[..., list(order)])


# The YUV formats of sensor_msgs/image_encodings (lower-case), raw camera images.
_YUV_ENCODINGS = ('yuv422', 'yuv422_yuy2', 'uyvy', 'yuyv', 'nv21', 'nv24')


def _encoding_hint(encoding: str) -> str:
    """What to do about an unsupported ``encoding`` (lower-case) that cameras are known to send,
    as the end of the error; '' for any other."""
    if encoding.startswith('bayer_'):
        # A camera's raw output: neither debayered nor rectified, so no rectified pair either.
        # Of a 16-bit one, debayer makes mono16 and bgr16: only image_rect is read then.
        deep = encoding.endswith('16')
        return (
            ': a raw Bayer (colour filter) image, neither debayered nor rectified; run '
            'image_proc on the camera (debayer, then rectify: stereo_image_proc does both) and '
            + ('give the node its image_rect (mono16)' if deep
               else 'give the node its image_rect (mono8) or image_rect_color (bgr8)')
        )
    if encoding in ('rgb16', 'bgr16', 'rgba16', 'bgra16'):
        # What stereo_image_proc's image_rect_color is for a 16-bit Bayer camera.
        return (
            ': 16-bit colour is not read; give the node the 16-bit gray image_rect (mono16) of '
            'the same camera (stereo_image_proc publishes both), or 8-bit colour (bgr8)'
        )
    if encoding in _YUV_ENCODINGS:
        # What USB cameras send as their raw image; image_proc converts and rectifies it.
        return (
            ': a YUV camera format (a raw image, as USB cameras send it); run image_proc on '
            'the camera (debayer converts YUV, then rectify: stereo_image_proc does both) and '
            'give the node its image_rect (mono8) or image_rect_color (bgr8)'
        )
    if encoding in ('8uc3', '8uc4'):
        # cv_bridge's cv2_to_imgmsg(image) without an encoding ("passthrough") names OpenCV's
        # BGR image 8UC3: the channel order is not in the message, so it is not guessed.
        return (
            ': an OpenCV type that does not say the channel order; publish the image as bgr8 '
            "or bgra8 (cv_bridge: cv2_to_imgmsg(image, 'bgr8')) or rgb8 / rgba8"
        )
    return ''


def compressed_image_to_array(msg: Any, name: str = 'image') -> np.ndarray:
    """Decode a ``sensor_msgs/CompressedImage`` (``image_transport``'s ``compressed``: JPEG or
    PNG) into the array layout of :func:`image_to_array`.

    The format string (``"bgr8; jpeg compressed bgr8"``, ``"mono8; png compressed"``, or a
    bare ``"jpeg"`` / ``"png"``) is checked for what cannot be an intensity image; the pixels
    are whatever the data decode to: gray stays gray, colour comes out RGB, a 16-bit PNG stays
    uint16 (see :func:`pair_to_uint8`).

    Raises:
        InputError: A ``compressedDepth`` format (depth, not intensity), one that names a raw
            Bayer or YUV image before its ``;`` (as ``image_transport`` writes it), empty data,
            data that is no JPEG or PNG or whose header names more than
            :data:`~cva_confidence_ros.ros.transport.MAX_PNG_PIXELS` pixels (checked before
            decoding), or data that OpenCV cannot decode.
    """
    import cv2

    text = str(msg.format)
    if 'compresseddepth' in text.lower().replace(' ', ''):
        raise InputError(
            f'{name} is a compressedDepth image (format {text!r}): a depth map, not an '
            'intensity image; expected image_transport compressed (jpeg or png)'
        )
    # compressed_image_transport converts colour encodings to bgr8 and compresses any other
    # as it is, naming it before the ';': a Bayer camera's image_raw/compressed is a gray
    # JPEG/PNG of the raw mosaic, decoded as a plausible gray image, while the same image
    # raw is refused (image_to_array).
    source, separator, _ = text.partition(';')
    source = source.strip().lower()
    if separator and (source.startswith('bayer_') or source in _YUV_ENCODINGS):
        raise InputError(
            f'{name} is a compressed {source!r} image (format {text!r})' + _encoding_hint(source)
        )
    raw = bytes(msg.data)
    if not raw:
        raise InputError(f'{name} is a compressed image with no data (format {text!r})')
    # The size from the header before OpenCV allocates anything: a message of some ten
    # kilobytes can name gigabytes (a palette PNG of 20000×20000 took 2.3 GB and 15 s).
    width, height = compressed_size(raw, f'{name} (format {text!r})')
    if width * height > MAX_PNG_PIXELS:
        raise InputError(
            f'{name}: the compressed image names {width}×{height} = {width * height} pixels; '
            f'at most {MAX_PNG_PIXELS} are decoded'
        )
    data = np.frombuffer(raw, dtype=np.uint8)
    pixels = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if pixels is None or pixels.size == 0:
        raise InputError(
            f'{name}: {data.size} bytes of compressed data (format {text!r}) do not decode as '
            'an image (JPEG or PNG expected)'
        )
    if pixels.dtype not in (np.uint8, np.uint16):
        raise InputError(f'{name} decodes to {pixels.dtype} pixels; expected 8 or 16 bits')
    if pixels.ndim == 2:
        return pixels
    if pixels.shape[2] == 1:
        return np.ascontiguousarray(pixels[..., 0])
    rgb = cv2.cvtColor(pixels[..., :3], cv2.COLOR_BGR2RGB)
    if rgb.dtype == np.uint16:
        # 16-bit colour: the core takes 16-bit gray only (pair_to_uint8 scales it).
        return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    return rgb


# JPEG start-of-frame markers (baseline, progressive, lossless, arithmetic): they hold the size.
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
# Markers without a length field: TEM and the restart markers RST0–7 (SOI/EOI too).
_JPEG_STANDALONE = frozenset({0x01, *range(0xD0, 0xDA)})


def compressed_size(data: bytes, name: str = 'image') -> tuple[int, int]:
    """``(width, height)`` that a JPEG or PNG names in its header, read without decoding.

    Raises:
        InputError: ``data`` is neither a JPEG nor a PNG, or its header is cut short or
            names an empty image.
    """
    if data[:8] == b'\x89PNG\r\n\x1a\n':
        width, height, _, _ = png_header(data, name)
        return width, height
    if data[:2] != b'\xff\xd8':
        raise InputError(f'{name} is neither a JPEG nor a PNG (it starts {data[:8]!r})')
    at = 2
    while at + 4 <= len(data):
        if data[at] != 0xFF:
            raise InputError(f'{name}: a broken JPEG header (no marker at byte {at})')
        marker = data[at + 1]
        if marker == 0xFF:  # fill byte before a marker
            at += 1
            continue
        if marker in _JPEG_STANDALONE:
            at += 2
            continue
        if marker == 0xDA:  # start of scan before any frame header
            break
        length = int.from_bytes(data[at + 2:at + 4], 'big')
        if marker in _JPEG_SOF and at + 9 <= len(data):
            height = int.from_bytes(data[at + 5:at + 7], 'big')
            width = int.from_bytes(data[at + 7:at + 9], 'big')
            if width == 0 or height == 0:
                # (a height of 0 defers it to a DNL marker, which OpenCV does not read)
                raise InputError(f'{name}: the JPEG header names an empty {width}×{height} image')
            return width, height
        at += 2 + length
    raise InputError(f'{name}: a JPEG without a frame header (cut short or broken)')


def pair_to_uint8(left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bring a decoded pair to uint8, scaling 16-bit images by one common factor.

    mono16 cameras often use 10 or 12 bits; a fixed ``>> 8`` would leave a handful of gray
    levels. Both images are scaled by ``255 / max(left.max(), right.max())`` instead, so that
    their brightness relation (what the matcher relies on) is kept.

    Args:
        left: (H, W) or (H, W, 3) uint8, or (H, W) uint16.
        right: Same kind as ``left``.

    Returns:
        Both as uint8, unchanged if they already were.

    Raises:
        InputError: One image is 8-bit and the other 16-bit.
    """
    if left.dtype == np.uint8 and right.dtype == np.uint8:
        return left, right
    if left.dtype != np.uint16 or right.dtype != np.uint16:
        raise InputError(
            f'left and right must both be 8-bit or both 16-bit; got {left.dtype} and {right.dtype}'
        )
    peak = max(int(left.max()), int(right.max()), 1)
    scale = 255.0 / peak
    return (
        np.round(left * scale).astype(np.uint8),
        np.round(right * scale).astype(np.uint8),
    )


def _packed_image(data: np.ndarray, header: Header, encoding: str) -> Image:
    """An ``Image`` of ``data`` ((H, W) or (H, W, C), little-endian dtype) without row
    padding."""
    data = np.ascontiguousarray(data)
    height, width = data.shape[:2]
    return Image(
        header=header,
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=0,
        step=width * (data.itemsize * (data.shape[2] if data.ndim == 3 else 1)),
        data=data.tobytes(),
    )


def array_to_image(array: np.ndarray, header: Header) -> Image:
    """Encode an (H, W) float32 array as a 32FC1 ``sensor_msgs/Image`` (little-endian).

    Raises:
        InputError: Not a 2-D array.
    """
    if array.ndim != 2:
        raise InputError(f'a 32FC1 image must be (H, W); got shape {array.shape}')
    return _packed_image(np.asarray(array, dtype='<f4'), header, '32FC1')


def rgb_to_image(rgb: np.ndarray, header: Header) -> Image:
    """Encode an (H, W, 3) uint8 RGB array as an ``rgb8`` ``sensor_msgs/Image``.

    Raises:
        InputError: Not an (H, W, 3) uint8 array.
    """
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise InputError(
            f'an rgb8 image must be (H, W, 3) uint8; got {rgb.dtype} {rgb.shape}'
        )
    return _packed_image(rgb, header, 'rgb8')


def float_image_to_array(msg: Image, name: str = '32FC1 image') -> np.ndarray:
    """Decode a 32FC1 ``sensor_msgs/Image`` into (H, W) float32.

    Args:
        msg: The image; row padding and big-endian data are handled.
        name: What the error messages call it.

    Raises:
        InputError: Another encoding, zero size, or a buffer that does not fit the size (as
            :func:`image_to_array`).
    """
    if msg.encoding != '32FC1':
        raise InputError(f'{name}: expected 32FC1; got {msg.encoding!r}')
    height, width = int(msg.height), int(msg.width)
    rows = _pixel_rows(msg, name, '32FC1', 4)
    dtype = np.dtype('>f4' if msg.is_bigendian else '<f4')
    return rows.copy().view(dtype).reshape(height, width).astype(np.float32)


def _pixel_rows(msg: Any, name: str, encoding: str, pixel_bytes: int) -> np.ndarray:
    """(height, width · pixel_bytes) uint8 view of an image's pixel bytes, row padding skipped.

    ``data`` must be ``height`` rows of ``step`` bytes; the last row's padding may be missing
    (a producer that sends ``step · (height − 1) + row`` bytes).

    Raises:
        InputError: Zero size, ``step`` shorter than a row, or ``data`` of another length.
    """
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    if height <= 0 or width <= 0:
        raise InputError(f'{name} must have a positive size; got {width}×{height}')
    row_bytes = width * pixel_bytes
    if step < row_bytes:
        raise InputError(
            f'{name} step must be ≥ {row_bytes} bytes for {width} px of {encoding}; got {step}'
        )
    data = np.frombuffer(msg.data, dtype=np.uint8)
    shortest = step * (height - 1) + row_bytes
    if not shortest <= data.size <= step * height:
        unpadded = ''
        if shortest < step * height:
            unpadded = f", or {shortest} without the last row's padding"
        raise InputError(
            f'{name} data must hold {height} rows of step {step} '
            f'({step * height} bytes{unpadded}); got {data.size}'
        )
    return np.lib.stride_tricks.as_strided(data, shape=(height, row_bytes), strides=(step, 1))


def depth_to_image(depth: np.ndarray, header: Header, encoding: str = '32FC1') -> Image:
    """Encode an (H, W) depth map in metres as a REP 118 depth ``sensor_msgs/Image``.

    Args:
        depth: (H, W) real array, metres; NaN (or any non-finite or non-positive value) =
            no depth.
        header: The image header (the left image's: depth is in the left camera's frame).
        encoding: ``32FC1`` (float32 metres, NaN = no depth) or ``16UC1`` (uint16 millimetres
            rounded to the nearest, 0 = no depth; depths beyond 65.535 m, which 16 bits cannot
            hold, and below 0.5 mm become 0 too: no depth rather than a wrong one).

    Raises:
        InputError: Not a 2-D real array, or another encoding.
    """
    if encoding not in DEPTH_ENCODINGS:
        raise InputError(f'depth encoding must be one of {DEPTH_ENCODINGS}; got {encoding!r}')
    depth = np.asarray(depth)
    if depth.ndim != 2 or depth.dtype.kind not in 'fiu':
        raise InputError(
            f'a depth image must be a 2-D real array; got shape {depth.shape}, dtype {depth.dtype}'
        )
    with np.errstate(invalid='ignore'):
        valid = np.isfinite(depth) & (depth > 0)
    if encoding == '32FC1':
        data = np.where(valid, depth, np.nan).astype('<f4')
    else:
        millimetres = np.zeros(depth.shape)
        np.multiply(depth, 1000.0, out=millimetres, where=valid)
        millimetres = np.rint(millimetres)
        millimetres[millimetres > _UINT16_MM_MAX] = 0.0
        data = millimetres.astype('<u2')
    return _packed_image(data, header, encoding)


def scan_to_message(scan: Scan, header: Header, frame_id: str | None = None) -> LaserScan:
    """A ``sensor_msgs/LaserScan`` of ``scan``, stamped like ``header``.

    Every beam comes from one exposure at the header's stamp: ``time_increment`` is 0, and so
    is ``scan_time`` (the time between scans, which one frame does not know).

    Args:
        scan: From :func:`cva_confidence_ros.scan.disparity_to_scan`.
        header: Header of the images (its stamp is the scan's).
        frame_id: Frame of the scan (x forward, z up; :func:`cva_confidence_ros.scan.
            scan_frame_id`); None = ``header.frame_id``.
    """
    if frame_id is not None:
        header = Header(stamp=header.stamp, frame_id=frame_id)
    return LaserScan(
        header=header,
        angle_min=float(scan.angle_min),
        angle_max=float(scan.angle_max),
        angle_increment=float(scan.angle_increment),
        time_increment=0.0,
        scan_time=0.0,
        range_min=float(scan.range_min),
        range_max=float(scan.range_max),
        ranges=np.asarray(scan.ranges, dtype=np.float32),
        intensities=np.asarray(scan.intensities, dtype=np.float32),
    )


def depth_image_to_array(msg: Image, name: str = '') -> np.ndarray:
    """Decode a REP 118 depth image (``32FC1`` metres or ``16UC1`` millimetres) into metres.

    ``name`` is what the error messages call it ('' = ``<encoding> depth image``).

    Returns:
        (H, W) float32 metres, NaN where the image has no depth (NaN, ±inf or ≤ 0 in
        ``32FC1``, 0 in ``16UC1``).

    Raises:
        InputError: Another encoding, zero size, or a buffer that does not fit the size (as
            :func:`image_to_array`).
    """
    encoding = str(msg.encoding)
    if encoding not in DEPTH_ENCODINGS:
        raise InputError(
            f'{name or "depth image"}: expected {" or ".join(DEPTH_ENCODINGS)}; got {encoding!r}'
        )
    height, width = int(msg.height), int(msg.width)
    name = name or f'{encoding} depth image'
    rows = _pixel_rows(msg, name, encoding, 4 if encoding == '32FC1' else 2)
    order = '>' if msg.is_bigendian else '<'
    if encoding == '32FC1':
        depth = rows.copy().view(f'{order}f4').reshape(height, width).astype(np.float32)
    else:
        millimetres = rows.copy().view(f'{order}u2').reshape(height, width)
        depth = np.where(millimetres > 0, millimetres / 1000.0, np.nan).astype(np.float32)
    with np.errstate(invalid='ignore'):
        depth[~(np.isfinite(depth) & (depth > 0))] = np.nan
    return depth


def camera_info_to_geometry(
    left_info: CameraInfo, right_info: CameraInfo, width: int, height: int
) -> StereoGeometry:
    """Check that a pair of rectified camera infos fits the images and read the geometry.

    Binning and region of interest are folded in as REP 104 and ``image_geometry`` have them
    (``camera_info.image_projection``), and the two projection matrices must then share fy
    and cy as well as fx: the rows of a rectified pair correspond, or the matcher compares
    the wrong ones.

    Args:
        left_info: ``CameraInfo`` of the left camera.
        right_info: ``CameraInfo`` of the right camera (``p[3] = −fx·B``).
        width: Width of the received images, pixels.
        height: Height of the received images, pixels.

    Returns:
        The stereo geometry at the received resolution.

    Raises:
        InputError: A camera info whose size (after binning and region of interest) is not
            the images', a region of interest outside its calibration size, a degenerate
            projection matrix, fx, fy or cy that differ between left and right, a vertical
            baseline (Ty of the two projections differing: rows that do not line up), an
            all-zero P (uncalibrated), a baseline ≤ 0 (the same Tx on both: the left info
            twice; a positive right Tx), or one outside [:data:`MIN_BASELINE_M`,
            :data:`MAX_BASELINE_M`] (a Tx in another unit than −fx·B with B in metres).
    """
    _, left = image_projection(left_info, 'left camera info', (width, height))
    _, right = image_projection(right_info, 'right camera info', (width, height))
    for side, projection in (('left', left), ('right', right)):
        if not projection.any():
            # What an uncalibrated camera, or a driver that leaves P unset, publishes.
            raise InputError(
                f'{side} camera info has an all-zero projection matrix P: the camera is not '
                'calibrated, or its driver does not fill P (the rectified projection, which '
                'the node needs; K alone is the unrectified camera)'
            )
    if np.isfinite(left).all() and np.isfinite(right).all() and left[0, 3] == right[0, 3]:
        # The left info sent twice, a mono camera's, or a driver that leaves the right Tx
        # unset: from_projections would suggest a swapped pair.
        raise InputError(
            'left and right camera infos have the same Tx (P[0, 3] = '
            f'{float(left[0, 3]):g}): a baseline of 0; the right camera info must carry the '
            'stereo calibration, Tx = −fx·B (the left camera info published on both topics, '
            'a mono camera, or a driver that does not fill the right Tx?)'
        )
    if left[0, 3] < right[0, 3] and left[2, 2] > 0 and right[2, 2] > 0 and right[0, 0] > 0:
        # Some drivers write +fx·B: from_projections would only suggest a swapped pair.
        raise InputError(
            f'the right camera info has P[0, 3] = {float(right[0, 3]):g} above the left '
            f"one's ({float(left[0, 3]):g}): a negative baseline; Tx must be −fx·B < 0 "
            '(REP 104: the right camera right of the left one); a driver that writes +fx·B, '
            'or left and right swapped?'
        )
    geometry = StereoGeometry.from_projections(left, right)  # shapes and finite values
    check_rows(left, right)
    if not MIN_BASELINE_M <= geometry.baseline <= MAX_BASELINE_M:
        # Tx = −fx·B in pixels × metres (REP 104); a driver that writes B itself, or B in
        # millimetres, gives a baseline fx times too small or 1000 times too large, and
        # every depth as wrong.
        raise InputError(
            f'baseline (P_left[0, 3] − P_right[0, 3]) / fx = {geometry.baseline:g} m is '
            f'outside [{MIN_BASELINE_M:g}, {MAX_BASELINE_M:g}] m: Tx must be −fx·B with B in '
            f'metres (got P_right[0, 3] = {float(right[0, 3]):g} at fx = {geometry.fx:g}; '
            'B itself, or B in millimetres?)'
        )
    return geometry


def image_camera_info(info: Any, width: int, height: int) -> CameraInfo:
    """A camera info for the ``width`` × ``height`` images as they arrive: binning and region
    of interest folded into the size, K and P (:func:`camera_info_to_geometry`'s rule), binning
    1 and no ROI, no header (:func:`scale_camera_info` gives the output's). When the images
    have its calibration size, K and P as they are (that rule again) and binning and ROI
    cleared all the same, or ``image_geometry`` would read the published info as images of
    another size or principal point; the message itself when it has neither. For consumers of
    the outputs, which have the images' size. Reads rclpy and ``rosbags`` messages alike.

    Raises:
        InputError: An info that does not describe images of that size (as
            :func:`camera_info_to_geometry`).
    """
    _, projection = image_projection(info, 'camera info', (width, height))
    k = np.array(info.k, dtype=np.float64).reshape(3, 3)
    if (int(info.width), int(info.height)) == (width, height):
        # K and P as they are (image_projection's rule); binning and ROI must not say more.
        roi = info.roi
        whole = (int(roi.width), int(roi.height)) in ((0, 0), (width, height))
        if max(int(info.binning_x), int(info.binning_y)) <= 1 and whole and not (
            int(roi.x_offset) or int(roi.y_offset)
        ):
            return info
    else:
        k = fold(k, info)
    return CameraInfo(
        width=width,
        height=height,
        distortion_model=info.distortion_model,
        d=list(info.d),
        k=k.ravel().tolist(),
        r=list(info.r),
        p=projection.ravel().tolist(),
    )


def stereo_pair_from_messages(
    left_msg: Any, right_msg: Any, left_info: Any, right_info: Any
) -> tuple[np.ndarray, np.ndarray, StereoGeometry]:
    """Decode a matched set of stereo messages into the pipeline's inputs.

    The node and the bag replay both use it, so a frame the node would drop is dropped by the
    replay for the same reason. Only message fields are read: rclpy and ``rosbags`` messages
    both work.

    Returns:
        ``(left, right, geometry)``: uint8 images (RGB or gray) and the stereo geometry at
        their resolution.

    Raises:
        InputError: Unknown encoding, images of different sizes or bit depths, or camera
            infos that do not fit them or are not a rectified pair
            (:func:`camera_info_to_geometry`).
    """
    left = image_to_array(left_msg, 'left image')
    right = image_to_array(right_msg, 'right image')
    if left.shape[:2] != right.shape[:2]:
        raise InputError(
            f'left and right images must have the same size; got '
            f'{left.shape[1]}×{left.shape[0]} and {right.shape[1]}×{right.shape[0]}'
        )
    left, right = pair_to_uint8(left, right)
    height, width = left.shape[:2]
    return left, right, camera_info_to_geometry(left_info, right_info, width, height)


def scale_camera_info(info: CameraInfo, factor: int, header: Header) -> CameraInfo:
    """The camera info of images shrunk by an integer factor (crop to a multiple, then shrink).

    Matches :class:`~cva_confidence_ros.pipeline.StereoPipeline`'s downsampling: rows and
    columns beyond a multiple of ``factor`` are cropped at the bottom and right, then blocks of
    ``factor``×``factor`` are averaged, so a pixel coordinate ``x`` becomes
    ``(x + 0.5) / factor − 0.5``. Focal lengths and ``P[0, 3]`` (= −fx·B) scale by 1/factor.

    ``info`` is read as REP 104 and ``image_geometry`` have it (binning and region of interest
    of its calibration size, :func:`~cva_confidence_ros.camera_info.image_projection`): the
    images it describes are ``roi`` divided by the binning. Binning and ROI are folded into K
    and P before the shrink, and the result has neither (binning as given when it was 0 or 1,
    an all-zero ROI): K, P, width and height are those of the shrunk images themselves, K and
    P scaled to a third row of ``(0, 0, 1, …)`` (read as entries, as consumers read them, a
    homogeneous ``w·P`` gives w times fx and cx). Kept
    as binning (``binning × factor``), ``image_geometry``'s ``x / binning`` would read every
    pixel ``(factor − 1) / (2 · factor)`` px off the block averages' centres, and an ROI offset
    by a non-multiple of ``factor`` cannot be written at all. Images of the calibration size
    whose info's ROI marks something else (the valid area) go through
    :func:`image_camera_info` first, as the node does.

    Args:
        info: Camera info of the input images.
        factor: 1, 2 or 4 (≥ 1).
        header: Header of the output (the left image's).

    Returns:
        A new ``CameraInfo`` for ``(w // factor) × (h // factor)`` images, ``w`` × ``h`` the
        size ``info`` describes.

    Raises:
        ConfigError: A ``factor`` that is not an integer ≥ 1.
        InputError: A ``factor`` larger than the images' width or height (no pixel is left),
            or an info whose size, ROI or binning describe no images (as
            :func:`~cva_confidence_ros.camera_info.image_projection`).
    """
    if not is_int(factor) or factor < 1:
        raise ConfigError(
            f'downsample factor must be an integer >= 1; got {type(factor).__name__} {factor!r}'
        )
    factor = int(factor)
    (width, height), p = image_projection(info, 'camera info')
    if width // factor == 0 or height // factor == 0:
        raise InputError(
            f'camera info of {width}×{height} px leaves no pixel when shrunk by {factor}'
        )
    scale = 1.0 / factor
    out = CameraInfo(
        header=header,
        height=height // factor,
        width=width // factor,
        distortion_model=info.distortion_model,
        d=list(info.d),
        # 0 and 1 both mean no binning; any other is folded into K and P.
        binning_x=min(int(info.binning_x), 1),
        binning_y=min(int(info.binning_y), 1),
    )
    # Homogeneous, as P (image_projection): consumers read fx and cx off K as entries.
    k = unit_projection(fold(np.array(info.k, dtype=np.float64).reshape(3, 3), info))
    for matrix in (k, p):
        # Rows 0 and 1 of K and P are pixel coordinates times the third row's value.
        matrix[:2] = matrix[:2] * scale + (scale - 1.0) * 0.5 * matrix[2]
    out.k = k.ravel().tolist()
    out.r = list(info.r)
    out.p = p.ravel().tolist()
    out.roi = RegionOfInterest(do_rectify=bool(info.roi.do_rectify))
    return out


def disparity_to_message(
    disparity: np.ndarray,
    header: Header,
    geometry: StereoGeometry,
    max_disparity: int,
    delta_d: float = 1.0,
) -> DisparityImage:
    """Fill a ``stereo_msgs/DisparityImage`` the way ``stereo_image_proc`` does.

    Args:
        disparity: (H, W) float32 raw disparity ``x_left − x_right``, NaN = invalid.
        header: Header of the left image (stamp and optical frame).
        geometry: Stereo geometry at the disparity's resolution.
        max_disparity: Cost-volume depth D; raw disparities 0 … D − 1 were searched.
        delta_d: Smallest disparity step (1 for integer WTA, 0 for continuous sub-pixel values).

    Returns:
        The message; its image holds ``d + Δ`` (Δ = cx_right − cx_left) and
        ``min_disparity − 1`` where ``disparity`` is NaN.
    """
    offset = geometry.disparity_offset
    min_d = float(offset)
    shifted = disparity.astype(np.float32) + np.float32(offset)
    shifted = np.where(np.isfinite(shifted), shifted, np.float32(min_d - 1.0)).astype(np.float32)
    height, width = disparity.shape
    left_border = min(max(int(max_disparity) - 1, 0), width)
    return DisparityImage(
        header=header,
        image=array_to_image(shifted, header),
        f=float(geometry.fx),
        t=float(geometry.baseline),
        valid_window=RegionOfInterest(
            x_offset=left_border, y_offset=0, height=height, width=width - left_border
        ),
        min_disparity=min_d,
        max_disparity=float(max_disparity - 1 + offset),
        delta_d=float(delta_d),
    )


def disparity_from_message(msg: DisparityImage) -> np.ndarray:
    """(H, W) float32 disparity of a ``DisparityImage``; NaN below ``min_disparity``.

    Raises:
        InputError: An image that is not 32FC1 (see :func:`float_image_to_array`), or a
            ``min_disparity`` that is NaN or +inf (every pixel would read as unknown).
    """
    lowest = float(msg.min_disparity)
    if math.isnan(lowest) or lowest == math.inf:
        raise InputError(
            f'disparity image: min_disparity must be a number below +inf (the smallest valid '
            f'disparity); got {lowest}, which would leave every pixel unknown'
        )
    values = float_image_to_array(msg.image, 'disparity image')
    with np.errstate(invalid='ignore'):
        invalid = ~(values >= msg.min_disparity)
    values[invalid] = np.nan
    return values


# The layouts this package writes: x, y, z, rgb (and confidence), float32 in a row.
_CLOUD_DTYPES = (CLOUD_DTYPE, CLOUD_CONFIDENCE_DTYPE)

# PointField datatype → numpy little-endian type.
_POINT_FIELD_TYPES = {
    PointField.INT8: 'i1',
    PointField.UINT8: 'u1',
    PointField.INT16: '<i2',
    PointField.UINT16: '<u2',
    PointField.INT32: '<i4',
    PointField.UINT32: '<u4',
    PointField.FLOAT32: '<f4',
    PointField.FLOAT64: '<f8',
}
_NUMPY_POINT_FIELDS = {np.dtype(code): datatype for datatype, code in _POINT_FIELD_TYPES.items()}


def _point_fields(dtype: np.dtype) -> list[PointField]:
    fields = []
    for name in dtype.names or ():
        assert dtype.fields is not None  # a dtype with field names has a fields mapping
        base, offset = dtype.fields[name][:2]
        count = int(np.prod(base.shape)) if base.shape else 1
        datatype = _NUMPY_POINT_FIELDS.get(base.base.newbyteorder('<'))
        if datatype is None or base.base.byteorder == '>':
            raise InputError(f'point field {name!r} has no PointField type: {base}')
        fields.append(PointField(name=name, offset=offset, datatype=datatype, count=count))
    return fields


def cloud_to_message(cloud: np.ndarray, header: Header) -> PointCloud2:
    """Encode a :data:`~cva_confidence_ros.pointcloud.CLOUD_DTYPE` (or
    :data:`~cva_confidence_ros.pointcloud.CLOUD_CONFIDENCE_DTYPE`) array as ``PointCloud2``.

    Args:
        cloud: (H, W) organised cloud (NaN points kept, ``is_dense`` False) or (N,) dense.
        header: Header of the left image.

    Raises:
        InputError: Another dtype or dimensionality.
    """
    if cloud.dtype not in _CLOUD_DTYPES:
        raise InputError(
            f'cloud dtype must be {CLOUD_DTYPE} or {CLOUD_CONFIDENCE_DTYPE}; got {cloud.dtype}'
        )
    return records_to_point_cloud(cloud, header)


def cloud_to_array(msg: PointCloud2) -> np.ndarray:
    """Decode a ``PointCloud2`` written by :func:`cloud_to_message` into (H, W) points.

    Raises:
        InputError: A layout other than x, y, z, rgb (and confidence) float32 at offsets 0, 4,
            8, 12 (16), or data that does not fit it.
    """
    layout = [(f.name, f.offset, f.datatype, f.count) for f in msg.fields]
    for dtype in _CLOUD_DTYPES:
        expected = [(f.name, f.offset, f.datatype, f.count) for f in _point_fields(dtype)]
        if layout == expected and msg.point_step == dtype.itemsize and not msg.is_bigendian:
            return point_cloud_to_records(msg).astype(dtype)
    raise InputError(
        f'cloud must have fields x, y, z, rgb (and confidence), float32, point_step '
        f'{CLOUD_DTYPE.itemsize} ({CLOUD_CONFIDENCE_DTYPE.itemsize}); got {layout} and '
        f'{msg.point_step}'
    )


def point_cloud_to_records(msg: PointCloud2) -> np.ndarray:
    """Decode any little-endian ``PointCloud2`` into an (H, W) structured array.

    The dtype has one field per ``PointField`` at its offset (``count`` > 1 becomes a
    sub-array) and ``point_step`` as its item size, so padding bytes and fields of other
    producers survive a round trip through :func:`records_to_point_cloud`; padding at the end
    of a row (``row_step`` > ``point_step`` × ``width``) is dropped.

    A field of ``count`` 0 declares no data and is left out, as are PCL's padding fields named
    ``_`` (older clouds declare one per gap, several of them): their bytes stay as padding. An
    empty cloud (height or width 0) gives an empty array with the fields it declares; its
    data must be empty (or ``row_step`` × ``height`` bytes of padding).

    Raises:
        InputError: Big-endian data, a ``point_step`` of 0, an unknown datatype, duplicate or
            overlapping-the-end fields, a ``row_step`` shorter than a row, or another number
            of data bytes than the header says (``row_step`` × ``height``).
    """
    if msg.is_bigendian:
        raise InputError('big-endian PointCloud2 data is not supported')
    height, width, step, row_step = msg.height, msg.width, msg.point_step, msg.row_step
    empty = height * width == 0
    if step == 0 and not empty:
        raise InputError(f'point_step is 0 for a cloud of {height}×{width} points')
    names, formats, offsets, ends = [], [], [], []
    for field in msg.fields:
        code = _POINT_FIELD_TYPES.get(field.datatype)
        if code is None:
            raise InputError(f'point field {field.name!r} has unknown datatype {field.datatype}')
        if field.name == '_':
            continue  # PCL's padding field (ROS 1 clouds may hold several): padding bytes
        if field.name in names:
            raise InputError(f'point field {field.name!r} appears twice')
        count = int(field.count)
        if count == 0:
            continue  # a declared field of no elements: nothing to read
        size = np.dtype(code).itemsize * count
        if field.offset + size > step and not empty:
            raise InputError(
                f'point field {field.name!r} (offset {field.offset}, {size} bytes) does not fit '
                f'in point_step {step}'
            )
        names.append(field.name)
        formats.append(code if count == 1 else (code, (count,)))
        offsets.append(field.offset)
        ends.append(field.offset + size)
    if row_step < step * width and not empty:
        raise InputError(f'row_step {row_step} is shorter than width × point_step {step * width}')
    data = np.frombuffer(msg.data, dtype=np.uint8)
    if data.size != row_step * height and not (empty and data.size == 0):
        # More is as wrong as less: a width, height or row_step that does not fit the data
        # (the rest would be dropped unseen), an empty cloud's included (its data must be
        # empty, or its rows of row_step of padding).
        raise InputError(
            f'cloud data holds {data.size} bytes; {height} rows of row_step {row_step} need '
            f'{row_step * height}'
        )
    if empty:
        itemsize = max([step, *ends])
        dtype = np.dtype(
            {'names': names, 'formats': formats, 'offsets': offsets, 'itemsize': itemsize}
        )
        return np.empty((height, width), dtype)
    dtype = np.dtype({'names': names, 'formats': formats, 'offsets': offsets, 'itemsize': step})
    rows = data[: row_step * height].reshape(height, row_step)[:, : step * width]
    return np.ascontiguousarray(rows).view(dtype).reshape(height, width)


def records_to_point_cloud(records: np.ndarray, header: Header) -> PointCloud2:
    """Encode an (H, W) organised or (N,) dense structured point array as ``PointCloud2``.

    ``is_dense`` is set when no point has a NaN or infinite x, y or z (always so for a
    one-row cloud of kept points).

    Raises:
        InputError: Not a structured array, not 1- or 2-D, or a field type PointField lacks.
    """
    if not isinstance(records, np.ndarray) or records.dtype.names is None:
        raise InputError(f'points must be a structured numpy array; got {type(records).__name__}')
    if records.ndim == 2:
        height, width = records.shape
    elif records.ndim == 1:
        height, width = 1, records.shape[0]
    else:
        raise InputError(f'cloud must be (H, W) or (N,); got shape {records.shape}')
    is_dense = all(
        bool(np.isfinite(records[name]).all())
        for name in ('x', 'y', 'z')
        if name in records.dtype.names
    )
    return PointCloud2(
        header=header,
        height=height,
        width=width,
        fields=_point_fields(records.dtype),
        is_bigendian=False,
        point_step=records.dtype.itemsize,
        row_step=records.dtype.itemsize * width,
        data=np.ascontiguousarray(records).tobytes(),
        is_dense=is_dense,
    )

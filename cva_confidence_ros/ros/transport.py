"""``image_transport``'s ``compressed`` and ``compressedDepth`` formats, written without it.

The C++ ``image_transport`` advertises every transport of an image topic beside the raw one
(``<topic>/compressed``, ``<topic>/compressedDepth``) and encodes only while someone listens;
rclpy has no such publisher, so the node does the same by hand for the two outputs that are
worth sending over a thin link:

* ``confidence_overlay/compressed``: the rgb8 overlay as JPEG (or PNG), ``format``
  ``"rgb8; jpeg compressed bgr8"`` as ``compressed_image_transport`` writes it, so that rviz,
  Foxglove, ``image_transport republish`` and :func:`~cva_confidence_ros.ros.convert.
  compressed_image_to_array` decode it.
* ``depth/compressedDepth``: the depth image as ``compressed_depth_image_transport`` lays it out:
  a 12-byte little-endian header (int32 ``INV_DEPTH`` = 0, float32 ``depthParam[2]``) followed
  by a 16-bit PNG; ``format`` ``"32FC1; compressedDepth png"`` or ``"16UC1; compressedDepth
  png"``. A 32FC1 depth ``z`` (metres) travels as the inverse-depth code ``q = A / z + B``
  truncated to uint16, with ``A = Q·(Q + 1)`` and ``B = 1 − A / depth_max`` for the
  quantisation ``Q`` (default 100) and the largest depth ``depth_max`` (default 10 m): the
  receiver gets ``z = A / (q − B)``, exact to ≈ ``z² / A`` (1 cm at 10 m, 0.1 mm at 1 m with the
  defaults); ``q = 0`` is no depth (NaN, and every depth ≥ ``depth_max``). 16UC1 millimetres
  travel as they are, those above ``depth_max`` set to 0 (no depth), as the C++ plugin does.
  Depths below ``A / (65535 − B)`` (0.15 m with the defaults), which the code cannot hold, are
  sent as that nearest depth rather than wrapped around.

:func:`compressed_depth_to_array` decodes the format back (for tests, tools and subscribers
without ``image_transport``). It reads the PNG's header first (:func:`png_header`) and refuses
one that names more than :data:`MAX_PNG_PIXELS` pixels or anything but one 16-bit channel
before OpenCV allocates the image: a message of some ten kilobytes can name gigabytes.
"""

from __future__ import annotations

import math
import struct
from typing import Any

import numpy as np
from sensor_msgs.msg import CompressedImage, Image

from cva_confidence_ros.checks import is_int, is_real
from cva_confidence_ros.errors import InputError

__all__ = [
    'COMPRESSED_DEPTH_HEADER',
    'MAX_PNG_PIXELS',
    'compressed_depth_to_array',
    'compressed_depth_values',
    'depth_image_to_compressed_depth',
    'png_header',
    'rgb_to_compressed',
]

#: The ``ConfigHeader`` of ``compressed_depth_image_transport``: int32 format (0 =
#: ``INV_DEPTH``), float32 ``depthParam[0]`` (A), float32 ``depthParam[1]`` (B).
COMPRESSED_DEPTH_HEADER = struct.Struct('<iff')
_INV_DEPTH = 0
_CODE_MAX = np.iinfo(np.uint16).max
#: The most pixels :func:`compressed_depth_to_array` decodes by default: 2**25, an 8K UHD
#: frame (7680×4320) fits. A PNG names its size in its first bytes, and zlib packs a
#: uniform image about 1000:1, so without a bound a message of under a megabyte made OpenCV
#: allocate and fill gigabytes.
MAX_PNG_PIXELS = 1 << 25
_PNG_SIGNATURE = b'\x89PNG\r\n\x1a\n'
#: The first chunk of every PNG: length 13, type IHDR, width, height, bit depth, colour type.
_PNG_IHDR = struct.Struct('>I4sIIBB')
_PNG_COLOUR_TYPES = {0: 'gray', 2: 'RGB', 3: 'palette', 4: 'gray + alpha', 6: 'RGBA'}


def png_header(data: bytes, name: str = 'image') -> tuple[int, int, int, int]:
    """``(width, height, bit_depth, colour_type)`` from a PNG's IHDR, without decoding it.

    Raises:
        InputError: ``data`` does not start with the PNG signature and an IHDR chunk, or that
            names a zero width or height.
    """
    if data[:len(_PNG_SIGNATURE)] != _PNG_SIGNATURE:
        raise InputError(f'{name} does not start with the PNG signature (starts {data[:8]!r})')
    if len(data) < len(_PNG_SIGNATURE) + _PNG_IHDR.size:
        raise InputError(f'{name}: {len(data)} bytes, too short for a PNG header')
    length, kind, width, height, bit_depth, colour_type = _PNG_IHDR.unpack_from(
        data, len(_PNG_SIGNATURE)
    )
    if kind != b'IHDR' or length != 13:
        raise InputError(
            f'{name}: the PNG does not begin with a 13-byte IHDR chunk (got {kind!r}, {length})'
        )
    if width == 0 or height == 0:
        raise InputError(f'{name}: the PNG header names an empty {width}×{height} image')
    return width, height, bit_depth, colour_type


def rgb_to_compressed(
    rgb: np.ndarray, header: Any, image_format: str = 'jpeg', jpeg_quality: int = 95,
    png_level: int = 9,
) -> CompressedImage:
    """An (H, W, 3) uint8 RGB array as ``compressed_image_transport`` sends an rgb8 image.

    Args:
        rgb: (H, W, 3) uint8, RGB order.
        header: The message header.
        image_format: ``jpeg`` or ``png``.
        jpeg_quality: 1–100 (JPEG only).
        png_level: zlib level 0–9 (PNG only).

    Raises:
        InputError: Not an (H, W, 3) uint8 array (or an empty one), another format, or a level
            out of range or not an integer.
    """
    import cv2

    if not isinstance(rgb, np.ndarray):
        # A list or an image message raised AttributeError ('list' object has no attribute
        # 'ndim') instead of saying what is wrong.
        raise InputError(
            f'an rgb8 image must be an (H, W, 3) uint8 numpy array; got {type(rgb).__name__}'
        )
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8 or rgb.size == 0:
        raise InputError(
            f'an rgb8 image must be (H, W, 3) uint8, H and W > 0; got {rgb.dtype} {rgb.shape}'
        )
    if image_format == 'jpeg':
        # True passed as 1 (the worst quality) and 50.7 as 50 before.
        if not (is_int(jpeg_quality) and 1 <= jpeg_quality <= 100):
            raise InputError(f'jpeg_quality must be in [1, 100], an integer; got {jpeg_quality!r}')
        params = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)]
    elif image_format == 'png':
        if not (is_int(png_level) and 0 <= png_level <= 9):
            raise InputError(f'png_level must be in [0, 9], an integer; got {png_level!r}')
        params = [cv2.IMWRITE_PNG_COMPRESSION, int(png_level)]
    else:
        raise InputError(f"image_format must be 'jpeg' or 'png'; got {image_format!r}")
    ok, data = cv2.imencode(f'.{image_format}', cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), params)
    if not ok:
        raise InputError(f'OpenCV could not encode a {rgb.shape[1]}×{rgb.shape[0]} {image_format}')
    return CompressedImage(
        header=header, format=f'rgb8; {image_format} compressed bgr8', data=data.tobytes()
    )


def compressed_depth_values(
    depth: np.ndarray, depth_max: float = 10.0, depth_quantization: float = 100.0
) -> tuple[np.ndarray, float, float]:
    """The uint16 inverse-depth codes of a float depth map and the header's ``A`` and ``B``.

    Args:
        depth: (H, W) metres; NaN, non-positive and ≥ ``depth_max`` = no depth (code 0).
        depth_max: Largest depth sent, metres (> 0).
        depth_quantization: ``Q`` (> 0); larger = finer near depths, fewer of them.

    Returns:
        ``(codes, A, B)``, with ``A`` and ``B`` rounded to float32 as the header holds them.

    Raises:
        InputError: ``depth_max`` or ``depth_quantization`` not a positive finite number, or
            so far apart that float32 (the header's type) cannot hold a finite ``A`` > 0 and
            ``B`` < 1, which every code needs to decode to a positive depth.
    """
    for name, value in (('depth_max', depth_max), ('depth_quantization', depth_quantization)):
        if not (is_real(value) and np.isfinite(value) and value > 0):
            raise InputError(f'{name} must be a positive number; got {value!r}')
    with np.errstate(over='ignore', divide='ignore', invalid='ignore'):
        a = np.float32(depth_quantization) * (np.float32(depth_quantization) + np.float32(1.0))
        b = np.float32(1.0) - a / np.float32(depth_max)
    # Else inf in the header and NaN codes (cast to anything) in the PNG, or codes that decode
    # to infinite or negative depths (what compressed_depth_to_array refuses).
    if not (np.isfinite(a) and a > 0 and np.isfinite(b) and b < 1):
        raise InputError(
            f'depth_quantization {depth_quantization:g} and depth_max {depth_max:g} give '
            f'A = Q·(Q + 1) = {a:g} and B = 1 − A / depth_max = {b:g} in float32; a '
            'compressedDepth header needs a finite A > 0 and B < 1'
        )
    depth = np.asarray(depth, dtype=np.float32)
    with np.errstate(invalid='ignore', divide='ignore', over='ignore'):
        sent = (depth > 0) & (depth < np.float32(depth_max))
        codes = np.zeros(depth.shape, dtype=np.uint16)
        # float32 throughout and truncation towards zero, as the C++ plugin computes it.
        values = a / depth[sent] + b
        codes[sent] = np.minimum(values, np.float32(_CODE_MAX)).astype(np.uint16)
    return codes, float(a), float(b)


def depth_image_to_compressed_depth(
    msg: Image, depth_max: float = 10.0, depth_quantization: float = 100.0, png_level: int = 9
) -> CompressedImage:
    """A REP 118 depth ``Image`` (32FC1 metres or 16UC1 millimetres) as ``compressedDepth``.

    Raises:
        InputError: Another encoding, a buffer that does not fit the size, a bad parameter
            (``png_level`` not an integer in [0, 9] included).
    """
    import cv2

    from cva_confidence_ros.ros.convert import depth_image_to_array

    if msg.encoding not in ('32FC1', '16UC1'):
        raise InputError(
            f'compressedDepth takes 32FC1 or 16UC1 depth images; got {msg.encoding!r}'
        )
    if not (is_int(png_level) and 0 <= png_level <= 9):
        raise InputError(f'png_level must be in [0, 9], an integer; got {png_level!r}')
    metres = depth_image_to_array(msg)
    if msg.encoding == '32FC1':
        codes, a, b = compressed_depth_values(metres, depth_max, depth_quantization)
    else:
        if not (is_real(depth_max) and np.isfinite(depth_max) and depth_max > 0):
            raise InputError(f'depth_max must be a positive number; got {depth_max!r}')
        with np.errstate(invalid='ignore'):
            millimetres = np.where(np.isfinite(metres), np.rint(metres * 1000.0), 0.0)
        # The plugin's cut: above depth_max in whole millimetres. 16UC1 holds no more than
        # 65535 mm, so a larger depth_max cuts nothing (and int() of it could overflow).
        millimetres[millimetres > math.floor(min(depth_max * 1000.0, _CODE_MAX))] = 0.0
        codes, a, b = millimetres.astype(np.uint16), 0.0, 0.0
    ok, png = cv2.imencode('.png', codes, [cv2.IMWRITE_PNG_COMPRESSION, int(png_level)])
    if not ok:
        raise InputError(f'OpenCV could not encode a {msg.width}×{msg.height} 16-bit PNG')
    return CompressedImage(
        header=msg.header,
        format=f'{msg.encoding}; compressedDepth png',
        data=COMPRESSED_DEPTH_HEADER.pack(_INV_DEPTH, a, b) + png.tobytes(),
    )


def compressed_depth_to_array(
    msg: Any, name: str = 'depth', max_pixels: int = MAX_PNG_PIXELS
) -> np.ndarray:
    """Decode a ``compressedDepth`` message into metres: (H, W) float32, NaN = no depth.

    Both encodings are read (32FC1 inverse-depth codes, 16UC1 millimetres, 0 = none); so are
    the older messages whose format names no compression (PNG).

    Args:
        msg: The ``sensor_msgs/CompressedImage``.
        name: What the error messages call it.
        max_pixels: The largest image decoded (width × height in the PNG header, read
            before anything is allocated).

    Raises:
        InputError: Not a compressedDepth format, a compression other than png named in it
            (an RVL payload included), data that is too short or
            is not a one-channel 16-bit PNG (checked in its header before decoding: another
            image format, bit depth or colour type), a PNG of more than ``max_pixels`` pixels
            or that does not decode (one larger than OpenCV reads included), ``max_pixels`` not
            a positive integer, or a 32FC1 header whose ``A`` and ``B`` give no positive
            depths (``A`` ≤ 0, ``B`` ≥ 1 or either not finite) or depths beyond float32
            (``A / (1 − B)``, the depth of code 1).
    """
    import cv2

    text = str(msg.format)
    encoding, _, rest = text.partition(';')
    encoding = encoding.strip()
    if rest and 'compresseddepth' not in rest.lower().replace(' ', ''):
        raise InputError(f'{name} is not a compressedDepth image (format {text!r})')
    if 'rvl' in rest.lower():
        raise InputError(f'{name}: RVL compressedDepth is not supported (format {text!r})')
    # What follows "compressedDepth" names the compression: png, or nothing in the older
    # plugin's messages (PNG too). Anything else ("compressedDepth jpeg") the C++ plugin refuses
    # as an unsupported format; it was decoded here as if it said png.
    compression = rest.lower().replace(' ', '').partition('compresseddepth')[2]
    if compression not in ('', 'png'):
        raise InputError(
            f'{name}: compressedDepth compression {compression!r} is not supported; expected '
            f'png (format {text!r})'
        )
    if encoding not in ('32FC1', '16UC1'):
        raise InputError(
            f'{name}: compressedDepth of {encoding!r}; expected 32FC1 or 16UC1 (format {text!r})'
        )
    if not (is_int(max_pixels) and max_pixels > 0):
        raise InputError(f'max_pixels must be a positive integer; got {max_pixels!r}')
    data = bytes(msg.data)
    if len(data) <= COMPRESSED_DEPTH_HEADER.size:
        raise InputError(
            f'{name}: {len(data)} bytes of compressedDepth data, fewer than its '
            f'{COMPRESSED_DEPTH_HEADER.size}-byte header and an image'
        )
    _, a, b = COMPRESSED_DEPTH_HEADER.unpack_from(data)
    # The size, depth and colour type from the PNG's header before OpenCV allocates anything
    # (and only a PNG: OpenCV decodes PGM, TIFF and more by their own signatures).
    try:
        width, height, bit_depth, colour_type = png_header(
            data[COMPRESSED_DEPTH_HEADER.size:], f'{name}: the compressedDepth payload'
        )
    except InputError as error:
        raise InputError(f'{error}; it is not a one-channel 16-bit PNG') from None
    if bit_depth != 16 or colour_type != 0:
        kind = _PNG_COLOUR_TYPES.get(colour_type, f'colour type {colour_type}')
        raise InputError(
            f'{name}: the compressedDepth payload is not a one-channel 16-bit PNG '
            f'({bit_depth}-bit {kind}, {width}×{height})'
        )
    if width * height > max_pixels:
        raise InputError(
            f'{name}: the compressedDepth payload does not decode as a 16-bit PNG of at most '
            f'{max_pixels} pixels: its header names {width}×{height} = {width * height}'
        )
    try:
        codes = cv2.imdecode(
            np.frombuffer(data, dtype=np.uint8, offset=COMPRESSED_DEPTH_HEADER.size),
            cv2.IMREAD_UNCHANGED,
        )
    except cv2.error as error:
        # A PNG header naming more pixels than OpenCV reads (2**30) raises instead of None.
        raise InputError(
            f'{name}: the compressedDepth payload does not decode as a 16-bit PNG '
            f'(OpenCV: {getattr(error, "err", None) or error})'
        ) from error
    if codes is None or codes.dtype != np.uint16 or codes.ndim != 2:
        raise InputError(f'{name}: the compressedDepth payload is not a one-channel 16-bit PNG')
    # Every valid encoder writes A = Q·(Q + 1) > 0 and B = 1 − A / depth_max < 1, so that each
    # code q ≥ 1 decodes to a positive depth A / (q − B); another header (corrupt, or the
    # zeros of a 16UC1 one) would give negative, zero or infinite depths.
    if encoding == '32FC1' and not (np.isfinite(a) and a > 0 and np.isfinite(b) and b < 1):
        raise InputError(
            f'{name}: the compressedDepth header holds A = {a:g}, B = {b:g}; a 32FC1 one needs '
            'a finite A > 0 and B < 1'
        )
    if encoding == '32FC1':
        # The farthest depth, that of code 1: A / (1 − B) = depth_max for every valid encoder;
        # a corrupt header (A = 3e38, B = 0.9999999) gave inf for every pixel, with a warning.
        with np.errstate(over='ignore'):
            farthest = np.float32(a) / (np.float32(1.0) - np.float32(b))
        if not np.isfinite(farthest):
            raise InputError(
                f'{name}: the compressedDepth header holds A = {a:g}, B = {b:.9g}, whose depths '
                f'A / (q − B) reach {float(farthest):g}, beyond float32'
            )
    depth = np.full(codes.shape, np.nan, dtype=np.float32)
    sent = codes > 0
    if encoding == '32FC1':
        depth[sent] = np.float32(a) / (codes[sent].astype(np.float32) - np.float32(b))
    else:
        depth[sent] = codes[sent].astype(np.float32) / np.float32(1000.0)
    return depth

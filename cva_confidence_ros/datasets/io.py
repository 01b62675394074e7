"""File formats of stereo data sets: PFM, images, encoded disparity PNGs, calibration files.

Readers return arrays in the package conventions: images uint8 RGB (H, W, 3) or gray (H, W),
disparities float32 (H, W) with NaN where unknown.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
import math
from pathlib import Path
import re
import warnings

import cv2
import numpy as np

from cva_confidence_ros.errors import ConfigError, DataError, reason

__all__ = [
    'Calibration',
    'MAX_IMAGE_PIXELS',
    'decode_image_file',
    'read_disparity_png',
    'read_image',
    'read_kitti_calibration',
    'read_middlebury_calibration',
    'read_pfm',
    'write_pfm',
]

#: Bytes at the end of a JPEG searched for its end-of-image marker (some writers pad after it).
_JPEG_TAIL = 4096
#: Most pixels an image file may declare (8192 × 8192; ETH3D's largest is 6048 × 4032): a
#: small file can declare far more (a 2.6 MB PNG of 30000 × 30000 decodes to 2.7 GB), and
#: OpenCV's own limit (2^30 pixels) lets that through.
MAX_IMAGE_PIXELS = 2**26


@dataclass(frozen=True)
class Calibration:
    """Pinhole calibration of a rectified stereo pair (left camera).

    Attributes:
        fx: Focal length along x, pixels.
        fy: Focal length along y, pixels.
        cx: Principal point x of the left camera, pixels.
        cy: Principal point y, pixels.
        baseline: Distance between the camera centres, metres.
        doffs: ``cx_right - cx_left`` in pixels (Middlebury); depth is
            ``fx * baseline / (d + doffs)``.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    baseline: float
    doffs: float = 0.0

    def depth(self, disparity: np.ndarray) -> np.ndarray:
        """Depth in metres, ``fx * baseline / (d + doffs)``; NaN where ``d + doffs ≤ 0`` or
        ``d`` is not finite.

        Args:
            disparity: Disparity, any shape, float, NaN or ±inf (Middlebury PFMs) = unknown.

        Returns:
            float32 array of the same shape.
        """
        total = np.asarray(disparity, dtype=np.float64) + self.doffs
        with np.errstate(divide='ignore', invalid='ignore'):
            # An inf disparity is unknown (as Middlebury stores it), not a point at depth 0.
            depth = np.where(
                np.isfinite(total) & (total > 0), self.fx * self.baseline / total, np.nan
            )
        return depth.astype(np.float32)


def _short(text: str, limit: int = 60) -> str:
    return text[:limit] + '…' if len(text) > limit else text


def read_pfm(path: str | Path) -> np.ndarray:
    """Read a Portable Float Map.

    The rows are stored bottom to top and flipped here; a negative scale means little-endian.

    Args:
        path: ``.pfm`` file, ``Pf`` (one channel) or ``PF`` (three channels).

    Returns:
        float32 array (H, W) or (H, W, 3), native byte order, top row first. Values are returned
        as stored (``inf`` included).

    Raises:
        DataError: The file is missing, has a bad header, or too little or too much data.
    """
    path = Path(path)
    try:
        with path.open('rb') as stream:
            magic = stream.readline().strip()
            tokens: list[bytes] = []
            while len(tokens) < 3:
                line = stream.readline()
                if not line:
                    break
                tokens.extend(line.split())
            data = stream.read()
    except OSError as exc:
        raise DataError(f'cannot read PFM file {path}: {exc}') from exc
    if magic not in (b'PF', b'Pf') or len(tokens) != 3:
        raise DataError(
            f'{path} is not a PFM file; expected header "PF|Pf", "W H", "scale"; '
            f'got {_short(repr(magic) + " " + repr(tokens))}'
        )
    try:
        width, height, scale = int(tokens[0]), int(tokens[1]), float(tokens[2])
    except ValueError as exc:
        # Shortened: a corrupt header line can be the whole (binary) file.
        raise DataError(f'{path}: bad PFM size or scale {_short(repr(tokens))}') from exc
    channels = 3 if magic == b'PF' else 1
    count = width * height * channels
    # The sign of the scale is the byte order: a NaN one has none (a corrupt header).
    if (
        width <= 0
        or height <= 0
        or not math.isfinite(scale)
        or scale == 0
        or len(data) < 4 * count
    ):
        raise DataError(
            f'{path}: expected {_short(str(width))}×{_short(str(height))}×{channels} float32 '
            f'values and a finite, non-zero scale; got {len(data) // 4} values, scale {scale}'
        )
    if len(data) >= 4 * (count + 1):
        # A whole value or more past the end: the header does not describe the data (a colour
        # map labelled 'Pf', a wrong size), which would otherwise be read as a scrambled map.
        raise DataError(
            f'{path}: header {magic.decode()} {width}×{height} declares {count} float32 values; '
            f'the file holds {len(data) // 4} (a wrong size or channel count)'
        )
    dtype = np.dtype('<f4' if scale < 0 else '>f4')
    array = np.frombuffer(data, dtype=dtype, count=count)
    shape = (height, width, 3) if channels == 3 else (height, width)
    return np.flipud(array.reshape(shape)).astype(np.float32)


def write_pfm(path: str | Path, array: np.ndarray, scale: float = 1.0) -> None:
    """Write a float array as a little-endian PFM (rows bottom to top, as the format wants).

    Args:
        path: Output file.
        array: (H, W) or (H, W, 3) real (float, integer or bool) array; converted to float32
            (NaN and ±inf are written as they are).
        scale: Absolute value of the header scale (stored negative for little-endian).

    Raises:
        DataError: Bad shape, dtype (complex, strings, objects), values that float32 cannot
            hold (finite ones that would become ±inf) or scale, or the file cannot be written.
    """
    array = np.asarray(array)
    if not (
        np.issubdtype(array.dtype, np.floating)
        or np.issubdtype(array.dtype, np.integer)
        or array.dtype == np.bool_
    ):
        # Complex values lost their imaginary part (a warning only), strings raised ValueError.
        raise DataError(f'PFM holds real numbers; got dtype {array.dtype}')
    with np.errstate(over='ignore'):
        values = array.astype(np.float32)
    overflow = np.isinf(values) & np.isfinite(array)
    if overflow.any():
        # Written as ±inf, which reads back as 'unknown' (Middlebury), not as the value.
        raise DataError(
            f'PFM stores float32: {int(overflow.sum())} finite value(s) beyond ±3.4e38 would '
            f'be written as inf (largest {float(np.abs(array[overflow]).max()):g})'
        )
    array = values
    if not (array.ndim == 2 or (array.ndim == 3 and array.shape[2] == 3)):
        raise DataError(f'PFM holds (H, W) or (H, W, 3) arrays; got shape {array.shape}')
    if array.shape[0] == 0 or array.shape[1] == 0:
        # read_pfm (and other readers) refuse a header of size 0: the file would not read back.
        raise DataError(f'PFM holds at least one pixel; got shape {array.shape}')
    if (
        isinstance(scale, bool)
        or not isinstance(scale, (int, float, np.integer, np.floating))
        or not (scale > 0 and math.isfinite(scale))
    ):
        raise DataError(f'PFM scale must be finite and > 0; got {scale!r}')
    magic = 'PF' if array.ndim == 3 else 'Pf'
    header = f'{magic}\n{array.shape[1]} {array.shape[0]}\n{-scale}\n'.encode('ascii')
    body = np.flipud(array).astype('<f4').tobytes()
    try:
        Path(path).write_bytes(header + body)
    except OSError as exc:
        raise DataError(f'cannot write PFM file {path}: {exc}') from exc


@contextmanager
def _quiet_opencv() -> Iterator[None]:
    """OpenCV's own log lines off while it decodes: our error says what went wrong."""
    logging = cv2.utils.logging
    level = logging.getLogLevel()
    logging.setLogLevel(logging.LOG_LEVEL_SILENT)
    try:
        yield
    finally:
        logging.setLogLevel(level)


def _declared_size(path: Path) -> tuple[int, int] | None:
    """(width, height) from the file's header without decoding it; None when Pillow does
    not know the format (OpenCV then decides) or is not installed (it comes with
    scikit-image)."""
    try:
        from PIL import Image
    except ImportError:
        return None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter('ignore')  # Pillow's own warning for large images
            with Image.open(path) as image:
                return int(image.size[0]), int(image.size[1])
    except Image.DecompressionBombError as exc:  # beyond Pillow's limit, which is above ours
        raise DataError(
            f'{path} declares more than {MAX_IMAGE_PIXELS} pixels, the most read (a corrupt '
            f'header, or a decompression bomb): {reason(exc)}'
        ) from None
    except (OSError, ValueError, SyntaxError, EOFError):
        return None  # not a format Pillow reads, or a damaged header: OpenCV decides


def decode_image_file(path: str | Path) -> np.ndarray | None:
    """The image of ``path`` as OpenCV decodes it (``IMREAD_UNCHANGED``: BGR order, any
    dtype), without OpenCV's log lines; None when it is no image that OpenCV reads.

    Raises:
        DataError: The header declares more than :data:`MAX_IMAGE_PIXELS` pixels (checked
            before any decoding), or the file is a truncated JPEG.
    """
    path = Path(path)
    if not path.is_file():
        return None
    size = _declared_size(path)
    if size is not None and size[0] * size[1] > MAX_IMAGE_PIXELS:
        raise DataError(
            f'{path} declares {size[0]}×{size[1]} pixels, more than {MAX_IMAGE_PIXELS}, the '
            f'most read (a corrupt header, or a decompression bomb)'
        )
    with _quiet_opencv():
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is not None:
        _check_jpeg_complete(path)
    return image


def _check_jpeg_complete(path: Path) -> None:
    """A truncated JPEG decodes without an error in OpenCV (the missing rows come out grey),
    so look for the end-of-image marker that every complete JPEG ends with. Judged by the
    content (a JPEG begins with FF D8), not the name: a PNG named .jpg was refused as a
    truncated JPEG, and a JPEG named .png was not checked."""
    with path.open('rb') as stream:
        if stream.read(2) != b'\xff\xd8':
            return
        stream.seek(max(0, path.stat().st_size - _JPEG_TAIL))
        tail = stream.read()
    if b'\xff\xd9' not in tail:
        raise DataError(f'{path} is a truncated JPEG: no end-of-image marker at its end')


def read_image(path: str | Path) -> np.ndarray:
    """Read an image file as uint8 RGB (H, W, 3) or gray (H, W).

    Alpha channels are dropped; 16-bit images are reduced to 8 bits.

    Raises:
        DataError: The file is missing or not an image, a truncated JPEG, or declares more
            than :data:`MAX_IMAGE_PIXELS` pixels.
    """
    image = decode_image_file(path)
    if image is None:
        raise DataError(f'cannot read image {path}; expected a PNG/JPEG/PPM/PGM file')
    if image.dtype == np.uint16:
        image = np.right_shift(image, 8).astype(np.uint8)
    elif image.dtype != np.uint8:
        raise DataError(f'{path}: expected an 8- or 16-bit image; got dtype {image.dtype}')
    if image.ndim == 3:
        code = cv2.COLOR_BGRA2RGB if image.shape[2] == 4 else cv2.COLOR_BGR2RGB
        image = cv2.cvtColor(image, code)
    return np.ascontiguousarray(image)


def read_disparity_png(path: str | Path, scale: float, bits: int | None = None) -> np.ndarray:
    """Read a disparity stored as integer image, ``d = value / scale``, 0 = unknown.

    Args:
        path: 8- or 16-bit single-channel PNG/PGM (KITTI: 16 bit, scale 256).
        scale: Divisor of the stored values.
        bits: 8 or 16: the bit depth the data set stores (a map saved at the other depth
            would be read with the wrong scale); None = either.

    Returns:
        (H, W) float32 disparity, NaN where the stored value is 0.

    Raises:
        ConfigError: ``scale`` is not finite and > 0, or ``bits`` is not 8, 16 or None.
        DataError: The file is missing, not a single-channel integer image, not of
            ``bits`` bits, or declares more than :data:`MAX_IMAGE_PIXELS` pixels.
    """
    # A scale of 0 gave inf, a negative one negative disparities, NaN no ground truth at all.
    if (
        isinstance(scale, bool)
        or not isinstance(scale, (int, float, np.integer, np.floating))
        or not (math.isfinite(scale) and scale > 0)
    ):
        raise ConfigError(f'disparity PNG scale must be finite and > 0; got {scale!r}')
    if bits not in (None, 8, 16):
        raise ConfigError(f'disparity PNG bits must be 8, 16 or None; got {bits!r}')
    raw = decode_image_file(path)
    if raw is None:
        raise DataError(f'cannot read disparity image {path}')
    if raw.ndim == 3:
        # Some tools save gray disparity maps as 3 equal channels.
        same = np.array_equal(raw[..., 0], raw[..., 1]) and np.array_equal(
            raw[..., 0], raw[..., 2]
        )
        if not same:
            raise DataError(f'{path}: expected a single-channel disparity image; got {raw.shape}')
        raw = raw[..., 0]
    if raw.dtype not in (np.uint8, np.uint16):
        raise DataError(f'{path}: expected an 8- or 16-bit disparity image; got {raw.dtype}')
    if bits is not None and raw.dtype.itemsize * 8 != bits:
        raise DataError(
            f'{path}: expected a {bits}-bit disparity image (disparity × {scale:g}); got '
            f'{raw.dtype.itemsize * 8}-bit, which would be read at the wrong scale'
        )
    disparity = raw.astype(np.float32) / np.float32(scale)
    disparity[raw == 0] = np.nan
    return disparity


def _read_key_values(path: Path) -> dict[str, str]:
    try:
        # utf-8-sig: a file saved by a Windows editor starts with a byte-order mark, which
        # would otherwise stick to the first key ('\ufeffcam0').
        text = path.read_text(encoding='utf-8-sig', errors='replace')
    except OSError as exc:
        raise DataError(f'cannot read calibration file {path}: {exc}') from exc
    values: dict[str, str] = {}
    for line in text.splitlines():
        key, sep, value = line.partition('=' if '=' in line else ':')
        if sep:
            values[key.strip()] = value.strip()
    return values


def _matrix(text: str, path: Path, key: str) -> np.ndarray:
    # Spaces, commas, semicolons and brackets all separate numbers ('[f, 0, cx; 0, f, cy; …]').
    numbers = re.split(r'[\s,;\[\]]+', text.strip())
    try:
        values = [float(value) for value in numbers if value]
    except ValueError as exc:
        raise DataError(f'{path}: {key} is not a list of numbers: {text!r}') from exc
    return np.asarray(values, dtype=np.float64)


def _checked(path: Path, calibration: Calibration) -> Calibration:
    """``calibration`` if it can give depths: finite, focal lengths and baseline > 0.

    Raises:
        DataError: A value that would make every depth 0, negative, infinite or NaN (a zeroed
            or corrupt file, or KITTI keys given right camera first).
    """
    values = (
        calibration.fx, calibration.fy, calibration.cx, calibration.cy, calibration.baseline,
        calibration.doffs,
    )
    if not all(math.isfinite(value) for value in values):
        raise DataError(f'{path}: calibration values must be finite; got {calibration}')
    if not (calibration.fx > 0 and calibration.fy > 0):
        raise DataError(
            f'{path}: focal lengths must be > 0; got fx={calibration.fx}, fy={calibration.fy}'
        )
    if not calibration.baseline > 0:
        raise DataError(
            f'{path}: baseline must be > 0 (the right camera to the right of the left one); '
            f'got {calibration.baseline}'
        )
    return calibration


def read_middlebury_calibration(path: str | Path) -> Calibration:
    """Read a Middlebury / ETH3D ``calib.txt`` (``cam0=[f 0 cx; 0 f cy; 0 0 1]``, ``doffs``,
    ``baseline`` in millimetres).

    Raises:
        DataError: Missing file or fields, or values that give no depth (fx, fy or baseline
            ≤ 0, or not finite).
    """
    path = Path(path)
    values = _read_key_values(path)
    try:
        cam0 = _matrix(values['cam0'], path, 'cam0')
        baseline_mm = float(values['baseline'])
        doffs = float(values.get('doffs', '0') or 0)
    except (KeyError, ValueError) as exc:
        raise DataError(
            f'{path}: expected cam0=[f 0 cx; 0 f cy; 0 0 1], baseline and doffs; missing or bad '
            f'{exc}'
        ) from exc
    if cam0.size != 9:
        raise DataError(f'{path}: cam0 must hold 9 numbers; got {cam0.size}')
    return _checked(
        path,
        Calibration(
            fx=float(cam0[0]),
            fy=float(cam0[4]),
            cx=float(cam0[2]),
            cy=float(cam0[5]),
            baseline=baseline_mm / 1000.0,
            doffs=doffs,
        ),
    )


def read_kitti_calibration(
    path: str | Path, left_key: str = 'P2', right_key: str = 'P3'
) -> Calibration:
    """Read a KITTI calibration with rectified projection matrices of both cameras.

    KITTI 2012 ``calib/<id>.txt`` holds ``P0 … P3`` (the stereo benchmark's gray and colour
    images both take P0/P1: its ``colored_0/1`` are aligned with the gray cameras, P2/P3 are
    the colour cameras of the raw recordings); KITTI 2015 ``calib_cam_to_cam/<id>.txt`` holds
    ``P_rect_02``/``P_rect_03``. The baseline is
    ``(P_left[0, 3] - P_right[0, 3]) / fx``.

    Args:
        path: Calibration file.
        left_key: Key of the left projection matrix.
        right_key: Key of the right projection matrix.

    Raises:
        DataError: Missing file or keys, or values that give no depth (fx, fy or baseline
            ≤ 0, e.g. the keys of the right camera first, or not finite).
    """
    path = Path(path)
    values = _read_key_values(path)
    try:
        left = _matrix(values[left_key], path, left_key).reshape(3, 4)
        right = _matrix(values[right_key], path, right_key).reshape(3, 4)
    except (KeyError, ValueError) as exc:
        raise DataError(
            f'{path}: expected 3×4 projection matrices {left_key!r} and {right_key!r}; '
            f'missing or bad {exc}'
        ) from exc
    fx = float(left[0, 0])
    if not fx > 0:  # checked here too: the baseline is divided by it
        raise DataError(f'{path}: {left_key}[0, 0] (fx) must be > 0; got {fx}')
    return _checked(
        path,
        Calibration(
            fx=fx,
            fy=float(left[1, 1]),
            cx=float(left[0, 2]),
            cy=float(left[1, 2]),
            baseline=float(left[0, 3] - right[0, 3]) / fx,
            doffs=float(right[0, 2] - left[0, 2]),
        ),
    )

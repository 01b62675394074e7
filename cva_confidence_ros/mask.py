"""Ignore masks: pixels of the camera image that are never judged (the robot's own body).

A camera on a robot often sees part of the robot: a bumper in the lower corners, an arm, a
mast, a wiper, a smudge on the lens. Their disparity is right, but they are not obstacles and
must not reach a point cloud, a depth image or a laser scan. A mask is an image of the camera's
size (PNG, 8 or 16 bit, grey or colour): black (0 in every channel) = ignore, anything else =
judge (in a lossy JPEG or WebP, below a quarter of full scale is black). The pipeline
(``PipelineConfig.mask_path``) publishes nothing at the black pixels, as it does outside the
region of interest, and skips the rows that are black from edge to edge at the top and bottom
of the image altogether.

Any image editor draws one on a frame of the camera; ``cva-mask`` draws rectangles and
polygons from the command line and shows the result over a frame.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cva_confidence_ros.datasets.io import decode_image_file
from cva_confidence_ros.datasets.resize import check_factor
from cva_confidence_ros.errors import ConfigError, DataError, InputError

__all__ = ['check_mask_size', 'load_mask', 'mask_rows', 'reduce_mask']


def load_mask(path: str | Path, option: str = 'mask_path') -> np.ndarray:
    """Read an ignore mask.

    Args:
        path: An image file that OpenCV reads (PNG, BMP, TIFF, …); black = ignore. In a
            JPEG or lossy WebP, whose black comes back as 1, 2, … near the edges, every
            value below a quarter of full scale (64 of 255) counts as black.
        option: The parameter or option that named the file, for the messages (e.g.
            ``'--start'`` of ``cva-mask``).

    Returns:
        (H, W) bool, True where pixels are judged.

    Raises:
        ConfigError: The file is missing, empty or not an image, a truncated JPEG, declares
            more pixels than :data:`~cva_confidence_ros.datasets.io.MAX_IMAGE_PIXELS`, holds
            NaN (a float image), or it ignores every pixel.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f'{option} {str(path)!r} is not a file')
    if path.stat().st_size == 0:
        raise ConfigError(f'{option} {str(path)!r} is an empty file')
    try:
        # Not cv2.imread: the size in the header is checked before decoding, and a truncated
        # JPEG (its missing rows decode grey = judged) is refused.
        image = decode_image_file(path)
    except DataError as exc:
        raise ConfigError(f'{option} {str(path)!r} cannot be used as a mask: {exc}') from None
    if image is None or image.size == 0:
        raise ConfigError(f'{option} {str(path)!r} cannot be read as an image')
    # Colour: a pixel is ignored where every colour channel is 0 (alpha is not looked at).
    values = image[..., :3] if image.ndim == 3 else image
    if values.dtype.kind == 'f' and np.isnan(values).any():
        # NaN is not 0, so it would be judged: in a float image it rather marks "no value".
        raise ConfigError(
            f'{option} {str(path)!r} holds {int(np.isnan(values).sum())} NaN values; a mask '
            f'is 0 (ignore) or another number (judge) at every pixel'
        )
    lossy = _lossy_format(path)
    # A lossy format brings black back as 1, 2, … next to the edges (up to 60 at low
    # quality), which read as "judge" published a rim of the robot's body: there, anything
    # darker than a quarter of full scale is black.
    dark = np.iinfo(values.dtype).max // 4 + 1 if lossy and values.dtype.kind == 'u' else 0
    judged = values >= dark if dark else values != 0
    keep = np.any(judged, axis=2) if judged.ndim == 3 else judged
    if not keep.any():
        raise ConfigError(
            f'{option} {str(path)!r} ignores every pixel (black everywhere); black = ignore, '
            f'any other value = judge' + (f' (in a {lossy}: {dark} or more)' if dark else '')
        )
    return keep


def _lossy_format(path: Path) -> str | None:
    """``'JPEG'`` or ``'WebP'`` when the file's content is in that lossy format (whatever its
    name), else None."""
    with path.open('rb') as stream:
        head = stream.read(16)
    if head.startswith(b'\xff\xd8\xff'):
        return 'JPEG'
    if head[:4] == b'RIFF' and head[8:16] == b'WEBPVP8 ':  # 'VP8L' is the lossless one
        return 'WebP'
    return None


def reduce_mask(mask: np.ndarray, factor: int) -> np.ndarray:
    """The mask at 1/``factor`` of its resolution, as the pipeline shrinks the images.

    The last rows and columns that do not fill a block are cropped (as
    :func:`~cva_confidence_ros.datasets.resize.resize_image` crops the images); an output pixel
    is judged only when all its ``factor × factor`` input pixels are, so that no pixel that
    mixes in the robot's body is published.

    Raises:
        ConfigError: ``factor`` is not an integer ≥ 1.
        InputError: ``mask`` is not (H, W), or smaller than one ``factor × factor`` block (as
            :func:`~cva_confidence_ros.datasets.resize.resize_image` refuses such an image).
    """
    factor = check_factor(factor)
    mask = _check_2d(mask)
    if factor == 1:
        return mask
    height, width = mask.shape[0] // factor, mask.shape[1] // factor
    if height == 0 or width == 0:
        # An empty mask would judge no pixel of an image that cannot be shrunk either.
        raise InputError(
            f'cannot shrink a {mask.shape[1]}×{mask.shape[0]} px mask by {factor}: it is '
            'smaller than one block'
        )
    blocks = mask[: height * factor, : width * factor].reshape(height, factor, width, factor)
    return np.asarray(blocks.all(axis=(1, 3)), dtype=bool)


def mask_rows(mask: np.ndarray) -> tuple[int, int]:
    """Rows ``[y0, y1)`` from the first to the last row with a judged pixel (``(0, 0)`` when
    there is none).

    Raises:
        InputError: ``mask`` is not (H, W).
    """
    rows = np.flatnonzero(_check_2d(mask).any(axis=1))
    if rows.size == 0:
        return 0, 0
    return int(rows[0]), int(rows[-1]) + 1


def check_mask_size(
    mask: np.ndarray, width: int, height: int, option: str = 'mask_path'
) -> None:
    """Raise :class:`InputError` unless the mask has the input images' size.

    Args:
        mask: (H, W) mask at the input resolution.
        width, height: The input images' size.
        option: The parameter or option that named the mask, for the message (e.g.
            ``'--mask'`` of the bag tools, or ``"mask_path 'robot.png'"``).
    """
    mask = _check_2d(mask, option)
    if mask.shape != (height, width):
        raise InputError(
            f'the mask ({option}) is {mask.shape[1]}×{mask.shape[0]} px but the images are '
            f'{width}×{height} px; draw the mask on a frame of this camera at the resolution '
            f'it publishes'
        )


def _check_2d(mask: np.ndarray, option: str = '') -> np.ndarray:
    """``mask`` as an (H, W) bool array, or :class:`InputError` naming its shape: a colour
    image or a flattened mask would be misread (rows counted across the channels) or fail
    inside numpy."""
    mask = np.asarray(mask)
    if mask.ndim != 2:
        name = f'the mask ({option})' if option else 'the mask'
        raise InputError(
            f'{name} must be (H, W), one value a pixel; got shape {mask.shape} (load_mask '
            'reads an image file into one)'
        )
    return mask.astype(bool, copy=False)

"""Downscaling of stereo samples, images and ground truth together.

The paper (Sec. 4) halves the Middlebury resolution until the largest disparity fits into the
cost-volume depth; :func:`fit_disparity_range` does that with :func:`resize_sample`.

Ground truth is reduced by averaging each ``f × f`` block of the valid disparities and dividing
by ``f``, which matches the block average that ``cv2.INTER_AREA`` takes of the images. A block
gets NaN when fewer than half of its pixels have ground truth or when its valid disparities
spread over more than ``f`` pixels (one pixel at the output scale): such a block straddles a
depth edge and its image pixel mixes two surfaces, so no single disparity is right for it.
"""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np

from cva_confidence_ros.datasets.io import Calibration
from cva_confidence_ros.datasets.loaders import StereoSample
from cva_confidence_ros.errors import ConfigError, DataError, InputError

__all__ = [
    'check_factor',
    'fit_disparity_range',
    'resize_disparity',
    'resize_image',
    'resize_sample',
]

#: Smallest image side :func:`fit_disparity_range` shrinks a pair to.
_MIN_FITTED_SIDE = 1

#: Dtypes OpenCV's INTER_AREA resize takes.
_RESIZABLE = tuple(np.dtype(t) for t in (np.uint8, np.uint16, np.int16, np.float32, np.float64))


def check_factor(factor: int) -> int:
    """``factor`` as an int, or :class:`ConfigError` unless it is an integer ≥ 1."""
    if isinstance(factor, bool) or not isinstance(factor, (int, np.integer)) or factor < 1:
        raise ConfigError(f'factor must be an integer ≥ 1; got {factor!r}')
    return int(factor)


def _blocks(array: np.ndarray, factor: int) -> np.ndarray:
    """(H, W) → (H // f, W // f, f * f) blocks, cropping the last rows and columns."""
    height, width = array.shape[0] // factor, array.shape[1] // factor
    cropped = array[: height * factor, : width * factor]
    blocks = cropped.reshape(height, factor, width, factor).swapaxes(1, 2)
    return blocks.reshape(height, width, factor * factor)


def resize_disparity(disparity: np.ndarray, factor: int) -> np.ndarray:
    """Shrink a disparity map by an integer factor, NaN-aware (see module docstring).

    Args:
        disparity: (H, W) float disparity in input pixels, NaN = unknown.
        factor: Integer ≥ 1.

    Returns:
        (H // factor, W // factor) float32 disparity in output pixels, NaN = unknown.

    Raises:
        ConfigError: ``factor`` is not an integer ≥ 1.
        InputError: ``disparity`` is not 2-D.
    """
    factor = check_factor(factor)
    disparity = np.asarray(disparity, dtype=np.float32)
    if disparity.ndim != 2:
        raise InputError(f'disparity must be (H, W); got shape {disparity.shape}')
    if factor == 1:
        # ±inf is unknown too (Middlebury, ETH3D), as the blocks of a larger factor have it.
        return np.where(np.isfinite(disparity), disparity, np.float32(np.nan))
    blocks = _blocks(disparity, factor)
    valid = np.isfinite(blocks)
    count = valid.sum(axis=2)
    total = np.where(valid, blocks, 0.0).sum(axis=2, dtype=np.float64)
    high = np.where(valid, blocks, -np.inf).max(axis=2)
    low = np.where(valid, blocks, np.inf).min(axis=2)
    keep = (2 * count >= factor * factor) & (high - low <= factor)
    with np.errstate(invalid='ignore', divide='ignore'):
        mean = total / count
    return np.where(keep, mean / factor, np.nan).astype(np.float32)


def resize_image(image: np.ndarray, factor: int) -> np.ndarray:
    """Shrink an image by an integer factor: crop to a multiple of it, then block-average.

    Args:
        image: (H, W) or (H, W, C) uint8, uint16, int16, float32 or float64 (what OpenCV's
            area resize takes).
        factor: Integer ≥ 1; 1 returns ``image`` unchanged.

    Returns:
        (H // factor, W // factor[, C]) of the same dtype, aligned with
        :func:`resize_disparity` of the same factor.

    Raises:
        ConfigError: ``factor`` is not an integer ≥ 1.
        InputError: Another rank or dtype (an OpenCV assertion otherwise), or the image is
            smaller than one ``factor × factor`` block.
    """
    factor = check_factor(factor)
    if factor == 1:
        return image
    if image.ndim not in (2, 3):
        raise InputError(f'image must be (H, W) or (H, W, C); got shape {image.shape}')
    if image.dtype not in _RESIZABLE:
        raise InputError(
            f'cannot shrink an image of dtype {image.dtype}; expected uint8, uint16, int16, '
            'float32 or float64'
        )
    height, width = image.shape[0] // factor, image.shape[1] // factor
    if height == 0 or width == 0:
        raise InputError(
            f'cannot shrink a {image.shape[0]}×{image.shape[1]} image by {factor}: it is '
            'smaller than one block'
        )
    cropped = np.ascontiguousarray(image[: height * factor, : width * factor])
    # On an exact multiple INTER_AREA is the plain f × f block mean, like the disparity.
    small = cv2.resize(cropped, (width, height), interpolation=cv2.INTER_AREA)
    # OpenCV drops the channel axis of an (H, W, 1) image.
    return small.reshape((height, width) + image.shape[2:])


def _resize_calibration(calib: Calibration, factor: int) -> Calibration:
    # Pixel centres sit at integer coordinates, so the principal point maps as (c + ½) / f − ½.
    return dataclasses.replace(
        calib,
        fx=calib.fx / factor,
        fy=calib.fy / factor,
        cx=(calib.cx + 0.5) / factor - 0.5,
        cy=(calib.cy + 0.5) / factor - 0.5,
        doffs=calib.doffs / factor,
    )


def resize_sample(sample: StereoSample, factor: int) -> StereoSample:
    """Shrink a stereo sample by an integer factor: images, ground truth, mask and calibration.

    Rows and columns beyond a multiple of ``factor`` are cropped first.

    Args:
        sample: Input pair.
        factor: Integer ≥ 1; 1 returns ``sample`` unchanged.

    Returns:
        A new :class:`StereoSample` of size (H // factor, W // factor): images by block mean
        (uint8), disparity by :func:`resize_disparity`, ``nonocc`` True where the whole block is
        non-occluded, calibration with focal length, principal point and ``doffs`` scaled.

    Raises:
        ConfigError: ``factor`` is not an integer ≥ 1.
        DataError: The image is smaller than one block.
    """
    factor = check_factor(factor)
    if factor == 1:
        return sample
    height, width = sample.shape
    if height < factor or width < factor:
        raise DataError(
            f'{sample.dataset}/{sample.scene}: cannot shrink a {height}×{width} pair by {factor}'
        )
    nonocc: np.ndarray | None = None
    if sample.nonocc is not None:
        nonocc = np.asarray(_blocks(sample.nonocc, factor).all(axis=2))
    return dataclasses.replace(
        sample,
        left=resize_image(sample.left, factor),
        right=resize_image(sample.right, factor),
        disparity=resize_disparity(sample.disparity, factor),
        nonocc=nonocc,
        calib=_resize_calibration(sample.calib, factor) if sample.calib is not None else None,
    )


def fit_disparity_range(sample: StereoSample, max_disparity: int) -> tuple[StereoSample, int]:
    """Halve the resolution until the ground truth fits into a cost volume of depth D.

    The factor is the smallest of 1, 2, 4, … with ``max finite GT disparity / factor ≤ D − 1``:
    the cost volume holds d = 0 … D − 1, and the paper halves Middlebury images as long as the
    maximum disparity exceeds 255 (D = 256).

    Args:
        sample: Input pair.
        max_disparity: Cost-volume depth D ≥ 1 (disparities 0 … D − 1).

    Returns:
        ``(resized sample, factor)``; the sample is returned unchanged with factor 1 when it
        already fits or has no finite ground truth.

    Raises:
        ConfigError: ``max_disparity`` < 1.
        DataError: The image would shrink below one pixel (an outlier or a ground truth
            stored at another scale).
    """
    # NaN, inf or None would escape int() as ValueError, OverflowError or TypeError.
    if (
        isinstance(max_disparity, bool)
        or not isinstance(max_disparity, (int, float, np.integer, np.floating))
        or not math.isfinite(max_disparity)
        or int(max_disparity) != max_disparity
        or max_disparity < 1
    ):
        raise ConfigError(f'max_disparity must be an integer ≥ 1; got {max_disparity!r}')
    largest = sample.max_disparity
    factor = 1
    height, width = sample.left.shape[:2]
    while largest / factor > max_disparity - 1:
        factor *= 2
        if min(height, width) / factor < _MIN_FITTED_SIDE:
            raise DataError(
                f'{sample.dataset}/{sample.scene}: ground truth reaches {largest:.4g} px; '
                f'fitting it into D = {max_disparity} would shrink the {width}×{height} pair '
                f'to nothing (check the ground truth and its scale, or use '
                'a larger D)'
            )
    return resize_sample(sample, factor), factor

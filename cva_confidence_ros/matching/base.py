"""The matcher interface and the checks every matcher shares at its entry.

A matcher is a class with a frozen-dataclass ``Config`` and one method, :meth:`Matcher.compute`,
that turns a checked uint8 image pair into a (D, H, W) float32 cost volume in [0, 1]. The public
entry :func:`cva_confidence_ros.matching.compute_cost_volume` validates the inputs here once, so
matchers only ever see clean arrays.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import fields
from typing import Any, ClassVar

import cv2
import numpy as np

from cva_confidence_ros.errors import ConfigError, InputError

__all__ = [
    'VIEWS',
    'Matcher',
    'check_image_pair',
    'check_max_disparity',
    'check_view',
    'to_gray',
]

VIEWS = ('left', 'right')

_FLOAT_KINDS = ('f',)


class Matcher(ABC):
    """Base class of the registered matchers.

    Subclasses set ``Config`` to a frozen dataclass whose fields are the matcher's parameters
    (with defaults) and whose ``__post_init__`` raises :class:`ConfigError` on bad values.

    Args:
        config: The parameters; ``None`` = the defaults of ``Config``.
    """

    Config: ClassVar[type]
    #: Bytes :meth:`compute` allocates per (D, H, W) entry of its volume: the float32 volume
    #: and its work arrays of the same size (SGM: 3 more).
    bytes_per_voxel: ClassVar[int] = 4
    #: Bytes it allocates per pixel of the pair besides (MC-CNN: both images' features).
    bytes_per_pixel: ClassVar[int] = 0

    def __init__(self, config: Any = None) -> None:
        if config is None:
            config = self.Config()
        if not isinstance(config, self.Config):
            raise ConfigError(
                f'{type(self).__name__} expects a {self.Config.__name__}; '
                f'got {type(config).__name__}'
            )
        self.config = config

    @classmethod
    def from_params(cls, **params: Any) -> Matcher:
        """Build the matcher from keyword parameters of its ``Config``.

        Raises:
            ConfigError: A name that is not a field of ``Config``, or a bad value.
        """
        names = sorted(f.name for f in fields(cls.Config))
        unknown = sorted(set(params) - set(names))
        if unknown:
            raise ConfigError(
                f'unknown parameters {unknown} for {cls.__name__}; expected a subset of {names}'
            )
        return cls(cls.Config(**params))

    @abstractmethod
    def compute(
        self, left: np.ndarray, right: np.ndarray, max_disparity: int, view: str
    ) -> np.ndarray:
        """Cost volume of an already checked pair.

        Args:
            left: (H, W) or (H, W, 3) uint8 left image (RGB order if colour).
            right: Same shape and dtype as ``left``.
            max_disparity: D, with 1 ≤ D < W.
            view: ``'left'`` (entry [d, y, x] pairs left (y, x) with right (y, x − d)) or
                ``'right'`` (right (y, x) with left (y, x + d)).

        Returns:
            (D, H, W) float32 C-contiguous costs in [0, 1], 1.0 where the partner pixel lies
            outside the image.
        """


def _check_image(side: str, image: object) -> np.ndarray:
    if not isinstance(image, np.ndarray):
        raise InputError(f'{side} image must be a numpy array; got {type(image).__name__}')
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] != 3):
        # An RGBA PNG as read (imageio, PIL) and a single-channel (H, W, 1) array: say what
        # to give instead.
        hint = {4: ' (drop the alpha channel: image[..., :3])',
                1: ' (give it as (H, W): image[..., 0])'}.get(
            image.shape[2] if image.ndim == 3 else 0, '')
        raise InputError(f'{side} image must be H×W or H×W×3; got shape {image.shape}{hint}')
    if image.size == 0:
        raise InputError(f'{side} image is empty; got shape {image.shape}')
    if image.dtype == np.uint8:
        return image
    if image.dtype.kind in _FLOAT_KINDS:
        if not np.all(np.isfinite(image)):
            bad = int(np.count_nonzero(~np.isfinite(image)))
            raise InputError(
                f'{side} image must be finite; got {bad} NaN/inf values in a {image.dtype} array'
            )
        low, high = float(image.min()), float(image.max())
        if low < 0.0 or high > 255.0:
            raise InputError(
                f'{side} float image must lie in [0, 255]; got values in [{low:g}, {high:g}]'
            )
        if 0.0 < high <= 1.0:
            raise InputError(
                f'{side} float image lies in [0, 1] (max {high:g}): it looks normalised, but '
                'the matchers take intensities in [0, 255]; multiply it by 255'
            )
        # Float input is a convenience for callers holding 0..255 intensities in float arrays;
        # the contract of every matcher is uint8.
        return np.rint(image).astype(np.uint8)
    raise InputError(
        f'{side} image must be uint8 (or float in [0, 255]); got dtype {image.dtype}'
    )


def check_image_pair(left: object, right: object) -> tuple[np.ndarray, np.ndarray]:
    """Validate a stereo pair and return it as uint8 arrays.

    Args:
        left: (H, W) or (H, W, 3) image, uint8, or float with finite values in [0, 255]
            (rounded to uint8; a float image whose values all lie in (0, 1] is refused as
            one normalised to [0, 1] by mistake).
        right: Same shape as ``left``.

    Returns:
        ``(left, right)`` as (H, W) or (H, W, 3) uint8 arrays.

    Raises:
        InputError: Not an array, wrong rank or channel count, empty, other dtype, NaN/inf or
            out-of-range float values, or different shapes.
    """
    left_u8 = _check_image('left', left)
    right_u8 = _check_image('right', right)
    if left_u8.shape != right_u8.shape:
        if left_u8.shape[:2] == right_u8.shape[:2]:
            # Same size, one colour and one grey: a camera pair of two encodings (image_rect
            # with image_rect_color, say), which a shape alone did not tell.
            kinds = ['colour' if image.ndim == 3 else 'grey' for image in (left_u8, right_u8)]
            raise InputError(
                f'left and right images must both be grey or both colour; got a {kinds[0]} '
                f'left {left_u8.shape} and a {kinds[1]} right {right_u8.shape} (give both '
                'cameras one encoding, e.g. both image_rect or both image_rect_color)'
            )
        raise InputError(
            'left and right images must have the same shape; '
            f'got {left_u8.shape} and {right_u8.shape}'
        )
    return left_u8, right_u8


def check_max_disparity(max_disparity: object, width: int) -> int:
    """Validate the cost-volume depth D against the image width.

    Returns:
        D as a Python int, 1 ≤ D < ``width``.

    Raises:
        ConfigError: Not an integer, D < 1, or D ≥ ``width``.
    """
    if isinstance(max_disparity, bool) or not isinstance(max_disparity, (int, np.integer)):
        raise ConfigError(
            f'max_disparity must be an integer; got {type(max_disparity).__name__} '
            f'{max_disparity!r}'
        )
    depth = int(max_disparity)
    if depth < 1:
        raise ConfigError(f'max_disparity must be ≥ 1; got {depth}')
    if depth >= width:
        raise ConfigError(
            f'max_disparity must be smaller than the image width {width}; got {depth}'
        )
    return depth


def check_view(view: object) -> str:
    """Validate the reference view name (``'left'`` or ``'right'``).

    Raises:
        ConfigError: Any other value.
    """
    if view not in VIEWS:
        raise ConfigError(f'view must be one of {VIEWS}; got {view!r}')
    return str(view)


def to_gray(image: np.ndarray) -> np.ndarray:
    """(H, W) uint8 gray image of an (H, W) or (H, W, 3) RGB uint8 image (ITU-R 601 weights)."""
    if image.ndim == 2:
        return np.ascontiguousarray(image)
    return cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY)

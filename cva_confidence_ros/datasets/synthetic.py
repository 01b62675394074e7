"""Synthetic stereo pairs with dense, exact ground truth, for training CVA-Net.

A scene is a background plane and a few occluding objects (rectangles, ellipses, convex polygons,
thin poles), each a slanted plane in disparity space ``d(x, y) = p + gx·x + gy·y`` (a plane in 3D
is a plane in disparity) with a texture attached to it. Textures are crops of real photographs
shipped with scikit-image, plus the hard cases the paper discusses: texture-less surfaces,
repetitive patterns along the epipolar lines, and — from the geometry — occlusions and depth
discontinuities.

Both views are rendered with a z-buffer in which nearer surfaces (larger disparity) win. Each
surface is forward-projected into a view exactly: a surface point at left-view coordinates
``(x, y)`` lands at ``x − d(x, y)`` in the right view, and since ``d`` is affine the projection
is inverted in closed form, ``x = (x_r + p + gy·y) / (1 − gx)``, so every right pixel gets the
texture of the surface it sees without holes or splatting. Occlusions are therefore real: a
left pixel whose point is hidden in the right view is marked occluded (``nonocc`` False), as are
pixels whose match falls outside the right image.

The right view then gets a mild gain/offset difference and both views sensor noise.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
import functools

import cv2
import numpy as np
import skimage.data

from cva_confidence_ros.checks import is_int, is_real
from cva_confidence_ros.datasets.io import Calibration
from cva_confidence_ros.datasets.loaders import StereoSample
from cva_confidence_ros.errors import ConfigError

__all__ = ['PHOTOS', 'SYNTHETIC_DATASET', 'synthetic_pair', 'synthetic_pairs']

SYNTHETIC_DATASET = 'synthetic'

#: scikit-image photographs used as surface textures (all ship with scikit-image).
PHOTOS = (
    'astronaut',
    'brick',
    'camera',
    'chelsea',
    'coffee',
    'coins',
    'grass',
    'gravel',
    'rocket',
    'hubble_deep_field',
    'immunohistochemistry',
    'page',
    'text',
)

# Texture kinds and their probabilities: mostly photographs, plus the hard cases.
_TEXTURES = ('photo', 'flat', 'stripes', 'checker', 'low_contrast')
_TEXTURE_P = (0.55, 0.12, 0.13, 0.08, 0.12)
# The background fills most of the image: a photograph, so that scenes stay natural; the
# hard textures go on objects, where they cover a part of the image as in real scenes.
_BACKGROUND_P = (0.95, 0.0, 0.0, 0.0, 0.05)
_SHAPES = ('rectangle', 'ellipse', 'polygon', 'pole')
# Largest horizontal slant |gx|: keeps 1 − gx well away from 0 (no fold-over in the right view).
_MAX_SLANT_X = 0.25
_MAX_SLANT_Y = 0.15


@dataclass(frozen=True)
class _Surface:
    """A planar surface: disparity plane, shape mask in left-view coordinates, texture."""

    plane: tuple[float, float, float]  # p, gx, gy of d = p + gx·x + gy·y
    inside: Callable[[np.ndarray, np.ndarray], np.ndarray]
    texture: np.ndarray  # (H, W_tex, 3) float32 in [0, 255], indexed by left-view (y, x)


@functools.cache
def _photo(name: str) -> tuple[np.ndarray, bool]:
    """A scikit-image photograph as (H, W, 3) float32 RGB in [0, 255] (read-only), and
    whether it is a grey-level one."""
    image = np.asarray(getattr(skimage.data, name)())
    grey = image.ndim == 2
    if grey:
        image = np.repeat(image[:, :, None], 3, axis=2)
    image = image[:, :, :3].astype(np.float32)
    image.setflags(write=False)
    return image, grey


def _integral(value: object) -> bool:
    """Whether ``value`` is a whole number (``32`` or ``32.0``, not ``True``, ``'32'``, NaN)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.number)):
        return False
    try:
        return int(value) == value
    except (OverflowError, ValueError):  # inf, NaN
        return False


def _check_arguments(
    seed: int, height: int, width: int, max_disparity: int
) -> tuple[int, int, int, int]:
    """The arguments as Python ints (``32.0`` → ``32``: the same pair and scene name as
    ``32``)."""
    for name, value in (('height', height), ('width', width), ('max_disparity', max_disparity)):
        if not _integral(value):
            raise ConfigError(f'{name} must be an integer; got {value!r}')
    if not _integral(seed) or seed < 0:
        raise ConfigError(f'seed must be an integer >= 0; got {seed!r}')
    seed, height, width, max_disparity = (
        int(seed), int(height), int(width), int(max_disparity)
    )
    if height < 16 or width < 16:
        raise ConfigError(f'synthetic pairs need at least 16×16 pixels; got {height}×{width}')
    if not 4 <= max_disparity <= width // 2:
        raise ConfigError(
            f'max_disparity must be in [4, width / 2 = {width // 2}] for a {height}×{width} '
            f'pair; got {max_disparity}'
        )
    return seed, height, width, max_disparity


def _plane(
    rng: np.random.Generator,
    box: tuple[float, float, float, float],
    low: float,
    high: float,
) -> tuple[float, float, float]:
    """A disparity plane whose values over ``box`` (x0, y0, x1, y1) stay within [low, high]."""
    x0, y0, x1, y1 = box
    gx = rng.uniform(-_MAX_SLANT_X, _MAX_SLANT_X) * rng.choice([0.0, 0.3, 1.0])
    gy = rng.uniform(-_MAX_SLANT_Y, _MAX_SLANT_Y) * rng.choice([0.0, 0.5, 1.0])
    half_span = abs(gx) * (x1 - x0) / 2 + abs(gy) * (y1 - y0) / 2
    if 2 * half_span > high - low:
        # Too slanted for the range: flatten until it fits.
        shrink = (high - low) / (2 * half_span + 1e-9)
        gx, gy, half_span = gx * shrink, gy * shrink, half_span * shrink
    centre_value = rng.uniform(low + half_span, high - half_span)
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    return centre_value - gx * cx - gy * cy, gx, gy


def _shape(
    rng: np.random.Generator, height: int, width: int
) -> tuple[Callable[[np.ndarray, np.ndarray], np.ndarray], tuple[float, float, float, float]]:
    """A random object shape: an inside-test on left-view coordinates and its bounding box."""
    kind = _SHAPES[rng.choice(len(_SHAPES), p=(0.3, 0.3, 0.3, 0.1))]
    cx, cy = rng.uniform(0, width), rng.uniform(0, height)
    size = min(height, width)
    if kind == 'pole':
        # Thin foreground structures give narrow occlusions and strong discontinuities.
        half_w, half_h, angle = rng.uniform(1.5, 4.0), rng.uniform(0.3, 0.8) * size, 0.0
    else:
        half_w = rng.uniform(0.08, 0.3) * size
        half_h = rng.uniform(0.08, 0.3) * size
        angle = rng.uniform(0, np.pi)
    cos, sin = np.cos(angle), np.sin(angle)

    def local(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u = (x - cx) * cos + (y - cy) * sin
        v = -(x - cx) * sin + (y - cy) * cos
        return u / half_w, v / half_h

    if kind in ('rectangle', 'pole'):

        def inside(x: np.ndarray, y: np.ndarray) -> np.ndarray:
            u, v = local(x, y)
            return (np.abs(u) <= 1) & (np.abs(v) <= 1)

    elif kind == 'ellipse':

        def inside(x: np.ndarray, y: np.ndarray) -> np.ndarray:
            u, v = local(x, y)
            return u * u + v * v <= 1

    else:
        corners = np.sort(rng.uniform(0, 2 * np.pi, size=int(rng.integers(3, 8))))
        px, py = np.cos(corners), np.sin(corners)

        def inside(x: np.ndarray, y: np.ndarray) -> np.ndarray:
            u, v = local(x, y)
            result = np.ones(u.shape, dtype=bool)
            # Counter-clockwise convex polygon: inside = left of every edge.
            for i in range(len(px)):
                j = (i + 1) % len(px)
                cross = (px[j] - px[i]) * (v - py[i]) - (py[j] - py[i]) * (u - px[i])
                result &= cross >= 0
            return result

    reach = float(np.hypot(half_w, half_h))
    box = (
        max(0.0, cx - reach),
        max(0.0, cy - reach),
        min(width, cx + reach),
        min(height, cy + reach),
    )
    return inside, box


def _texture(
    rng: np.random.Generator, height: int, width: int, p: tuple[float, ...] = _TEXTURE_P
) -> np.ndarray:
    """A (height, width, 3) float32 texture in [0, 255] of a kind drawn with probabilities p."""
    kind = _TEXTURES[rng.choice(len(_TEXTURES), p=p)]
    colour = rng.uniform(30, 225, size=3).astype(np.float32)
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    if kind == 'flat':
        # Texture-less: a smooth shading ramp only, well below one grey level per pixel.
        ramp = (xx * rng.uniform(-1, 1) + yy * rng.uniform(-1, 1)) * 20.0 / max(height, width)
        return np.clip(colour[None, None] + ramp[:, :, None], 0, 255)
    if kind == 'stripes':
        # Repetitive along the epipolar lines: several matches look equally good.
        period = rng.uniform(4.0, 14.0)
        angle = rng.uniform(-0.5, 0.5)
        phase = (xx * np.cos(angle) + yy * np.sin(angle)) * 2 * np.pi / period
        wave = np.sin(phase)
        if rng.random() < 0.5:
            wave = np.sign(wave)
        other = rng.uniform(30, 225, size=3).astype(np.float32)
        mix = (wave[:, :, None] + 1) / 2
        return colour[None, None] * mix + other[None, None] * (1 - mix)
    if kind == 'checker':
        cell = rng.uniform(3.0, 10.0)
        board = ((np.floor(xx / cell) + np.floor(yy / cell)) % 2)[:, :, None]
        other = rng.uniform(30, 225, size=3).astype(np.float32)
        return colour[None, None] * board + other[None, None] * (1 - board)
    photo, grey = _photo(PHOTOS[int(rng.integers(len(PHOTOS)))])
    # Mostly shrunk: fine natural texture, as in real scenes at a distance.
    scale = rng.uniform(0.35, 1.2)
    size = (max(1, round(photo.shape[1] * scale)), max(1, round(photo.shape[0] * scale)))
    resized = cv2.resize(
        photo, size, interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
    )
    # Mirror-tile when the photograph is smaller than the texture.
    pad_y, pad_x = max(0, height - resized.shape[0]), max(0, width - resized.shape[1])
    if pad_y or pad_x:
        resized = np.pad(resized, ((0, pad_y), (0, pad_x), (0, 0)), mode='symmetric')
    y0 = int(rng.integers(0, resized.shape[0] - height + 1))
    x0 = int(rng.integers(0, resized.shape[1] - width + 1))
    crop = resized[y0 : y0 + height, x0 : x0 + width]
    if rng.random() < 0.5:
        crop = crop[:, ::-1]
    if grey:
        crop = crop * (0.6 + 0.4 * colour / 255.0)[None, None]  # tint grey photographs
    if kind == 'low_contrast':
        # Weakly textured: a photograph at 5-15 % contrast.
        mean = crop.mean(axis=(0, 1), keepdims=True)
        crop = mean + (crop - mean) * rng.uniform(0.05, 0.15)
    return np.ascontiguousarray(crop, dtype=np.float32)


def _render(
    surfaces: list[_Surface], height: int, width: int, view: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Z-buffer rendering of one view.

    Returns:
        (image (H, W, 3) float32, disparity (H, W) float32, surface index (H, W) int16).
    """
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    image = np.zeros((height, width, 3), dtype=np.float32)
    depth = np.full((height, width), -np.inf)
    index = np.full((height, width), -1, dtype=np.int16)
    for number, surface in enumerate(surfaces):
        p, gx, gy = surface.plane
        # Left-view x of the surface point seen at each pixel of this view.
        x_left = xx if view == 'left' else (xx + p + gy * yy) / (1.0 - gx)
        disparity = p + gx * x_left + gy * yy
        hit = surface.inside(x_left, yy) & (disparity > depth)
        if not hit.any():
            continue
        colour = cv2.remap(
            surface.texture,
            x_left.astype(np.float32),
            yy.astype(np.float32),
            interpolation=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REFLECT_101,
        )
        image[hit] = colour[hit]
        depth[hit] = disparity[hit]
        index[hit] = number
    return image, depth.astype(np.float32), index


def _visible_in_right(
    disparity: np.ndarray, index_left: np.ndarray, index_right: np.ndarray
) -> np.ndarray:
    """Left pixels whose surface point is the one the right view sees at ``x − d``."""
    height, width = disparity.shape
    xx = np.arange(width)[None, :] - disparity
    rows = np.broadcast_to(np.arange(height)[:, None], disparity.shape)
    visible = xx >= 0
    # Both right pixels around the sub-pixel match must show the same surface.
    for column in (np.floor(xx), np.ceil(xx)):
        column = np.clip(column, 0, width - 1).astype(np.intp)
        visible &= index_right[rows, column] == index_left
    return visible


def _to_uint8(image: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def synthetic_pair(
    seed: int,
    height: int = 128,
    width: int = 160,
    max_disparity: int = 64,
) -> StereoSample:
    """A synthetic rectified stereo pair with dense ground truth, deterministic by seed.

    Args:
        seed: Integer ≥ 0; the same seed (and size) always gives the same pair.
        height: Image rows, ≥ 16.
        width: Image columns, ≥ 16.
        max_disparity: Cost-volume depth D in [4, width / 2]; every ground-truth disparity
            lies in [0, D − 1].

    Returns:
        A :class:`StereoSample` with ``dataset='synthetic'``, ``scene=f'seed{seed}'``,
        (H, W, 3) uint8 RGB images with ``left[y, x] ≈ right[y, x − d]`` on visible pixels
        (up to a gain/offset of the right view and noise), float32 disparity defined at every
        pixel, ``nonocc`` (False where the point is hidden in, or outside, the right view) and a
        pinhole calibration (fx = W, baseline 0.1 m).

    Raises:
        ConfigError: Sizes out of range.
    """
    seed, height, width, max_disparity = _check_arguments(seed, height, width, max_disparity)
    rng = np.random.default_rng([seed, height, width, max_disparity])
    high = float(max_disparity - 1)
    # The right view sees left-view x up to about W + D / (1 − gx); textures cover that.
    texture_width = width + int(np.ceil(high / (1 - _MAX_SLANT_X))) + 2

    background_box = (0.0, 0.0, float(width), float(height))
    surfaces = [
        _Surface(
            plane=_plane(rng, background_box, 0.0, high * rng.uniform(0.2, 0.6)),
            inside=lambda x, y: np.ones(np.shape(x), dtype=bool),
            texture=_texture(rng, height, texture_width, _BACKGROUND_P),
        )
    ]
    for _ in range(int(rng.integers(3, 9))):
        inside, box = _shape(rng, height, width)
        low = high * rng.uniform(0.05, 0.6)
        surfaces.append(
            _Surface(
                plane=_plane(rng, box, low, high),
                inside=inside,
                texture=_texture(rng, height, texture_width),
            )
        )

    left, disparity, index_left = _render(surfaces, height, width, 'left')
    right, _, index_right = _render(surfaces, height, width, 'right')
    # Fold the range once more: the planes are bounded over their boxes, the background over
    # the image, so this only trims rounding.
    disparity = np.clip(disparity, 0.0, high).astype(np.float32)
    nonocc = _visible_in_right(disparity, index_left, index_right)

    gain = rng.uniform(0.9, 1.1)
    offset = rng.uniform(-8.0, 8.0)
    right = right * gain + offset
    noise = rng.uniform(0.5, 2.0)
    left = left + rng.normal(0.0, noise, size=left.shape)
    right = right + rng.normal(0.0, noise, size=right.shape)

    calib = Calibration(
        fx=float(width), fy=float(width), cx=(width - 1) / 2, cy=(height - 1) / 2, baseline=0.1
    )
    return StereoSample(
        dataset=SYNTHETIC_DATASET,
        scene=f'seed{seed}',
        left=_to_uint8(left),
        right=_to_uint8(right),
        disparity=disparity,
        nonocc=nonocc,
        calib=calib,
    )


def synthetic_pairs(
    count: int, first_seed: int = 0, height: int = 128, width: int = 160, max_disparity: int = 64
) -> list[StereoSample]:
    """``count`` pairs of :func:`synthetic_pair` with seeds ``first_seed … first_seed+count−1``.

    Raises:
        ConfigError: A count that is not a whole number ≥ 0, or a first seed or size that
            :func:`synthetic_pair` refuses (checked even when ``count`` is 0).
    """
    # A whole float (2.0, as synthetic_pair takes its sizes) is a count; range() refused it.
    whole = is_real(count) and float(count).is_integer()
    if not (is_int(count) or whole) or count < 0:
        raise ConfigError(f'count must be a whole number >= 0; got {count!r}')
    if not _integral(first_seed) or first_seed < 0:
        raise ConfigError(f'first_seed must be an integer >= 0; got {first_seed!r}')
    # As Python ints: a numpy first_seed wrapped around (np.uint8(255) + 1 = 0, a pair twice),
    # and the sizes are checked even for count 0.
    first_seed, height, width, max_disparity = _check_arguments(
        first_seed, height, width, max_disparity
    )
    return [
        synthetic_pair(first_seed + i, height, width, max_disparity) for i in range(int(count))
    ]

"""PNG helpers: confidence and disparity maps, the correctness overlay, ROC curves and
reliability diagrams.

Arrays in, PNG path out. Maps are written pixel for pixel (one PNG pixel per array element,
no axes), so they can be laid over the input image; ROC curves and reliability diagrams are
small matplotlib figures.
Only the Agg canvas is used, never ``pyplot``, so importing this module changes no global
matplotlib state and needs no display.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
import errno
import itertools
import math
import os
from pathlib import Path
import struct
from typing import TYPE_CHECKING
import zlib

import numpy as np

from cva_confidence_ros.checks import is_int, is_real
from cva_confidence_ros.errors import InputError
from cva_confidence_ros.outputs import naming

if TYPE_CHECKING:
    from cva_confidence_ros.calibration import ReliabilityTable

__all__ = [
    'CORRECT_RGB',
    'UNKNOWN_RGB',
    'WRONG_RGB',
    'confidence_overlay',
    'correctness_classes',
    'optimal_roc_curve',
    'save_confidence_map',
    'save_confidence_overlay',
    'save_correctness_overlay',
    'save_disparity_map',
    'save_reliability_diagram',
    'save_roc_curves',
]

CORRECT_RGB = (0, 200, 0)
WRONG_RGB = (230, 0, 0)
UNKNOWN_RGB = (40, 40, 110)
"""Colour of NaN entries in confidence and disparity maps (e.g. pixels not computed)."""

PathLike = str | os.PathLike[str]

_PARTIAL_IDS = itertools.count()


def _check_map(name: str, array: np.ndarray) -> np.ndarray:
    array = np.asarray(array)
    if array.ndim != 2 or array.size == 0:
        raise InputError(f'{name} must be a non-empty (H, W) array; got shape {array.shape}')
    # Complex is a number too, but casting it drops the imaginary part (with only a warning).
    if array.dtype.kind not in 'biuf':
        raise InputError(f'{name} must be real numbers or bool; got dtype {array.dtype}')
    return array


def _save(path: PathLike, write: Callable[[Path], object]) -> Path:
    """Make the parent folders of ``path`` and ``write`` it: to a file beside it, renamed
    onto ``path`` once complete.

    Raises:
        OSError: The file cannot be written. A folder at ``path`` and a file where a parent
            folder belongs are named as such (mkdir said ``File exists``, naming the file in
            the way and not the PNG). Still OSErrors, as a full disk's: the callers handle
            those (the replay's report stops its PNGs, ``cva-evaluate`` exits with the reason).
    """
    out = Path(path)
    if out.is_dir():
        raise IsADirectoryError(
            errno.EISDIR, f'cannot write PNG {out}: it is a folder; expected a file path'
        )
    for folder in out.parents:
        if folder.exists():
            if not folder.is_dir():
                raise NotADirectoryError(
                    errno.ENOTDIR, f'cannot write PNG {out}: {folder} is a file, not a folder'
                )
            break
    out.parent.mkdir(parents=True, exist_ok=True)
    # Written beside ``path`` and renamed onto it: a write that fails half-way (a full disk)
    # leaves no truncated PNG, and a PNG already at ``path`` stays whole until then.
    partial = out.with_name(f'.{out.name[:200]}.{os.getpid()}-{next(_PARTIAL_IDS)}.part')
    try:
        # A write that fails half-way names the PNG, not the temporary file (or nothing).
        with naming(out):
            write(partial)
            os.replace(partial, out)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise
    return out


def _text_chunks(text: Mapping[str, str]) -> bytes:
    """PNG ``iTXt`` chunks (UTF-8: 'ε', '≤') of ``text``, keyword → value."""
    chunks = b''
    for key, value in text.items():
        data = key.encode('latin-1') + b'\0\0\0\0\0' + value.encode('utf-8')
        body = b'iTXt' + data
        chunks += struct.pack('>I', len(data)) + body + struct.pack('>I', zlib.crc32(body))
    return chunks


def _write_rgb(rgb: np.ndarray, path: PathLike, text: Mapping[str, str] | None = None) -> Path:
    import cv2

    # Not matplotlib's imsave: it adds an alpha channel (an RGBA PNG where RGB is promised).
    # OpenCV takes BGR; encoded in memory, so that nothing is written if encoding fails.
    bgr = np.ascontiguousarray(np.asarray(rgb, dtype=np.uint8)[..., ::-1])
    ok, png = cv2.imencode('.png', bgr)
    if not ok:
        raise InputError(f'cannot encode a {rgb.shape} image as PNG')
    data = png.tobytes()
    if text:
        # After the signature (8 bytes) and IHDR (25): where readers look for text.
        data = data[:33] + _text_chunks(text) + data[33:]
    return _save(path, lambda out: out.write_bytes(data))


def _bound(name: str, value: float | None) -> float | None:
    """A colour-scale bound given by the caller: a finite real number (NaN drew all grey)."""
    if value is None:
        return None
    if not is_real(value) or not math.isfinite(value):
        raise InputError(f'{name} must be a finite number or None; got {value!r}')
    return float(value)


def _scale_bounds(
    values: np.ndarray, vmin: float | None, vmax: float | None
) -> tuple[float, float]:
    """The values drawn at the colormap's start and end: the given ones, else the finite
    minimum / maximum."""
    vmin, vmax = _bound('vmin', vmin), _bound('vmax', vmax)
    finite = values[np.isfinite(values)]
    # A default bound never lies beyond the given one: the scale would be inverted, and a
    # map wholly below a given vmin drawn white instead of black.
    if vmin is None:
        vmin = float(finite.min()) if finite.size else 0.0
        if vmax is not None:
            vmin = min(vmin, vmax)
    if vmax is None:
        vmax = float(finite.max()) if finite.size else 1.0
        vmax = max(vmax, vmin)
    return vmin, vmax


def _colorize(
    values: np.ndarray, cmap: str, vmin: float | None, vmax: float | None
) -> np.ndarray:
    """Map values through ``cmap`` onto (H, W, 3) uint8; NaN becomes UNKNOWN_RGB.

    ``vmin`` is drawn at the colormap's start, ``vmax`` at its end (``vmin > vmax`` inverts
    the scale); values beyond are clipped.
    """
    from matplotlib import colormaps

    values = values.astype(np.float64)
    known = ~np.isnan(values)
    vmin, vmax = _scale_bounds(values, vmin, vmax)
    # Halves: vmax − vmin of two finite extremes can overflow to inf (and x / inf is 0).
    half_span = vmax / 2 - vmin / 2
    with np.errstate(invalid='ignore', over='ignore'):
        if half_span != 0:
            scaled = (values / 2 - vmin / 2) / half_span
        else:
            # A constant map would divide by zero: mid-grey, with what lies above and below
            # (±inf among equal finite values) still saturating.
            scaled = np.where(values > vmin, 1.0, np.where(values < vmin, 0.0, 0.5))
    # ±inf is a legitimate extreme (e.g. a ratio over a zero cost); it saturates the map.
    scaled = np.clip(np.where(known, scaled, 0.0), 0.0, 1.0)
    rgb = (colormaps[cmap](scaled)[..., :3] * 255.0 + 0.5).astype(np.uint8)
    rgb[~known] = UNKNOWN_RGB
    return rgb


def save_confidence_map(
    confidence: np.ndarray,
    path: PathLike,
    vmin: float | None = None,
    vmax: float | None = None,
    cmap: str = 'gray',
    description: str | None = None,
) -> Path:
    """Write a confidence map as a PNG, black = low, white = high (as in the paper's figures).

    The values drawn black and white are recorded in the PNG's text (``iTXt``) chunks
    ``vmin``, ``vmax`` and ``Description`` (PIL: ``Image.open(path).text``): the pixels alone
    do not say what a grey level means.

    Args:
        confidence: (H, W) float array, any real range (±inf saturate); NaN marks pixels
            without a value (drawn in ``UNKNOWN_RGB``).
        path: Output PNG file; parent folders are created.
        vmin: Value drawn black; default the finite minimum (use 0 for learned confidence),
            or ``vmax`` where that is lower.
        vmax: Value drawn white; default the finite maximum (use 1 for learned confidence),
            or ``vmin`` where that is higher. ``vmin > vmax`` (both given) inverts the scale. A
            constant map is drawn mid-grey.
        cmap: Any matplotlib colormap name.
        description: The ``Description`` text; default ``'black = <vmin>, white = <vmax>'``.

    Returns:
        The path written, an (H, W) RGB PNG.

    Raises:
        InputError: ``confidence`` is not a non-empty real 2-D array, or ``vmin`` / ``vmax``
            is not a finite number.
        OSError: ``path`` cannot be written (a folder, under a file, no permission).
    """
    confidence = _check_map('confidence', confidence)
    low, high = _scale_bounds(confidence.astype(np.float64), vmin, vmax)
    text = {
        'vmin': f'{low:.9g}',
        'vmax': f'{high:.9g}',
        'Description': description or f'black = {low:.6g}, white = {high:.6g}',
    }
    return _write_rgb(_colorize(confidence, cmap, vmin, vmax), path, text)


def save_disparity_map(
    disparity: np.ndarray,
    path: PathLike,
    max_disparity: float | None = None,
    cmap: str = 'magma',
) -> Path:
    """Write a disparity map as a PNG, dark = far (small d), bright = near.

    Args:
        disparity: (H, W) float array, ≥ 0 pixels; NaN = unknown (drawn ``UNKNOWN_RGB``).
            Callers with ``inf`` = unknown (PFM ground truth) convert it to NaN first.
        path: Output PNG file; parent folders are created.
        max_disparity: Disparity drawn brightest, > 0; default the finite maximum (1 where
            that is 0, so that a map of zeros is drawn dark, as far away).
        cmap: Any matplotlib colormap name.

    Returns:
        The path written, an (H, W) RGB PNG.

    Raises:
        InputError: ``disparity`` is not a non-empty real 2-D array, or ``max_disparity`` is
            not a finite number > 0.
        OSError: ``path`` cannot be written (a folder, under a file, no permission).
    """
    disparity = _check_map('disparity', disparity)
    if max_disparity is None:
        finite = disparity[np.isfinite(disparity)]
        peak = float(finite.max()) if finite.size else 0.0
        # 0 (or below) would make the range [0, 0], drawn as a mid-range colour.
        max_disparity = peak if peak > 0 else 1.0
    elif not is_real(max_disparity) or not 0 < max_disparity < math.inf:
        raise InputError(f'max_disparity must be a finite number > 0; got {max_disparity!r}')
    return _write_rgb(_colorize(disparity, cmap, 0.0, float(max_disparity)), path)


def _confidence_tint() -> np.ndarray:
    """60 % of a 256-entry RGB ramp from red (confidence 0) through yellow (0.5) to green (1),
    as uint16 to add to 40 % of the grey scene."""
    t = np.linspace(0.0, 1.0, 256)
    red = np.where(t < 0.5, 1.0, 2.0 * (1.0 - t))
    green = np.where(t < 0.5, 2.0 * t, 1.0)
    ramp = np.stack([230.0 * red, 200.0 * green, np.zeros_like(t)], axis=1)
    return np.rint(0.6 * ramp).astype(np.uint16)


_TINT = _confidence_tint()


def confidence_overlay(
    image: np.ndarray, confidence: np.ndarray, kept: np.ndarray
) -> np.ndarray:
    """The scene with what the node keeps, coloured by confidence, for a person to look at.

    The image in grey, dimmed to 45 %; the kept pixels tinted from red (confidence 0) through
    yellow (0.5) to green (1), 60 % colour over 40 % scene, so that texture stays visible under
    the tint. Pixels not kept (below the threshold, in a speckle, without a disparity) stay dim
    grey: what a mapper receives is what is coloured. Integer arithmetic: 14–19 ms for 640×480
    on the 2-core CPU of the README's benchmarks.

    Args:
        image: (H, W) or (H, W, C) uint8 image (the left image at the output resolution),
            C = 1, 3 or 4; a colour image is shown as the mean of its first three channels.
        confidence: (H, W) float confidence in [0, 1] (values outside are clipped, NaN is 0).
        kept: (H, W) bool, the pixels the node keeps (``PipelineResult.valid``).

    Returns:
        (H, W, 3) uint8 RGB.

    Raises:
        InputError: Shapes that disagree, an image that is not uint8, or a confidence that is
            not float (an integer map, e.g. 0–255, would be clipped to green almost
            everywhere).
    """
    confidence = _check_map('confidence', confidence)
    if confidence.dtype.kind != 'f':
        raise InputError(
            f'confidence must be a float array in [0, 1]; got dtype {confidence.dtype} '
            '(scale an integer map to [0, 1] first)'
        )
    shape = confidence.shape
    image = np.asarray(image)
    if (
        image.dtype != np.uint8
        or image.shape[:2] != shape
        or image.ndim not in (2, 3)
        or (image.ndim == 3 and image.shape[2] not in (1, 3, 4))
    ):
        raise InputError(
            f'image must be uint8 (H, W) or (H, W, 1|3|4) with (H, W) = {shape}; got '
            f'{image.dtype} {image.shape}'
        )
    kept = np.asarray(kept)
    if kept.dtype != np.bool_ or kept.shape != shape:
        raise InputError(
            f'kept must be a bool array of shape {shape}; got {kept.dtype} {kept.shape}'
        )
    if image.ndim == 3:
        channels = min(image.shape[2], 3)  # a (H, W, 1) image is grey already
        # Channel by channel: numpy's sum over an axis of 3 took 4 of a 640×480 overlay's
        # 15 ms, this 0.3 ms (the same integers).
        gray = image[..., 0].astype(np.uint16)
        for channel in range(1, channels):
            gray += image[..., channel]
        gray //= channels
    else:
        gray = image.astype(np.uint16)
    dim = (gray * 115 + 128) >> 8  # 45 %
    base = (gray * 102 + 128) >> 8  # 40 %
    values = np.nan_to_num(confidence.astype(np.float32), nan=0.0)
    index = np.rint(np.clip(values, 0.0, 1.0) * 255.0).astype(np.uint8)
    tinted = base[..., None] + _TINT[index]
    return np.where(kept[..., None], tinted, dim[..., None]).astype(np.uint8)


def correctness_classes(
    confidence: np.ndarray, error: np.ndarray, tau: float = 0.5
) -> np.ndarray:
    """Tell where a confidence map classifies the disparity correctly at threshold ``tau``.

    The paper's rule (Fig. 4 caption): a pixel is classified correctly if its disparity is
    correct and ``confidence > tau``, or its disparity is wrong and ``confidence <= tau``.

    Args:
        confidence: (...) float array.
        error: Same shape, bool; True = the disparity is wrong.
        tau: Threshold on the confidence, a real number (not NaN: every pixel would be red).

    Returns:
        Bool array of the same shape, True where the confidence classifies correctly.
        NaN confidence compares False both ways, so it yields False; callers mask it out.

    Raises:
        InputError: The shapes differ, ``tau`` is not a number or NaN, ``confidence`` is not
            real, or a float ``error`` holds NaN (cast to bool it would count as wrong;
            :func:`save_correctness_overlay` takes NaN as not judged).
    """
    if not is_real(tau) or math.isnan(tau):
        raise InputError(f'tau must be a real number (not NaN); got {tau!r}')
    confidence = np.asarray(confidence)
    if confidence.dtype.kind not in 'biuf':
        raise InputError(f'confidence must be real numbers; got dtype {confidence.dtype}')
    error = np.asarray(error)
    if error.dtype.kind in 'fc' and np.isnan(error).any():
        raise InputError(
            'error must be a bool array (True = wrong); got '
            f'{int(np.isnan(error).sum())} NaN values in a float error map'
        )
    error = error.astype(bool)
    if confidence.shape != error.shape:
        raise InputError(
            f'confidence and error must have the same shape; got {confidence.shape} '
            f'and {error.shape}'
        )
    with np.errstate(invalid='ignore'):
        return (~error & (confidence > tau)) | (error & (confidence <= tau))


def _gray_background(image: np.ndarray | None, shape: tuple[int, int]) -> np.ndarray:
    if image is None:
        return np.zeros((*shape, 3), dtype=np.uint8)
    image = np.asarray(image)
    if (
        image.shape[:2] != shape
        or image.ndim not in (2, 3)
        or (image.ndim == 3 and image.shape[2] not in (1, 3, 4))
    ):
        raise InputError(
            f'image must be (H, W) or (H, W, 1|3|4) with (H, W) = {shape}; got {image.shape}'
        )
    if image.dtype.kind not in 'biuf':
        raise InputError(f'image must be real numbers; got dtype {image.dtype}')
    gray = image.astype(np.float64)
    if gray.ndim == 3:
        gray = gray[..., :3].mean(axis=2)
    # NaN or ±inf in a float image (pixels without a value) are drawn black; left in, they
    # warned (all-NaN max) and cast to an undefined uint8.
    gray[~np.isfinite(gray)] = 0.0
    peak = float(gray.max()) if gray.size else 0.0
    if image.dtype != np.uint8 and peak <= 1.0:
        gray = gray * 255.0
    elif peak > 255.0:
        # 16-bit (often 10 or 12 bits used) or a float image beyond 8 bits: scaled by its
        # peak, as the node scales a mono16 pair; clipped, it was a white sheet.
        gray = gray * (255.0 / peak)
    # Dimmed so that the green/red classes stand out against the scene.
    dim = np.clip(gray * 0.5, 0, 255).astype(np.uint8)
    return np.repeat(dim[..., None], 3, axis=2)


def save_confidence_overlay(
    image: np.ndarray, confidence: np.ndarray, kept: np.ndarray, path: PathLike
) -> Path:
    """Write :func:`confidence_overlay` (the node's ``confidence_overlay``) as an RGB PNG,
    one pixel per image pixel; parent folders are created.

    Raises:
        InputError: As :func:`confidence_overlay`.
        OSError: ``path`` cannot be written (a folder, under a file, no permission).
    """
    return _write_rgb(confidence_overlay(image, confidence, kept), path)


def save_correctness_overlay(
    confidence: np.ndarray,
    error: np.ndarray,
    path: PathLike,
    tau: float = 0.5,
    image: np.ndarray | None = None,
    mask: np.ndarray | None = None,
) -> Path:
    """Write the paper's green/red correctness visualisation (Fig. 4) as a PNG.

    Green: the disparity is correct and ``confidence > tau``, or it is wrong and
    ``confidence <= tau`` (the confidence classifies it correctly). Red: the opposite.
    Pixels outside ``mask`` (no ground truth, not evaluated) or with NaN confidence show the
    dimmed grey ``image`` (black without one).

    Args:
        confidence: (H, W) float confidence.
        error: (H, W) bool, True = disparity wrong (numbers: non-zero = wrong, NaN = not
            judged, drawn as outside ``mask``).
        path: Output PNG file; parent folders are created.
        tau: Threshold; 0.5 for confidences in [0, 1] as in the paper.
        image: Optional (H, W) or (H, W, 3) reference image drawn under the classes;
            uint8, float in [0, 1] (NaN and ±inf drawn black), or 16-bit / beyond 255
            (scaled by its peak).
        mask: Optional (H, W) bool, True = pixel is evaluated; default every pixel.

    Returns:
        The path written, an (H, W) RGB PNG.

    Raises:
        InputError: Shapes disagree, a dtype that is not real, NaN in a float ``mask``, or a
            ``tau`` that is not a number or NaN.
        OSError: ``path`` cannot be written (a folder, under a file, no permission).
    """
    confidence = _check_map('confidence', confidence).astype(np.float64)
    error_in = _check_map('error', error)
    # A float error map may hold NaN for "not judged": shown as unevaluated, not as wrong
    # (NaN cast to bool is True).
    judged = ~np.isnan(error_in) if error_in.dtype.kind == 'f' else None
    error = np.nan_to_num(error_in).astype(bool) if judged is not None else error_in.astype(bool)
    shape = confidence.shape
    if error.shape != shape:
        raise InputError(f'error must have shape {shape} like confidence; got {error.shape}')
    if mask is None:
        mask = np.ones(shape, dtype=bool)
    else:
        mask = _check_map('mask', mask)
        if mask.dtype.kind == 'f' and np.isnan(mask).any():
            # NaN cast to bool is True: the pixel would be drawn as evaluated.
            raise InputError('mask must be a bool array; got NaN in a float mask')
        mask = mask.astype(bool)
        if mask.shape != shape:
            raise InputError(f'mask must have shape {shape} like confidence; got {mask.shape}')
    rgb = _gray_background(image, shape)
    shown = mask & ~np.isnan(confidence)
    if judged is not None:
        shown &= judged
    right = correctness_classes(confidence, error, tau)
    rgb[shown & right] = CORRECT_RGB
    rgb[shown & ~right] = WRONG_RGB
    return _write_rgb(rgb, path)


def optimal_roc_curve(error_rate: float, samples: int = 201) -> tuple[np.ndarray, np.ndarray]:
    """The ROC curve of a perfect confidence map for a disparity map with error ``error_rate``.

    All correct pixels come first, so the error rate among the first ``p`` of the pixels is
    ``max(0, p − (1 − ε)) / p`` (its integral is the paper's Eq. (1), AUC_opt).

    Args:
        error_rate: ε in [0, 1].
        samples: Number of density samples in (0, 1].

    Returns:
        ``(density, error_rate)``, two float64 arrays of ``samples + 1`` values (``samples``
        where the kink at ``1 − ε`` is 0 or equals a sample, e.g. ε = 0 or ε = 1), density
        ascending, including the kink.

    Raises:
        InputError: ``error_rate`` is not a number in [0, 1], or ``samples`` is not an
            integer ≥ 2.
    """
    if not is_real(error_rate) or not 0.0 <= error_rate <= 1.0:
        raise InputError(f'error_rate must be in [0, 1]; got {error_rate!r}')
    if not is_int(samples) or samples < 2:
        raise InputError(f'samples must be an integer ≥ 2; got {samples!r}')
    density = np.unique(np.append(np.linspace(1.0 / samples, 1.0, samples), 1.0 - error_rate))
    density = density[density > 0]
    rate = np.maximum(0.0, density - (1.0 - error_rate)) / density
    return density, rate


def _curve_problem(density: np.ndarray, rate: np.ndarray) -> str:
    """What is wrong with an ROC curve's values, or '' if nothing."""
    for label, values in (('density', density), ('error rate', rate)):
        if np.isnan(values).any():
            return f'{int(np.isnan(values).sum())} NaN {label} values'
        if values.size and (values.min() < 0.0 or values.max() > 1.0):
            return f'{label} in [{values.min():g}, {values.max():g}]'
    if np.any(np.diff(density) < 0.0):
        at = int(np.flatnonzero(np.diff(density) < 0.0)[0])
        return f'density {density[at]:g} before {density[at + 1]:g} (not ascending)'
    return ''


def save_roc_curves(
    curves: Mapping[str, tuple[np.ndarray, np.ndarray]],
    path: PathLike,
    error_rate: float | None = None,
    title: str | None = None,
) -> Path:
    """Plot ROC curves (error rate over density) of several confidence methods in one figure.

    Args:
        curves: Method name → ``(density, error_rate)``, 1-D arrays of equal length, density
            in (0, 1] ascending, error rate in [0, 1], as returned by ``metrics.roc_curve``.
        path: Output PNG file; parent folders are created.
        error_rate: Overall error ε of the disparity map; when given, the optimal curve is
            drawn as a dashed black line labelled ``optimal``.
        title: Figure title.

    Returns:
        The path written.

    Raises:
        InputError: A curve's two arrays differ in length or are not 1-D, or hold NaN, a
            density outside [0, 1] or not ascending, or an error rate outside [0, 1]; an
            ``error_rate`` that is not a number in [0, 1].
        OSError: ``path`` cannot be written (a folder, under a file, no permission).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(5.0, 4.0), dpi=100)
    FigureCanvasAgg(figure)
    axes = figure.add_subplot(1, 1, 1)
    for name, (density, rate) in curves.items():
        density = np.asarray(density, dtype=np.float64)
        rate = np.asarray(rate, dtype=np.float64)
        if density.ndim != 1 or density.shape != rate.shape:
            raise InputError(
                f'curve {name!r} needs two 1-D arrays of equal length; got {density.shape} '
                f'and {rate.shape}'
            )
        # NaN or an unsorted density would be drawn as a gap or a zigzag, without a word.
        problem = _curve_problem(density, rate)
        if problem:
            raise InputError(f'curve {name!r} needs density in [0, 1] ascending and error rate '
                             f'in [0, 1]; got {problem}')
        # Above the axes' frame and unclipped: a curve at error rate 0 (a scene without
        # errors) lay on the bottom spine, half cut off, and the plot looked empty.
        axes.plot(density, rate, label=name, linewidth=1.5, zorder=3, clip_on=False)
    if error_rate is not None:
        # Not float(error_rate) first: a string or True would pass optimal_roc_curve's checks.
        density, rate = optimal_roc_curve(error_rate)
        axes.plot(density, rate, 'k--', label='optimal', linewidth=1.2, zorder=3,
                  clip_on=False)
    axes.set_xlim(0.0, 1.0)
    axes.set_ylim(bottom=0.0)
    if axes.get_lines() and not any(np.any(line.get_ydata()) for line in axes.get_lines()):
        # Every curve at 0 (no wrong disparity): lifted off the bottom spine, where they
        # vanished, and said in words, or the plot reads as empty.
        axes.set_ylim(-0.002, 0.05)
        axes.text(0.5, 0.5, 'no wrong disparities: every curve is at error rate 0',
                  transform=axes.transAxes, ha='center', fontsize=8, color='0.4')
    axes.set_xlabel('density (fraction of pixels, by decreasing confidence)')
    axes.set_ylabel('error rate')
    if title:
        axes.set_title(title, fontsize=10)
    axes.grid(True, alpha=0.3)
    if axes.get_legend_handles_labels()[0]:  # no curves: an empty legend only warns
        # Where it covers the fewest points: at 'upper left' it hid the flat curve of an
        # uninformative method (error rate ε at every density) or a scene with ε = 1.
        axes.legend(fontsize=8, loc='best')
    figure.tight_layout()
    return _save(path, lambda out: figure.savefig(out, format='png'))


def save_reliability_diagram(
    tables: Mapping[str, ReliabilityTable],
    path: PathLike,
    title: str | None = None,
) -> Path:
    """Plot reliability diagrams: accuracy over mean confidence per bin, and the pixels per bin.

    A calibrated method lies on the diagonal (a confidence of 0.8 is right 80 % of the time);
    below it a method is over-confident, above it under-confident. The lower panel shows how
    the pixels spread over the bins (log scale): most of a good method's pixels sit in the last.

    Args:
        tables: Method name → ``calibration.ReliabilityTable`` (ECE shown in the legend).
        path: Output PNG file; parent folders are created.
        title: Figure title.

    Returns:
        The path written.

    Raises:
        InputError: No tables, or a table holds no pixels.
        OSError: ``path`` cannot be written (a folder, under a file, no permission).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    if not tables:
        raise InputError('no reliability tables to plot')
    figure = Figure(figsize=(5.0, 5.5), dpi=100)
    FigureCanvasAgg(figure)
    top = figure.add_axes((0.14, 0.38, 0.82, 0.54))
    bottom = figure.add_axes((0.14, 0.08, 0.82, 0.2), sharex=top)
    top.plot([0.0, 1.0], [0.0, 1.0], 'k--', linewidth=1.0, label='calibrated')
    for name, table in tables.items():
        if table.n_pixels == 0:
            raise InputError(f'reliability table of {name!r} holds no pixels')
        filled = table.counts > 0
        line = top.plot(
            table.mean_confidence[filled], table.accuracy[filled], marker='o', markersize=3,
            linewidth=1.5, label=f'{name} (ECE {100 * table.ece:.1f} %)',
        )
        centres = 0.5 * (table.edges[:-1] + table.edges[1:])
        bottom.plot(centres[filled], table.counts[filled] / table.n_pixels, marker='o',
                    markersize=3, linewidth=1.0, color=line[0].get_color())
    top.set_xlim(0.0, 1.0)
    top.set_ylim(0.0, 1.0)
    top.set_ylabel('share of correct disparities')
    top.grid(True, alpha=0.3)
    top.legend(fontsize=8, loc='upper left')
    if title:
        top.set_title(title, fontsize=10)
    bottom.set_yscale('log')
    bottom.set_xlabel('confidence')
    bottom.set_ylabel('share of pixels')
    bottom.grid(True, alpha=0.3)
    return _save(path, lambda out: figure.savefig(out, format='png'))

"""PNG helpers: confidence and disparity maps, the correctness overlay, ROC curves and
reliability diagrams.

Arrays in, PNG path out. Maps are written pixel for pixel (one PNG pixel per array element,
no axes), so they can be laid over the input image; ROC curves and reliability diagrams are
small matplotlib figures.
Only the Agg canvas is used, never ``pyplot``, so importing this module changes no global
matplotlib state and needs no display.
"""

from __future__ import annotations

from collections.abc import Mapping
import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from cva_confidence_ros.errors import InputError

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


def _check_map(name: str, array: np.ndarray) -> np.ndarray:
    array = np.asarray(array)
    if array.ndim != 2 or array.size == 0:
        raise InputError(f'{name} must be a non-empty (H, W) array; got shape {array.shape}')
    if not np.issubdtype(array.dtype, np.number) and array.dtype != np.bool_:
        raise InputError(f'{name} must be numeric; got dtype {array.dtype}')
    return array


def _prepare_path(path: PathLike) -> Path:
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    return out


def _write_rgb(rgb: np.ndarray, path: PathLike) -> Path:
    from matplotlib.image import imsave

    out = _prepare_path(path)
    imsave(out, np.ascontiguousarray(rgb, dtype=np.uint8), format='png')
    return out


def _colorize(
    values: np.ndarray, cmap: str, vmin: float | None, vmax: float | None
) -> np.ndarray:
    """Map values through ``cmap`` onto (H, W, 3) uint8; NaN becomes UNKNOWN_RGB."""
    from matplotlib import colormaps

    values = values.astype(np.float64)
    finite = np.isfinite(values)
    known = ~np.isnan(values)
    if vmin is None:
        vmin = float(values[finite].min()) if finite.any() else 0.0
    if vmax is None:
        vmax = float(values[finite].max()) if finite.any() else 1.0
    span = vmax - vmin
    # A constant map would divide by zero; draw it mid-grey rather than fail.
    scaled = (values - vmin) / span if span > 0 else np.full(values.shape, 0.5)
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
) -> Path:
    """Write a confidence map as a PNG, black = low, white = high (as in the paper's figures).

    Args:
        confidence: (H, W) float array, any real range (±inf saturate); NaN marks pixels
            without a value (drawn in ``UNKNOWN_RGB``).
        path: Output PNG file; parent folders are created.
        vmin: Value drawn black; default the finite minimum (use 0 for learned confidence).
        vmax: Value drawn white; default the finite maximum (use 1 for learned confidence).
        cmap: Any matplotlib colormap name.

    Returns:
        The path written, an (H, W) RGB PNG.

    Raises:
        InputError: ``confidence`` is not a non-empty numeric 2-D array.
    """
    confidence = _check_map('confidence', confidence)
    return _write_rgb(_colorize(confidence, cmap, vmin, vmax), path)


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
        max_disparity: Disparity drawn brightest; default the finite maximum.
        cmap: Any matplotlib colormap name.

    Returns:
        The path written, an (H, W) RGB PNG.

    Raises:
        InputError: ``disparity`` is not a non-empty numeric 2-D array.
    """
    disparity = _check_map('disparity', disparity)
    return _write_rgb(_colorize(disparity, cmap, 0.0, max_disparity), path)


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
        InputError: Shapes that disagree, or an image that is not uint8.
    """
    confidence = _check_map('confidence', confidence)
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
        gray = image[..., :channels].sum(axis=2, dtype=np.uint16) // channels
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
        tau: Threshold on the confidence.

    Returns:
        Bool array of the same shape, True where the confidence classifies correctly.
        NaN confidence compares False both ways, so it yields False; callers mask it out.

    Raises:
        InputError: The shapes differ.
    """
    confidence = np.asarray(confidence)
    error = np.asarray(error, dtype=bool)
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
        InputError: Shapes disagree.
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
        mask = _check_map('mask', mask).astype(bool)
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
        InputError: ``error_rate`` outside [0, 1] or ``samples`` < 2.
    """
    if not 0.0 <= error_rate <= 1.0:
        raise InputError(f'error_rate must be in [0, 1]; got {error_rate}')
    if samples < 2:
        raise InputError(f'samples must be ≥ 2; got {samples}')
    density = np.unique(np.append(np.linspace(1.0 / samples, 1.0, samples), 1.0 - error_rate))
    density = density[density > 0]
    rate = np.maximum(0.0, density - (1.0 - error_rate)) / density
    return density, rate


def save_roc_curves(
    curves: Mapping[str, tuple[np.ndarray, np.ndarray]],
    path: PathLike,
    error_rate: float | None = None,
    title: str | None = None,
) -> Path:
    """Plot ROC curves (error rate over density) of several confidence methods in one figure.

    Args:
        curves: Method name → ``(density, error_rate)``, 1-D arrays of equal length, density
            in (0, 1] ascending, as returned by ``metrics.roc_curve``.
        path: Output PNG file; parent folders are created.
        error_rate: Overall error ε of the disparity map; when given, the optimal curve is
            drawn as a dashed black line labelled ``optimal``.
        title: Figure title.

    Returns:
        The path written.

    Raises:
        InputError: A curve's two arrays differ in length or are not 1-D.
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
        axes.plot(density, rate, label=name, linewidth=1.5)
    if error_rate is not None:
        density, rate = optimal_roc_curve(float(error_rate))
        axes.plot(density, rate, 'k--', label='optimal', linewidth=1.2)
    axes.set_xlim(0.0, 1.0)
    axes.set_ylim(bottom=0.0)
    axes.set_xlabel('density (fraction of pixels, by decreasing confidence)')
    axes.set_ylabel('error rate')
    if title:
        axes.set_title(title, fontsize=10)
    axes.grid(True, alpha=0.3)
    if axes.get_legend_handles_labels()[0]:  # no curves: an empty legend only warns
        axes.legend(fontsize=8, loc='upper left')
    figure.tight_layout()
    out = _prepare_path(path)
    figure.savefig(out, format='png')
    return out


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
    out = _prepare_path(path)
    figure.savefig(out, format='png')
    return out

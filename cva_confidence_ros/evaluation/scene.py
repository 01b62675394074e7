"""Score confidence methods on one stereo scene with ground truth (the paper's protocol).

Per scene and matcher: cost volume → winner-takes-all disparity → KITTI error label at every
pixel with ground truth → for each confidence method the ROC curve, its AUC, and the optimal
AUC of that disparity map (paper Sec. 4.1, Eq. (1)). Lower AUC is better.

Pixel subsets (``max_pixels``): a fixed random subset of the ground-truth pixels is scored
instead of all of them. Learned methods that can run at single pixels (CVA-Net, patch mode)
are computed only there; the other methods are computed densely (they are cheap) and read at
the same pixels, so every method is scored on exactly the same pixels.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping, MutableMapping, Sequence
import contextlib
from dataclasses import dataclass
from pathlib import Path
import sys
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from cva_confidence_ros.checks import is_int
from cva_confidence_ros.errors import InputError
from cva_confidence_ros.evaluation.records import EvalRecord
from cva_confidence_ros.outputs import naming

if TYPE_CHECKING:
    from cva_confidence_ros.calibration import ReliabilityTable

__all__ = [
    'ScoredMethod',
    'confidence_at',
    'evaluate_scene',
    'overlay_threshold',
    'score_confidence',
    'select_pixels',
]

Logger = Callable[[str], None]


@dataclass(frozen=True)
class ScoredMethod:
    """ROC analysis of one confidence map on a set of pixels.

    Attributes:
        auc: Area under the ROC curve, in [0, 1]; lower = better.
        auc_opt: Optimal AUC for the error rate (paper Eq. (1)), over the density range of
            the ROC curve: for ε above ``1 −`` its first density (ε > 0.95) the area left of
            the curve's start is not counted, as it is not in ``auc`` either.
        error_rate: Fraction of the scored pixels whose disparity is wrong.
        n_pixels: Number of scored pixels.
        density: (K,) float ROC density samples in (0, 1], ascending.
        roc_error: (K,) float error rate among the ``density`` most confident pixels.
    """

    auc: float
    auc_opt: float
    error_rate: float
    n_pixels: int
    density: np.ndarray
    roc_error: np.ndarray


def select_pixels(
    known: np.ndarray, max_pixels: int | None = None, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Pick the pixels to score: all ground-truth pixels, or a fixed random subset of them.

    Args:
        known: (H, W) bool, True where the ground truth is known.
        max_pixels: Subset size N ≥ 1; None (or N ≥ number of known pixels) = all of them.
        seed: Seed of the subset; the same (``known``, N, seed) always gives the same pixels.

    Returns:
        ``(ys, xs)``, two (M,) int64 arrays in row-major order, M = min(N, known pixels).

    Raises:
        InputError: ``known`` is not a 2-D bool mask, ``max_pixels`` is not an integer ≥ 1
            (or None) or ``seed`` not an integer ≥ 0.
    """
    known = np.asarray(known)
    if known.dtype != np.bool_:
        # A cast read a disparity map given in its place as known where it is NaN or nonzero.
        raise InputError(
            f'known must be an (H, W) bool mask (e.g. np.isfinite(gt)); got dtype {known.dtype}'
        )
    if known.ndim != 2:
        raise InputError(f'known must be an (H, W) bool mask; got shape {known.shape}')
    # NaN passed every comparison and scored all pixels; 2.5 or True failed in numpy's choice.
    if max_pixels is not None and not is_int(max_pixels):
        raise InputError(f'max_pixels must be an integer ≥ 1 or None; got {max_pixels!r}')
    if max_pixels is not None and max_pixels < 1:
        raise InputError(f'max_pixels must be ≥ 1 or None; got {max_pixels}')
    if not is_int(seed):
        raise InputError(f'seed must be an integer ≥ 0; got {seed!r}')
    if seed < 0:  # numpy's generator says only 'expected non-negative integer'
        raise InputError(f'seed must be ≥ 0; got {seed}')
    flat = np.flatnonzero(known)
    if max_pixels is not None and max_pixels < flat.size:
        rng = np.random.default_rng(seed)
        flat = np.sort(rng.choice(flat, size=max_pixels, replace=False))
    ys, xs = np.unravel_index(flat, known.shape)
    return ys.astype(np.int64), xs.astype(np.int64)


def score_confidence(confidence: np.ndarray, error: np.ndarray) -> ScoredMethod:
    """ROC curve, AUC and optimal AUC of confidence values against error labels.

    Args:
        confidence: (N,) or (H, W) real (float or int) confidence at the scored pixels,
            higher = more confident; ±inf allowed, NaN not. Ranked in its own dtype (a
            float64 map keeps its order).
        error: Same shape, bool, True = the disparity is wrong.

    Returns:
        The :class:`ScoredMethod`.

    Raises:
        InputError: Shapes differ, nothing to score, NaN confidence, ``confidence`` is not
            real (bool, complex, str, object) or ``error`` is not bool.
    """
    from cva_confidence_ros.metrics import auc_scores, roc_curve

    # No cast: casting to float would read a bool confidence as 0 / 1, drop a complex one's
    # imaginary part, parse a str one ('a' a bare ValueError), and casting a float64 map down
    # would tie values that differ only beyond float32's 7 digits.
    confidence = np.asarray(confidence)
    error = np.asarray(error)
    if confidence.dtype.kind not in 'fiu':
        raise InputError(
            f'confidence must hold real numbers (float or int); got dtype {confidence.dtype}'
        )
    if error.dtype != np.bool_:
        raise InputError(f'error must be a bool array (True = wrong); got dtype {error.dtype}')
    if confidence.shape != error.shape:
        raise InputError(
            f'confidence and error must have the same shape; got {confidence.shape} '
            f'and {error.shape}'
        )
    confidence = confidence.ravel()
    error = error.ravel()
    if confidence.size == 0:
        raise InputError('no pixels to score: the scene has no ground-truth pixels')
    if np.isnan(confidence).any():
        bad = int(np.isnan(confidence).sum())
        raise InputError(f'confidence must not be NaN at scored pixels; got {bad} NaN values')
    scores = auc_scores(confidence, error)
    density, roc_error = roc_curve(confidence, error)
    return ScoredMethod(
        auc=float(scores['auc']),
        auc_opt=float(scores['auc_opt']),
        error_rate=float(scores['error_rate']),
        n_pixels=int(scores['n_pixels']),
        density=np.asarray(density, dtype=np.float64),
        roc_error=np.asarray(roc_error, dtype=np.float64),
    )


def overlay_threshold(confidence: np.ndarray, error_rate: float) -> float:
    """Threshold τ of the green/red correctness overlay for a confidence map.

    Confidences in [0, 1] (learned, probabilistic) use the paper's τ = 0.5. Hand-crafted
    measures on other scales have no natural 0.5, so τ is their ε-quantile: the most
    confident 1 − ε of the pixels count as "confident", as many as there are correct ones.

    Args:
        confidence: Confidence values at the scored pixels, any shape.
        error_rate: ε of the disparity map on those pixels, in [0, 1].

    Returns:
        τ as a float.
    """
    values = np.asarray(confidence, dtype=np.float64)
    values = values[np.isfinite(values)]
    if values.size == 0 or (values.min() >= 0.0 and values.max() <= 1.0):
        return 0.5
    return float(np.quantile(values, min(max(error_rate, 0.0), 1.0)))


def confidence_at(
    method: Any, inputs: Any, ys: np.ndarray, xs: np.ndarray
) -> tuple[np.ndarray, np.ndarray | None]:
    """Confidence of ``method`` at pixels ``(ys, xs)``, computed only there if it can.

    Patch mode is used for a method that offers ``confidence_at(inputs, ys, xs)`` (CVA-Net:
    ``model.predict_confidence_at`` on 13×13×D extracts); any other method is run densely and
    read at the pixels.

    Args:
        method: A confidence method from ``confidence.CONFIDENCE_METHODS``.
        inputs: Its ``ConfidenceInputs``.
        ys: (N,) int row indices.
        xs: (N,) int column indices.

    Returns:
        ``(values, dense)``: (N,) float32 confidences and the (H, W) float32 map if the method
        was run densely, else None.

    Raises:
        InputError: The cost volume does not fit the network (depth) or matcher.
    """
    point_fn = getattr(method, 'confidence_at', None)
    if callable(point_fn):
        return np.asarray(point_fn(inputs, ys, xs), dtype=np.float32).ravel(), None
    dense = np.asarray(method(inputs), dtype=np.float32)
    return dense[ys, xs], dense


@contextlib.contextmanager
def _network_progress(method: Any, label: str, enabled: bool) -> Iterator[None]:
    """A tqdm bar fed by the ``progress`` hook of ``method.evaluator`` (CVA-Net and the
    networks run like it) while the block runs; nothing for other methods or if not enabled."""
    evaluator = getattr(method, 'evaluator', None)
    if not enabled or evaluator is None or not hasattr(evaluator, 'progress'):
        yield
        return
    from tqdm import tqdm

    bar = None
    # In a log file (not a terminal) every refresh is one more '\r'-joined copy of the bar on
    # the same line: a minute apart there instead of a second.
    interval = 1.0 if sys.stderr.isatty() else 60.0

    def update(done: int, total: int) -> None:
        nonlocal bar
        if bar is None:
            bar = tqdm(total=total, desc=label, unit='px', unit_scale=True, leave=False,
                       dynamic_ncols=True, mininterval=interval)
        bar.update(done - bar.n)

    evaluator.progress = update
    try:
        yield
    finally:
        evaluator.progress = None
        if bar is not None:
            bar.close()


#: How ``confidence_<method>.png`` is scaled, as recorded beside it (:func:`_map_range`).
FIXED_RANGE = 'fixed [0, 1]: every value lies in [0, 1]'
PERCENTILE_RANGE = "1st and 99th percentile of the map's finite values; values beyond saturate"


def _map_range(values: np.ndarray) -> tuple[float, float, str]:
    """(value drawn black, value drawn white, how they were chosen) of a confidence map."""
    finite = values[np.isfinite(values)]
    if finite.size == 0 or (finite.min() >= 0.0 and finite.max() <= 1.0):
        return 0.0, 1.0, FIXED_RANGE
    # Hand-crafted ratios (PKRN) have long tails that would leave the map black.
    low, high = np.percentile(finite, [1.0, 99.0])
    # + 0.0: LRC's best value was written 'white = -0'.
    return float(low) + 0.0, float(high) + 0.0, PERCENTILE_RANGE


def _write_plots(
    plot_dir: Path,
    sample: Any,
    disparity: np.ndarray,
    max_disparity: int,
    error: np.ndarray,
    ys: np.ndarray,
    xs: np.ndarray,
    maps: Mapping[str, np.ndarray],
    scores: Mapping[str, ScoredMethod],
    matcher: str,
) -> None:
    from cva_confidence_ros.plots import (
        save_confidence_map,
        save_correctness_overlay,
        save_disparity_map,
        save_roc_curves,
    )

    mask = np.zeros(disparity.shape, dtype=bool)
    mask[ys, xs] = True
    # Each under naming(): a full disk said only '[Errno 28] No space left on device'.
    path = plot_dir / 'disparity.png'
    with naming(path):
        save_disparity_map(disparity, path, max_disparity=max_disparity - 1)
    for name, confidence in maps.items():
        vmin, vmax, how = _map_range(confidence)
        tau = overlay_threshold(confidence[ys, xs], scores[name].error_rate)
        # A hand-crafted measure's map is stretched over its own percentiles: without the
        # values a reader could not tell what black and white mean, nor compare two PNGs.
        path = plot_dir / f'confidence_{name}.png'
        with naming(path):
            save_confidence_map(
                confidence, path, vmin, vmax,
                description=f'{sample.dataset}/{sample.scene} {matcher} {name}: black = '
                f'{vmin:.6g}, white = {vmax:.6g} ({how}); correct_{name}.png τ = {tau:.6g}',
            )
        path = plot_dir / f'correct_{name}.png'
        with naming(path):
            save_correctness_overlay(
                confidence, error, path, tau=tau, image=sample.left, mask=mask,
            )
    any_score = next(iter(scores.values()))
    path = plot_dir / 'roc.png'
    with naming(path):
        save_roc_curves(
            {name: (s.density, s.roc_error) for name, s in scores.items()},
            path,
            error_rate=any_score.error_rate,
            # The matcher too: the PNG pasted into a report no longer has its folder's name.
            title=f'{sample.dataset}/{sample.scene}  {matcher}  '
            f'ε = {100 * any_score.error_rate:.1f} %',
        )


def evaluate_scene(
    sample: Any,
    matcher: str,
    methods: Mapping[str, Any],
    *,
    max_disparity: int = 64,
    max_pixels: int | None = None,
    seed: int = 0,
    plot_dir: str | Path | None = None,
    log: Logger | None = None,
    method_order: Sequence[str] | None = None,
    progress: bool = False,
    reliability: MutableMapping[tuple[str, str, str], ReliabilityTable] | None = None,
) -> list[EvalRecord]:
    """Score confidence methods on one scene for one matcher.

    The scene is first halved in resolution until its largest ground-truth disparity fits
    the cost-volume depth, i.e. is at most D − 1 (``datasets.fit_disparity_range``, as in the
    paper: halved "as long as the maximum disparity exceeds 255" for D = 256).

    Args:
        sample: A ``datasets.StereoSample`` (left/right uint8 images, (H, W) float32
            ground-truth disparity with NaN = unknown).
        matcher: Registered matcher name.
        methods: Method name → confidence method built for this matcher and depth (from
            ``confidence.CONFIDENCE_METHODS``); built once by the caller so learned weights
            are loaded once.
        max_disparity: Cost-volume depth D.
        max_pixels: Score a fixed random subset of this many ground-truth pixels; None = all.
        seed: Seed of that subset.
        plot_dir: If given, write ``disparity.png``, ``confidence_<method>.png``,
            ``correct_<method>.png`` (green/red overlay on the scored pixels) and ``roc.png``
            there. Each confidence PNG records in its text chunks (``vmin``, ``vmax``,
            ``Description``) the values drawn black and white, how they were chosen, and the
            overlay's τ. In a subset run, a method computed in patch mode has values only at
            the scored pixels; the rest of its confidence map is drawn in
            ``plots.UNKNOWN_RGB``.
        log: Receives one progress line per stage (matching, each method), with seconds.
        method_order: Order of the records; default the order of ``methods``.
        progress: Show a progress bar on stderr (pixels) while a network method runs: on a
            CPU, CVA-Net on a whole Middlebury v3 image takes minutes.
        reliability: If given, the reliability table (``calibration.reliability``) of each
            probabilistic method (``ConfidenceMethod.probabilistic``: the networks) on the
            scored pixels is merged into it under ``(dataset, matcher, method)``. With
            ``plot_dir``, such methods also get ``reliability.png`` there.

    Returns:
        One :class:`EvalRecord` per method, in ``method_order``.

    Raises:
        InputError: The scene has no ground-truth pixels, ``method_order`` names a method
            not in ``methods``, or a method returns a bad map (NaN at a scored pixel, or, in
            patch mode, not one value per scored pixel); the message names the method.
        ConfigError: Unknown matcher.
    """
    from cva_confidence_ros.confidence import ConfidenceInputs
    from cva_confidence_ros.datasets import fit_disparity_range
    from cva_confidence_ros.matching import compute_cost_volume, wta_disparity
    from cva_confidence_ros.metrics import kitti_error

    names = list(method_order) if method_order is not None else list(methods)
    unknown = [name for name in names if name not in methods]
    if unknown:  # a bare KeyError before
        raise InputError(
            f'method_order names methods that are not given: {unknown}; given: {list(methods)}'
        )
    emit = log if log is not None else (lambda _message: None)
    largest = sample.max_disparity
    sample, factor = fit_disparity_range(sample, max_disparity)
    if factor > 1:
        # The cost volume holds d = 0 … D − 1: a ground truth of D − 0.5 is halved, though it
        # does not exceed D.
        emit(f'ground truth reaches {largest:.4g} px > D − 1 = {max_disparity - 1}: '
             f'evaluating at 1/{factor} resolution')
    gt = np.asarray(sample.disparity, dtype=np.float32)
    ys, xs = select_pixels(np.isfinite(gt), max_pixels, seed)
    if ys.size == 0:
        raise InputError(
            f'scene {sample.dataset}/{sample.scene} has no ground-truth pixels to score'
        )

    tic = time.perf_counter()
    volume = compute_cost_volume(sample.left, sample.right, matcher, max_disparity)
    disparity = wta_disparity(volume)
    volume_right = disparity_right = None
    if any(getattr(methods[name], 'needs_right', False) for name in names):
        volume_right = compute_cost_volume(
            sample.left, sample.right, matcher, max_disparity, view='right'
        )
        disparity_right = wta_disparity(volume_right)
    emit(f'{matcher} matching {volume.shape[2]}x{volume.shape[1]}x{volume.shape[0]} '
         f'{time.perf_counter() - tic:.2f} s')
    inputs = ConfidenceInputs(
        cost_volume=volume,
        disparity=disparity,
        image=sample.left,
        cost_volume_right=volume_right,
        disparity_right=disparity_right,
        matcher=matcher,
    )
    error_map = np.asarray(kitti_error(disparity, gt), dtype=bool)
    error = error_map[ys, xs]
    subset = max_pixels is not None

    records: list[EvalRecord] = []
    maps: dict[str, np.ndarray] = {}
    scores: dict[str, ScoredMethod] = {}
    tables: dict[str, ReliabilityTable] = {}
    for name in names:
        tic = time.perf_counter()
        with _network_progress(methods[name], f'{matcher} {name}', progress):
            if subset:
                values, dense = confidence_at(methods[name], inputs, ys, xs)
            else:
                dense = np.asarray(methods[name](inputs), dtype=np.float32)
                values = None
        if dense is not None and dense.shape != disparity.shape:
            raise InputError(
                f'confidence method {name!r} must return shape {disparity.shape}; '
                f'got {dense.shape}'
            )
        if values is None:
            assert dense is not None  # values is None only where the method was run densely
            values = dense[ys, xs]
        elif values.shape != ys.shape:
            # A bare numpy broadcast ValueError before (or, for one value, a filled map).
            raise InputError(
                f'confidence method {name!r} must return one value per scored pixel, '
                f'{ys.size}; got {values.size}'
            )
        if dense is None:
            dense = np.full(disparity.shape, np.nan, dtype=np.float32)
            dense[ys, xs] = values
        try:
            score = score_confidence(values, error)
        except InputError as exc:  # a NaN map named neither the method nor the scene
            raise InputError(
                f'confidence method {name!r} on {sample.dataset}/{sample.scene}: {exc}'
            ) from None
        emit(f'{matcher} {name} {time.perf_counter() - tic:.2f} s '
             f'AUC {100 * score.auc:.2f} (opt {100 * score.auc_opt:.2f})')
        maps[name] = dense
        scores[name] = score
        if getattr(methods[name], 'probabilistic', False):
            from cva_confidence_ros.calibration import add_table
            from cva_confidence_ros.calibration import reliability as reliability_table

            tables[name] = reliability_table(values, ~error)
            if reliability is not None:
                add_table(reliability, (sample.dataset, matcher, name), tables[name])
        records.append(
            EvalRecord(
                dataset=sample.dataset,
                scene=sample.scene,
                matcher=matcher,
                method=name,
                auc=score.auc,
                auc_opt=score.auc_opt,
                error_rate=score.error_rate,
                n_pixels=score.n_pixels,
            )
        )
    if plot_dir is not None and scores:
        _write_plots(
            Path(plot_dir), sample, disparity, max_disparity, error_map, ys, xs, maps, scores,
            matcher,
        )
        if tables:
            from cva_confidence_ros.plots import save_reliability_diagram

            path = Path(plot_dir) / 'reliability.png'
            with naming(path):
                save_reliability_diagram(
                    tables, path, title=f'{sample.dataset}/{sample.scene}  {matcher}',
                )
        _remove_stale_plots(Path(plot_dir), set(maps), bool(tables))
    return records


def _remove_stale_plots(plot_dir: Path, methods: set[str], reliability: bool) -> None:
    """Remove the PNGs of an earlier run in ``plot_dir`` that this scene's run did not write
    (other methods' maps and overlays, a reliability diagram): they sat beside this run's as
    if of it."""
    stale = [
        path
        for prefix in ('confidence_', 'correct_')
        for path in plot_dir.glob(f'{prefix}*.png')
        if path.stem[len(prefix):] not in methods
    ]
    if not reliability:
        stale.append(plot_dir / 'reliability.png')
    for path in stale:
        with contextlib.suppress(OSError):
            if path.is_file() and not path.is_symlink():
                path.unlink()

"""Per-frame confidence metrics of a replay and its report (JSON, CSV, Markdown, PNGs).

Scoring reuses the evaluation module (``evaluation.select_pixels``,
``evaluation.score_confidence``, ``metrics.kitti_error``) on the disparity the node publishes,
so with ``--subpixel none`` (integer disparities, the paper's protocol) a frame's AUC is exactly
what ``cva-evaluate`` reports for the same images, ground truth and pixel subset; with sub-pixel
disparities (the default) the error labels of a few pixels near 3 px differ.

Per frame, on the pixels with ground truth (or a fixed random subset of ``max_pixels`` of them):

* ``error_rate``: fraction of wrong disparities (KITTI criterion: |d − d_gt| ≥ 3 px and
  ≥ 5 % of d_gt; a NaN disparity is wrong);
* ``auc`` / ``auc_opt``: area under the ROC curve of the confidence map and its optimum;
* ``kept_density``: fraction of those pixels the node keeps (finite disparity, confidence ≥
  threshold and not in a speckle, i.e. finite in ``disparity_filtered``);
* ``kept_error_rate``: fraction of wrong disparities among the kept pixels (None if none);
* ``expected_kept_error``: for a method whose confidence is a probability (the networks), the
  error rate it predicts for the same kept pixels, mean(1 − confidence) — what the node reports
  in ``/diagnostics`` without ground truth — to compare with ``kept_error_rate``;
* ``kept_epe``: mean absolute disparity error |d − d_gt| of the kept pixels (end-point error,
  pixels at the processed resolution; what sub-pixel refinement lowers).

Per frame on all pixels, with or without ground truth (what a robot's own bag can tell; the
node's ``/diagnostics`` reports the same two numbers):

* ``kept_fraction``: share of the pixels the node keeps (of those it judges: its region of
  interest ``roi_top`` to ``roi_bottom`` and the pixels its ignore mask leaves, when it has
  them);
* ``predicted_kept_error``: for the networks, mean(1 − confidence) over those kept pixels, the
  error rate their confidence predicts (README, *What a confidence of 0.8 means*);
* ``mean_confidence``: mean confidence of the pixels with a disparity.

The report's PNGs: a confidence map and the node's ``confidence_overlay`` of frames spread
evenly over the bag (``overlay_<frame>.png``, :class:`ReportWriter`), the ROC curve of those
with ground truth, ``confidence_over_time.png`` (kept share and predicted error of every frame:
where the scene got hard), ``least_kept_<frame>.png`` (the overlay of the frame in which the
node kept the least) and, with ground truth, ``auc_over_time.png``.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Collection
import csv
from dataclasses import asdict, dataclass, field
import io
import math
import os
from pathlib import Path
import re
from typing import TYPE_CHECKING, Any, BinaryIO, cast

import numpy as np

from cva_confidence_ros import strict_json
from cva_confidence_ros.errors import ConfigError, InputError, reason
from cva_confidence_ros.outputs import lock_folder, write_atomic

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = [
    'FRAME_KEYS',
    'SCAN_KEYS',
    'FrameScore',
    'METRIC_KEYS',
    'REPORT_KEYS',
    'ReplayReport',
    'ReportFolderLock',
    'ReportWriter',
    'check_report_folder',
    'clear_report',
    'report_files',
    'score_frame',
]

METRIC_KEYS = ('error_rate', 'auc', 'auc_opt', 'kept_density', 'kept_error_rate')
REPORT_KEYS = ('frame', 'stamp_ns', *METRIC_KEYS)
#: Statistics of every frame, with or without ground truth (all pixels).
FRAME_KEYS = ('kept_fraction', 'predicted_kept_error', 'mean_confidence')
#: The laser scan against the ground truth's (``--scan`` and ground truth).
SCAN_KEYS = ('scan_beams', 'scan_phantom_rate', 'scan_far_rate', 'scan_none_rate')
_EXTRA_KEYS = (
    'expected_kept_error', 'kept_epe', *FRAME_KEYS, *SCAN_KEYS, 'n_pixels', 'width', 'height',
    'processing_ms', 'latency_ms', 'note',
)
#: Names of the files a replay writes into its report folder (``node.log``: live mode).
#: (A killed writer's partial file, ``report.csv.<pid>-<thread>.tmp``, is one of them.)
_REPORT_FILE = re.compile(
    r'((report\.json|report\.csv|summary\.md|auc_over_time\.png|confidence_over_time\.png)'
    r'(\.\d+-\d+\.tmp)?)|report\.json\.tmp|node\.log'
    r'|(confidence|roc|overlay|least_kept)_\d+\.png'
)
#: Unpaired messages listed one by one in ``report.json`` (all are counted).
MAX_LISTED_UNPAIRED = 100


def report_files(folder: str | Path) -> list[Path]:
    """The files in ``folder`` whose names are those a replay writes (sorted)."""
    path = Path(folder)
    if not path.is_dir():
        return []
    return sorted(
        p for p in path.iterdir()
        if _REPORT_FILE.fullmatch(p.name) and p.is_file() and not p.is_symlink()
    )


def _busy_message(folder: str | Path) -> str:
    return (
        f'the report folder {folder} is being written by another cva-bag-replay now; wait '
        f'until it ends, or pick another folder'
    )


def report_folder_busy(folder: str | Path) -> bool:
    """Whether another process holds the :class:`ReportFolderLock` of ``folder`` now."""
    path = Path(folder)
    if not path.is_dir() or path.resolve() in ReportFolderLock.held:
        return False
    try:
        handle = lock_folder(path, shared=True)
    except BlockingIOError:
        return True
    if handle is not None:
        os.close(handle)
    return False


class ReportFolderLock:
    """Holds a report folder for one run (``flock`` on the folder itself, so no file is left
    behind and a killed run holds nothing): two replays into one folder at once both passed
    the empty-folder check and wrote a mix of their PNGs and reports, without a word.

    Creates the folder. Re-entrant within a process (live mode holds it from before the old
    report is cleared; its session takes it again).

    Raises:
        ConfigError: Another process holds the folder, or it cannot be created.
    """

    #: Resolved folders held by this process → how many times.
    held: dict[Path, int] = {}

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        self._key: Path | None = None
        self._fd: int | None = None

    def __enter__(self) -> ReportFolderLock:
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            key = self.folder.resolve()
            if key in self.held:
                self.held[key] += 1
                self._key = key
                return self
        except OSError as err:
            raise ConfigError(
                f'cannot create the report folder {self.folder}: {reason(err)}'
            ) from None
        try:
            fd = lock_folder(self.folder)  # None: no locks here, run unguarded as before
        except BlockingIOError:
            raise ConfigError(_busy_message(self.folder)) from None
        self.held[key] = 1
        self._key, self._fd = key, fd
        return self

    def __exit__(self, *exc: object) -> None:
        if self._key is None:
            return
        self.held[self._key] -= 1
        if not self.held[self._key]:
            del self.held[self._key]
            if self._fd is not None:
                os.close(self._fd)  # releases the lock
        self._key = self._fd = None


def check_report_folder(
    folder: str | Path, overwrite: bool, ignore: Collection[Path] = ()
) -> None:
    """Refuse a report folder that holds something, unless ``overwrite`` and it is a report.

    A folder that holds an earlier report would end up with a mix of two runs (old PNGs next
    to a new ``report.json``), so it needs ``overwrite`` (:func:`clear_report` then removes
    the old report's files, and only those). A folder that does not look like a report (no
    ``report.json``, and names this tool never writes) is refused even with ``overwrite``,
    and so is one where a name of the report's files is a symbolic link or a folder.

    Args:
        folder: The report folder (need not exist).
        overwrite: ``--overwrite`` was given.
        ignore: Entries of the folder that do not count (resolved paths: the input and
            output bags when they lie inside it, and what holds them).

    Raises:
        ConfigError: The folder holds something and ``overwrite`` is off, or it holds
            something that is not a report (a link or folder of a report file's name too),
            or another run is writing it now (:class:`ReportFolderLock`).
    """
    path = Path(folder)
    if not path.is_dir():
        return
    if report_folder_busy(path):
        # Before the listing: "holds an earlier report, use --overwrite" would have the user
        # delete the files of a run that is still writing them.
        raise ConfigError(_busy_message(folder))
    entries = sorted(p for p in path.iterdir() if p.resolve() not in ignore)
    if not entries:
        return
    for entry in entries:
        if _REPORT_FILE.fullmatch(entry.name) and (entry.is_symlink() or not entry.is_file()):
            # Neither listed as the report's nor deleted by clear_report: the report was then
            # written through a link (into the file it points to, elsewhere) or failed at the
            # end of the run on a folder of that name.
            kind = 'a symbolic link' if entry.is_symlink() else 'not a file'
            raise ConfigError(
                f'the report folder {folder} holds {entry.name}, which is {kind}; a report '
                f'writes a file of that name: remove it, or pick another folder'
            )
    names = [p.name for p in entries]
    listing = ', '.join(names[:3]) + (f' and {len(names) - 3} more' if len(names) > 3 else '')
    ours = {p.name for p in report_files(path)}
    is_report = 'report.json' in ours or all(name in ours for name in names)
    if not is_report:
        raise ConfigError(
            f'the report folder {folder} is not empty and holds no cva-bag-replay report '
            f'(no report.json; it has {listing}); pick another folder'
        )
    if not overwrite:
        raise ConfigError(
            f'the report folder {folder} holds an earlier report ({listing}); use --overwrite '
            f'to replace it, or pick another folder'
        )


def clear_report(folder: str | Path, keep: Collection[str] = ()) -> list[Path]:
    """Delete the files of an earlier report in ``folder`` (see :func:`report_files`);
    anything else in it stays. Returns the deleted paths.

    Args:
        folder: The report folder.
        keep: Names not to delete (e.g. ``node.log`` a live run has just begun).

    Raises:
        ConfigError: A file cannot be deleted.
    """
    removed = []
    for path in report_files(folder):
        if path.name in keep:
            continue
        try:
            path.unlink()
        except OSError as err:
            raise ConfigError(
                f'cannot remove {path.name} of the earlier report in {folder}: {reason(err)}'
            ) from None
        removed.append(path)
    return removed


@dataclass
class FrameScore:
    """One frame of the report; metric fields are None when the frame has no ground truth.

    Attributes:
        frame: Index of the stereo pair in the input bag (0-based, in stamp order).
        stamp_ns: Header stamp of the left image (ns).
        error_rate: Fraction of wrong disparities among the scored pixels.
        auc: Area under the ROC curve; lower = better.
        auc_opt: Optimal AUC for ``error_rate``.
        kept_density: Fraction of the scored pixels kept by the confidence threshold.
        kept_error_rate: Error rate among the kept pixels; None if none is kept.
        expected_kept_error: The error rate a probabilistic confidence predicts for the same
            pixels, mean(1 − confidence); None for other methods or if none is kept.
        kept_epe: Mean |d − d_gt| of the kept pixels, in pixels; None if none is kept.
        kept_fraction: Share of the pixels of the region of interest kept (all pixels without
            one; with or without ground truth).
        predicted_kept_error: mean(1 − confidence) over all kept pixels for a probabilistic
            method (the networks), the error rate it predicts without ground truth; None for
            other methods or if none is kept.
        mean_confidence: Mean confidence of the pixels with a finite disparity (None if none).
        scan_beams: With ``--scan`` and ground truth: beams of the ground truth's scan (of its
            known pixels) with a return in range, the beams scored (``scan.score_scan``).
        scan_phantom_rate: Share of them where the scan of the kept pixels with ground truth
            is wrong and nearer (a phantom obstacle). scan_far_rate: wrong and farther.
            scan_none_rate: no return (nothing kept in the beam).
        n_pixels: Number of scored pixels (0 without ground truth).
        width: Processed width. height: Processed height.
        processing_ms: Pipeline time (offline) for this frame.
        latency_ms: Live mode: wall time from publishing the pair to receiving the output.
        note: Why a frame has no metrics, if it has none.
        density: (K,) ROC densities (not written to JSON/CSV). roc_error: (K,) ROC errors.
    """

    frame: int
    stamp_ns: int
    error_rate: float | None = None
    auc: float | None = None
    auc_opt: float | None = None
    kept_density: float | None = None
    kept_error_rate: float | None = None
    expected_kept_error: float | None = None
    kept_epe: float | None = None
    kept_fraction: float | None = None
    predicted_kept_error: float | None = None
    mean_confidence: float | None = None
    scan_beams: int | None = None
    scan_phantom_rate: float | None = None
    scan_far_rate: float | None = None
    scan_none_rate: float | None = None
    n_pixels: int = 0
    width: int = 0
    height: int = 0
    processing_ms: float | None = None
    latency_ms: float | None = None
    note: str = ''
    density: np.ndarray | None = field(default=None, repr=False)
    roc_error: np.ndarray | None = field(default=None, repr=False)

    def as_dict(self) -> dict[str, Any]:
        """The JSON record: :data:`REPORT_KEYS` first, then the extras; NaN → None."""
        values = asdict(self)
        keys = (*REPORT_KEYS, *_EXTRA_KEYS)
        return {key: strict_json.json_ready(values[key]) for key in keys}


def score_frame(
    frame: int,
    stamp_ns: int,
    disparity: np.ndarray,
    confidence: np.ndarray,
    kept: np.ndarray,
    gt: np.ndarray | None,
    *,
    max_pixels: int | None = None,
    seed: int = 0,
    probabilistic: bool = False,
    region: np.ndarray | None = None,
) -> FrameScore:
    """Score one processed frame against its ground truth.

    Args:
        frame: Frame index. stamp_ns: Its stamp.
        disparity: (h, w) float32 disparity at the processed resolution, NaN = invalid.
        confidence: (h, w) float32 confidence, higher = more confident.
        kept: (h, w) bool, True where the node keeps the pixel (finite filtered disparity).
        gt: (h, w) float32 ground truth at the processed resolution (NaN unknown), or None.
        max_pixels: Score a fixed random subset of this many ground-truth pixels.
        seed: Seed of the subset (same pixels as ``cva-evaluate --max-pixels N --seed S``).
        probabilistic: ``confidence`` is a probability of a correct disparity in [0, 1] (the
            networks): also report ``expected_kept_error``.
        region: (h, w) bool, the pixels the node judges (its region of interest ``roi_top``
            to ``roi_bottom`` and its ignore mask, ``PipelineResult.region``):
            ``kept_fraction`` is the share of them, as in ``/diagnostics``, and the
            ground-truth metrics take the pixels with ground truth among them; None = the
            whole image.

    Returns:
        The :class:`FrameScore`: :data:`FRAME_KEYS` always, the ground-truth metrics None
        when ``gt`` is None or has no known pixel.

    Raises:
        InputError: A disparity that is no 2-D map of numbers, shapes that differ, a
            confidence that is no real number (bool, complex, ...), ``kept`` or ``region``
            not bool, or (from ``evaluation.score_confidence``) a NaN confidence at a scored
            pixel.
    """
    from cva_confidence_ros.evaluation import score_confidence, select_pixels
    from cva_confidence_ros.metrics import kitti_error

    disparity = np.asarray(disparity)
    if disparity.ndim != 2 or disparity.dtype.kind not in 'fiu':
        # Unpacked below as (h, w): a (h, w, 1) map was a bare ValueError, a list an
        # AttributeError, neither caught by the replay as a frame it cannot score.
        raise InputError(
            f'disparity must be an (h, w) map of numbers; got shape {disparity.shape} '
            f'and dtype {disparity.dtype}'
        )
    height, width = disparity.shape
    score = FrameScore(frame=frame, stamp_ns=stamp_ns, width=width, height=height)
    arrays = (('confidence', confidence), ('kept', kept)) + (
        (('ground truth', gt),) if gt is not None else ()
    )
    if region is not None:
        arrays += (('region', region),)
    for name, array in arrays:
        if np.shape(array) != disparity.shape:
            raise InputError(
                f'{name} must have the disparity shape {disparity.shape}; got {np.shape(array)}'
            )
    confidence = np.asarray(confidence)
    if confidence.dtype.kind not in 'fiu':
        # Cast to float32, a bool map was read as 0 / 1, which score_confidence refuses.
        raise InputError(
            f'confidence must hold real numbers (float or int); got dtype {confidence.dtype}'
        )
    for name, mask in (('kept', kept), ('region', region)):
        if mask is not None and np.asarray(mask).dtype != np.bool_:
            # Cast to bool, a disparity map given in its place counted NaN and nonzero as True.
            raise InputError(
                f'{name} must be an (h, w) bool mask; got dtype {np.asarray(mask).dtype}'
            )
    _frame_statistics(score, disparity, confidence, kept, probabilistic, region)
    if gt is None:
        score.note = 'no ground truth'
        return score
    known = np.isfinite(gt)
    if region is not None:
        # Not the pixels the user told the node not to judge (its bumper, a hood, rows outside
        # the region of interest): they were all scored as errors of confidence 0, and a mask
        # of 30 % made a matcher 25 % wrong (0.29 → 25.00 %) and the AUC ×10² 0.01 → 3.41.
        known &= np.asarray(region, dtype=bool)
    ys, xs = select_pixels(known, max_pixels, seed)
    if ys.size == 0:
        score.note = (
            'ground truth has no known pixel'
            if region is None or not np.isfinite(gt).any()
            else 'ground truth has no known pixel among those judged (region of interest, mask)'
        )
        return score
    error = np.asarray(kitti_error(disparity, gt), dtype=bool)[ys, xs]
    # Ranked in its own dtype, as cva-evaluate ranks it: a cast to float32 tied float64
    # values that differ only beyond its 7 digits.
    scored = score_confidence(confidence[ys, xs], error)
    kept_here = np.asarray(kept, dtype=bool)[ys, xs]
    score.error_rate = scored.error_rate
    score.auc = scored.auc
    score.auc_opt = scored.auc_opt
    score.n_pixels = scored.n_pixels
    score.kept_density = float(kept_here.mean())
    score.kept_error_rate = float(error[kept_here].mean()) if kept_here.any() else None
    if kept_here.any():
        deviation = np.abs(np.asarray(disparity, np.float64)[ys, xs] - gt[ys, xs])[kept_here]
        score.kept_epe = float(deviation.mean())
    if probabilistic:
        from cva_confidence_ros.calibration import expected_error

        values = np.clip(np.asarray(confidence, dtype=np.float32)[ys, xs], 0.0, 1.0)
        score.expected_kept_error = expected_error(values, kept_here)
    score.density = scored.density
    score.roc_error = scored.roc_error
    return score


def _frame_statistics(
    score: FrameScore,
    disparity: np.ndarray,
    confidence: np.ndarray,
    kept: np.ndarray,
    probabilistic: bool,
    region: np.ndarray | None,
) -> None:
    """Fill the :data:`FRAME_KEYS` of ``score`` (all pixels the node judges, no ground truth
    needed)."""
    kept = np.asarray(kept, dtype=bool)
    values = np.asarray(confidence, dtype=np.float32)
    judged = kept if region is None else kept[np.asarray(region, dtype=bool)]
    score.kept_fraction = float(judged.mean()) if judged.size else None
    matched = np.isfinite(disparity) & np.isfinite(values)
    if matched.any():
        score.mean_confidence = float(values[matched].mean(dtype=np.float64))
    if probabilistic:
        from cva_confidence_ros.calibration import expected_error

        score.predicted_kept_error = expected_error(np.clip(values, 0.0, 1.0), kept)


@dataclass
class ReplayReport:
    """Everything ``report.json`` holds.

    Attributes:
        frames: Per-frame scores, sorted by frame index when written.
        config: Replay settings (bag, mode, pipeline options, topics).
        counts: Counters: ``total`` (left images in the bag), ``pairs`` (stereo pairs matched
            by stamp), ``processed``, ``skipped`` (pairs not processed: bad frames; offline
            ``pairs`` = ``processed`` + ``skipped``), ``unpaired`` (input messages that
            matched no pair), ``unreadable`` (messages that cannot be deserialised),
            ``dropped`` (live mode: pairs the node did not answer), ``gt_unmatched``
            (ground-truth messages that matched no processed frame: no stereo pair of their
            stamp was processed, i.e. their images are missing, unpaired, skipped or, live,
            not answered, or the ground truth is not stamped like its left image).
        interrupted: The run was stopped (Ctrl-C) before the end of the bag.
        error: The fault that ended the run early, if any.
        unpaired: The first :data:`MAX_LISTED_UNPAIRED` input messages that matched no pair:
            records with ``topic``, ``stamp_ns`` and ``reason`` (``no partner`` or
            ``duplicate stamp``).
        unpaired_by_topic: Input topic → number of its messages that matched no pair.
        gt_unmatched_stamps: Stamps (ns) of the first few ground-truth messages that matched
            no processed frame (``counts['gt_unmatched']`` counts them all).
    """

    frames: list[FrameScore] = field(default_factory=list)
    config: dict[str, Any] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)
    interrupted: bool = False
    error: str = ''
    unpaired: list[dict[str, Any]] = field(default_factory=list)
    unpaired_by_topic: dict[str, int] = field(default_factory=dict)
    gt_unmatched_stamps: list[int] = field(default_factory=list)

    def add_unpaired(self, topic: str, stamp_ns: int, why: str) -> None:
        """Record one input message that matched no pair."""
        self.unpaired_by_topic[topic] = self.unpaired_by_topic.get(topic, 0) + 1
        if len(self.unpaired) < MAX_LISTED_UNPAIRED:
            self.unpaired.append({'topic': topic, 'stamp_ns': int(stamp_ns), 'reason': why})

    def not_scored(self) -> dict[str, int]:
        """Why frames have no metrics: note → number of frames (most frequent first)."""
        notes = Counter(f.note or 'no metrics' for f in self.frames if f.auc is None)
        return dict(notes.most_common())

    def least_kept(self) -> FrameScore | None:
        """The frame in which the node kept the smallest share of pixels (the earliest of
        equal ones), or None if no frame has statistics."""
        frames = [f for f in self.frames if f.kept_fraction is not None]
        return min(frames, key=lambda f: (cast(float, f.kept_fraction), f.frame), default=None)

    def summary(self) -> dict[str, Any]:
        """Means of the metrics over the frames that have them, plus the counters."""
        out: dict[str, Any] = {}
        for key in (*METRIC_KEYS, 'expected_kept_error', 'kept_epe', *FRAME_KEYS):
            values = [getattr(f, key) for f in self.frames if getattr(f, key) is not None]
            out[key] = float(np.mean(values)) if values else None
        # The scan's rates pooled over the beams of every scored frame.
        scanned = [f for f in self.frames if f.scan_beams]
        beams = sum(cast(int, f.scan_beams) for f in scanned)
        out['scan_beams'] = beams if scanned else None
        for key in SCAN_KEYS[1:]:
            out[key] = (sum(cast(float, getattr(f, key)) * cast(int, f.scan_beams)
                            for f in scanned) / beams) if beams else None
        # The frames a person looks at first: where the node kept least, predicted worst
        # (the earliest of equal ones).
        least = self.least_kept()
        out['min_kept_fraction'] = least.kept_fraction if least is not None else None
        out['min_kept_fraction_frame'] = least.frame if least is not None else None
        predicted = [f for f in self.frames if f.predicted_kept_error is not None]
        worst = min(predicted, key=lambda f: (-cast(float, f.predicted_kept_error), f.frame),
                    default=None)
        out['max_predicted_kept_error'] = worst.predicted_kept_error if worst else None
        out['max_predicted_kept_error_frame'] = worst.frame if worst else None
        latencies = [f.latency_ms for f in self.frames if f.latency_ms is not None]
        timings = [f.processing_ms for f in self.frames if f.processing_ms is not None]
        out['mean_processing_ms'] = float(np.mean(timings)) if timings else None
        out['mean_latency_ms'] = float(np.mean(latencies)) if latencies else None
        out['frames'] = len(self.frames)
        out['frames_scored'] = sum(1 for f in self.frames if f.auc is not None)
        out['not_scored'] = self.not_scored()
        out.update({key: int(value) for key, value in self.counts.items()})
        out['unpaired_by_topic'] = dict(sorted(self.unpaired_by_topic.items()))
        out['gt_unmatched_stamps'] = [int(stamp) for stamp in self.gt_unmatched_stamps]
        out['interrupted'] = self.interrupted
        out['error'] = self.error or None
        return {key: strict_json.json_ready(value) for key, value in out.items()}

    def as_dict(self) -> dict[str, Any]:
        """The JSON document: ``config``, ``frames`` (records), ``summary``, ``unpaired``
        (the first unpaired input messages, see :attr:`unpaired`)."""
        frames = sorted(self.frames, key=lambda f: (f.frame, f.stamp_ns))
        return {
            'config': self.config,
            'frames': [f.as_dict() for f in frames],
            'summary': self.summary(),
            'unpaired': list(self.unpaired),
        }


def _probabilistic(method: str) -> bool:
    """Whether the confidence method ``method`` gives probabilities (False if unknown)."""
    from cva_confidence_ros.confidence import is_probabilistic

    try:
        return is_probabilistic(method)
    except ConfigError:
        return False


def _frame_axis(axes: Any, index: list[int]) -> None:
    """Whole frame numbers on the x axis; one frame in the middle of -1 … +1 (matplotlib
    spread a single point over ±0.05, ticked -0.04 … 0.04)."""
    from matplotlib.ticker import MaxNLocator

    axes.xaxis.set_major_locator(MaxNLocator(integer=True))
    if index[0] == index[-1]:
        axes.set_xlim(index[0] - 1, index[0] + 1)


def _fmt(value: Any, percent: bool = False, digits: int = 1) -> str:
    if value is None:
        return '–'
    if isinstance(value, float):
        return f'{100 * value:.2f}' if percent else f'{value:.{digits}f}'
    return str(value)


class ReportWriter:
    """Writes the report folder: ``report.json``, ``report.csv``, ``summary.md`` and PNGs.

    Per-frame PNGs (written as frames come, while their arrays exist) for at most
    ``max_plots`` frames spread evenly over the bag (every ⌈``expected_frames`` /
    ``max_plots``⌉-th frame: a long robot bag is seen from start to end, not only in its first
    seconds): ``confidence_<frame>.png`` (the map), ``overlay_<frame>.png`` (the node's
    ``confidence_overlay``: the kept pixels red → green over the scene) and, for a frame with
    ground truth, ``roc_<frame>.png``. At the end: ``least_kept_<frame>.png``, the overlay of
    the frame in which the node kept the smallest share of pixels (where it trusted the scene
    least), ``confidence_over_time.png`` and, with ground truth, ``auc_over_time.png``.

    Args:
        folder: Report folder (created, with its parents, if it does not exist).
        max_plots: Number of frames that get per-frame PNGs (0 = none; the end-of-run PNGs
            are written all the same).
        expected_frames: Stereo pairs the bag is expected to hold (0 = unknown: the first
            ``max_plots`` frames are plotted).
        run: What the run was, for the per-frame PNGs' titles (``census_bm + pkrn``; empty:
            the method passed to :meth:`frame_plots`).

    Raises:
        ConfigError: ``folder`` is an existing file, or cannot be created.
    """

    def __init__(
        self, folder: str | Path, max_plots: int = 10, expected_frames: int = 0, run: str = ''
    ) -> None:
        self.folder = Path(folder)
        self.run = run
        self.max_plots = max_plots
        self.stride = max(1, math.ceil(expected_frames / max_plots)) if max_plots > 0 else 1
        self._plotted = 0
        # (kept fraction, frame) → the overlay's inputs, of the frame kept least so far.
        self._least: tuple[tuple[float, int], tuple[np.ndarray, ...]] | None = None
        if self.folder.exists() and not self.folder.is_dir():
            raise ConfigError(f'the report folder {self.folder} is a file; expected a folder')
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise ConfigError(
                f'cannot create the report folder {self.folder}: {reason(err)}'
            ) from None

    def wants(self, frame: int) -> bool:
        """Whether frame ``frame`` gets per-frame PNGs (on the stride, budget left)."""
        return self._plotted < self.max_plots and frame % self.stride == 0

    def frame_plots(
        self,
        score: FrameScore,
        confidence: np.ndarray,
        label: str,
        kept: np.ndarray | None = None,
        image: Callable[[], np.ndarray | None] | None = None,
    ) -> list[Path]:
        """Write the PNGs of one frame that :meth:`wants` them, and remember the frame if the
        node kept less in it than in any before.

        Args:
            score: The frame's score (its ROC curve is drawn when it has one).
            confidence: (h, w) published confidence.
            label: Method name for the ROC legend.
            kept: (h, w) bool, the pixels the node keeps (for the overlays).
            image: Returns the left image at the output resolution (uint8), or None where it
                cannot be had; called only for a frame whose overlay is drawn or kept.

        Returns:
            The PNGs written now.

        Raises:
            ConfigError: A PNG cannot be written (a full disk), naming the frame and folder;
                no further frame gets PNGs.
        """
        left: np.ndarray | None = None
        if kept is not None and image is not None and score.kept_fraction is not None:
            key = (score.kept_fraction, score.frame)
            if self._least is None or key < self._least[0]:
                left = image()
                if left is not None:
                    self._least = (key, (left, confidence.copy(), kept.copy()))
        if not self.wants(score.frame):
            return []
        self._plotted += 1
        try:
            return self._draw_frame(score, confidence, label, kept, image, left)
        except OSError as err:
            # A full disk: no more PNGs (the report files may still fit), and the run stops
            # with the reason rather than a traceback.
            self.max_plots = self._plotted
            raise ConfigError(
                f'cannot write the PNGs of frame {score.frame} into the report folder '
                f'{self.folder}: {reason(err)}'
            ) from None

    def _draw_frame(
        self,
        score: FrameScore,
        confidence: np.ndarray,
        label: str,
        kept: np.ndarray | None,
        image: Callable[[], np.ndarray | None] | None,
        left: np.ndarray | None,
    ) -> list[Path]:
        """Write the PNGs of one frame (see :meth:`frame_plots`)."""
        from cva_confidence_ros.plots import (
            save_confidence_map,
            save_confidence_overlay,
            save_roc_curves,
        )

        finite = confidence[np.isfinite(confidence)]
        vmin = vmax = None
        if _probabilistic(label):
            # A probability is drawn on [0, 1] always, so that two frames' maps compare: by
            # percentiles, an easy frame (1st percentile above 0.25) was stretched, 0.5 black.
            vmin, vmax = 0.0, 1.0
        elif finite.size:
            low, high = (float(v) for v in np.percentile(finite, [1.0, 99.0]))
            # A map that uses most of [0, 1] (learned) is drawn on that fixed scale; one with a
            # long tail (hand-crafted ratios, even min–max scaled) is stretched, or it is black.
            vmin, vmax = (0.0, 1.0) if low <= 0.25 and high >= 0.75 else (low, high)
        paths = [
            save_confidence_map(
                confidence, self.folder / f'confidence_{score.frame:05d}.png', vmin, vmax
            )
        ]
        if kept is not None and image is not None:
            if left is None:
                left = image()
            if left is not None:
                paths.append(save_confidence_overlay(
                    left, confidence, kept, self.folder / f'overlay_{score.frame:05d}.png'
                ))
        if score.density is not None and score.roc_error is not None:
            paths.append(
                save_roc_curves(
                    {label: (score.density, score.roc_error)},
                    self.folder / f'roc_{score.frame:05d}.png',
                    error_rate=score.error_rate,
                    # The run and the stamp too (as cva-evaluate's roc.png names the matcher):
                    # two runs' roc_00003.png side by side were told apart by folder only.
                    # × 10² as in the tables: a bare "AUC 4.66" over axes of 0 to 1 misleads.
                    title=f'{self.run or label}, frame {score.frame}\nstamp '
                    f'{score.stamp_ns // 10**9}.{score.stamp_ns % 10**9:09d} s  '
                    f'AUC × 10² {100 * (score.auc or 0):.2f} '
                    f'(opt {100 * (score.auc_opt or 0):.2f})',
                )
            )
        return paths

    def write(self, report: ReplayReport) -> dict[str, Path]:
        """Write JSON, CSV, Markdown and the AUC-over-time plot; return their paths.

        Each file is written beside its place and renamed onto it: a file that cannot be
        written is left as an earlier run wrote it, or not there.

        Raises:
            ConfigError: A file cannot be written (a full disk), naming the file.
        """
        try:
            return self._write(report)
        except OSError as err:
            raise ConfigError(
                f'cannot write the report into {self.folder}: {reason(err)}'
            ) from None

    def _write(self, report: ReplayReport) -> dict[str, Path]:
        document = report.as_dict()
        paths = {
            'json': self.folder / 'report.json',
            'csv': self.folder / 'report.csv',
            'markdown': self.folder / 'summary.md',
        }
        # Each file to a temporary one beside it, renamed in place: written directly, a full
        # disk left a truncated report.csv or summary.md (an error naming only the folder).
        _write_file(paths['json'], strict_json.dumps(document, indent=2) + '\n')
        stream = io.StringIO()
        writer = csv.writer(stream)
        keys = (*REPORT_KEYS, *_EXTRA_KEYS)
        writer.writerow(keys)
        for record in document['frames']:
            writer.writerow(['' if record[k] is None else record[k] for k in keys])
        _write_file(paths['csv'], stream.getvalue())
        _write_file(paths['markdown'], format_summary(document))
        plot = self._auc_plot(report)
        if plot is not None:
            paths['auc_over_time'] = plot
        plot = self._confidence_plot(report)
        if plot is not None:
            paths['confidence_over_time'] = plot
        if self._least is not None:
            from cva_confidence_ros.plots import save_confidence_overlay

            (_, frame), (left, confidence, kept) = self._least
            least = self.folder / f'least_kept_{frame:05d}.png'
            try:
                paths['least_kept'] = save_confidence_overlay(left, confidence, kept, least)
            except OSError as err:
                raise _unwritable(least, err) from None
        return paths

    def _confidence_plot(self, report: ReplayReport) -> Path | None:
        """``confidence_over_time.png``: per frame the kept share, the predicted error of the
        kept pixels (networks) and, where there is ground truth, their measured error."""
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        frames = sorted(
            (f for f in report.frames if f.kept_fraction is not None), key=lambda f: f.frame
        )
        if not frames:
            return None
        figure = Figure(figsize=(7.0, 4.5), dpi=100)
        FigureCanvasAgg(figure)
        kept_axes, error_axes = figure.subplots(2, 1, sharex=True)
        index = [f.frame for f in frames]
        kept_axes.plot(index, [100 * cast(float, f.kept_fraction) for f in frames], 'o-',
                       markersize=3, label='kept pixels')
        kept_axes.set_ylim(0.0, 100.0)
        kept_axes.set_ylabel('kept %')
        least = report.least_kept()
        if least is not None:
            for axes in (kept_axes, error_axes):
                axes.axvline(least.frame, color='0.6', linewidth=0.8)
            # Written towards the middle: beside a line at the right end it ran off the
            # figure (and over the frame of the axes).
            first, last = index[0], index[-1]
            right = last > first and least.frame > (first + last) / 2
            kept_axes.annotate(f' least kept: frame {least.frame} ', (least.frame, 4.0),
                               fontsize=7, color='0.35', ha='right' if right else 'left')
        drawn = False
        for key, label, style in (
            ('predicted_kept_error', 'predicted by the confidence', 's--'),
            ('kept_error_rate', 'measured (pixels with ground truth)', 'x:'),
        ):
            points = [(f.frame, 100 * getattr(f, key)) for f in frames
                      if getattr(f, key) is not None]
            if points:
                xs, ys = zip(*points, strict=True)
                error_axes.plot(xs, ys, style, markersize=3, linewidth=1, label=label)
                drawn = True
        if drawn:
            error_axes.legend(fontsize=7)
        else:
            error_axes.text(0.5, 0.5, 'no prediction (not a probability) and no ground truth',
                            transform=error_axes.transAxes, ha='center', fontsize=8,
                            color='0.4')
        error_axes.set_ylim(bottom=0.0)
        error_axes.set_ylabel('error of the kept %')
        error_axes.set_xlabel('frame')
        _frame_axis(error_axes, index)
        for axes in (kept_axes, error_axes):
            axes.grid(True, alpha=0.3)
        kept_axes.set_title(f"{report.config.get('matcher', '')} + "
                            f"{report.config.get('confidence_method', '')}, threshold "
                            f"{report.config.get('confidence_threshold', '')}", fontsize=9)
        figure.tight_layout()
        return _write_file(self.folder / 'confidence_over_time.png', figure)

    def _auc_plot(self, report: ReplayReport) -> Path | None:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        frames = sorted((f for f in report.frames if f.auc is not None), key=lambda f: f.frame)
        if not frames:
            return None
        index = [f.frame for f in frames]
        figure = Figure(figsize=(6.0, 3.5), dpi=100)
        FigureCanvasAgg(figure)
        axes = figure.add_subplot(1, 1, 1)
        # Scored frames (auc set) have auc_opt and error_rate too: score_frame sets all three.
        aucs = [100 * cast(float, f.auc) for f in frames]
        auc_opts = [100 * cast(float, f.auc_opt) for f in frames]
        error_rates = [100 * cast(float, f.error_rate) for f in frames]
        # Every line with markers: a bag with one scored frame showed only the AUC's dot.
        axes.plot(index, aucs, 'o-', label='AUC', markersize=3)
        axes.plot(index, auc_opts, 'k+--', label='AUC opt', linewidth=1, markersize=5)
        axes.plot(index, error_rates, 'x:', label='error rate', linewidth=1, markersize=4)
        axes.set_xlabel('frame')
        _frame_axis(axes, index)
        axes.set_ylabel('× 100 (error rate: %)')
        axes.set_ylim(bottom=0.0)
        axes.set_title(f"{report.config.get('matcher', '')} + "
                       f"{report.config.get('confidence_method', '')}: AUC per frame",
                       fontsize=9)
        axes.grid(True, alpha=0.3)
        axes.legend(fontsize=8)
        figure.tight_layout()
        return _write_file(self.folder / 'auc_over_time.png', figure)


def _unwritable(path: Path, err: OSError) -> ConfigError:
    """The error of a report file that cannot be written, naming it (not only its folder)."""
    kept = '; the one there was left as it was' if path.is_file() else ''
    return ConfigError(f'cannot write the report file {path}: {reason(err)}{kept}')


def _write_file(path: Path, content: str | Figure) -> Path:
    """Write ``content`` (text, UTF-8; or a figure, as PNG) to ``path`` atomically.

    Raises:
        ConfigError: ``path`` cannot be written (:func:`_unwritable`).
    """

    def write(handle: BinaryIO) -> None:
        if isinstance(content, str):
            handle.write(content.encode('utf-8'))
        else:
            content.savefig(handle, format='png')

    try:
        write_atomic(path, write)
    except OSError as err:
        raise _unwritable(path, err) from None
    return path


def format_summary(document: dict[str, Any], max_rows: int = 200) -> str:
    """The ``summary.md`` text of a report document (see :meth:`ReplayReport.as_dict`)."""
    summary = document['summary']
    config = document['config']
    lines = ['# Bag replay report', '']
    for key in ('bag', 'mode', 'matcher', 'confidence_method', 'max_disparity', 'downsample',
                'confidence_threshold', 'subpixel', 'speckle_size', 'speckle_range', 'roi_top',
                'roi_bottom', 'mask_path', 'gt_topic',
                'max_pixels'):
        if key in config:
            lines.append(f'- {key}: {config[key]}')
    lines += [
        '',
        '| frames | scored | skipped | dropped | error rate % | AUC ×100 | AUC opt ×100 '
        '| kept density % | kept error % | expected kept error % | kept EPE px |',
        '|---|---|---|---|---|---|---|---|---|---|---|',
        f"| {summary['frames']} | {summary['frames_scored']} | {summary.get('skipped', 0)} "
        f"| {summary.get('dropped', 0)} | {_fmt(summary['error_rate'], True)} "
        f"| {_fmt(summary['auc'], True)} | {_fmt(summary['auc_opt'], True)} "
        f"| {_fmt(summary['kept_density'], True)} | {_fmt(summary['kept_error_rate'], True)} "
        f"| {_fmt(summary.get('expected_kept_error'), True)} "
        f"| {_fmt(summary.get('kept_epe'), digits=3)} |",
        '',
    ]
    if summary.get('scan_beams'):
        lines += [
            f"Laser scan (`--scan`) of the kept pixels with ground truth against the ground "
            f"truth's, {summary['scan_beams']} beams with a return: phantom (wrong, nearer) "
            f"{_fmt(summary['scan_phantom_rate'], True)} %, far (wrong, farther) "
            f"{_fmt(summary['scan_far_rate'], True)} %, none "
            f"{_fmt(summary['scan_none_rate'], True)} %.",
            '',
        ]
    if summary.get('kept_fraction') is not None:
        # What every frame tells without ground truth (a robot's own bag), on all pixels.
        least = (f"{_fmt(summary['min_kept_fraction'], True)} (frame "
                 f"{summary['min_kept_fraction_frame']})")
        worst = (f"{_fmt(summary['max_predicted_kept_error'], True)} (frame "
                 f"{summary['max_predicted_kept_error_frame']})"
                 if summary.get('max_predicted_kept_error') is not None else '–')
        lines += [
            'Every frame, all pixels, no ground truth needed (as `/diagnostics`):',
            '',
            '| kept % | least kept % | predicted error of the kept % | highest of a frame % | '
            'mean confidence |',
            '|---|---|---|---|---|',
            f"| {_fmt(summary['kept_fraction'], True)} | {least} "
            f"| {_fmt(summary.get('predicted_kept_error'), True)} | {worst} "
            f"| {_fmt(summary.get('mean_confidence'), digits=3)} |",
            '',
        ]
    if summary.get('unreadable'):
        lines += [f"Unreadable messages (cannot be deserialised, skipped): "
                  f"{summary['unreadable']}", '']
    if summary.get('interrupted'):
        text = '**Interrupted**: the report holds the frames done before the stop.'
        if summary.get('in_flight'):
            text += (f" {summary['in_flight']} frames published after the last one the node "
                     'answered were still on their way (not counted as dropped).')
        lines += [text, '']
    if summary.get('error'):
        lines += [f"**Stopped by an error**: {summary['error']}", '']
    if summary.get('gt_unmatched'):
        count = summary['gt_unmatched']
        stamps = summary.get('gt_unmatched_stamps') or []
        listed = ', '.join(str(stamp) for stamp in stamps)
        more = ', …' if count > len(stamps) else ''
        lines += [
            f'Ground-truth messages that matched no processed frame: {count}'
            + (f' (stamps {listed}{more} ns)' if stamps else '')
            + '. No stereo pair of their stamp was processed: their images are missing, '
            'unpaired or skipped (live: not answered), or the ground truth is not stamped '
            'like its left image.',
            '',
        ]
    not_scored = summary.get('not_scored') or {}
    if not_scored:
        lines += ['Frames without metrics:', '']
        lines += [f'- {count} × {note}' for note, count in not_scored.items()]
        lines.append('')
    by_topic = summary.get('unpaired_by_topic') or {}
    if by_topic:
        listed = document.get('unpaired', [])
        lines += [
            f"Unpaired input messages: {summary.get('unpaired', sum(by_topic.values()))} ("
            + ', '.join(f'{topic}: {count}' for topic, count in by_topic.items()) + ')',
            '',
            '| topic | stamp (ns) | reason |',
            '|---|---|---|',
        ]
        lines += [f"| {m['topic']} | {m['stamp_ns']} | {m['reason']} |" for m in listed]
        if sum(by_topic.values()) > len(listed):
            lines.append(f'\n({sum(by_topic.values()) - len(listed)} more not listed)')
        lines.append('')
    frames = document['frames']
    if frames:
        lines += [
            '| frame | stamp (ns) | error rate % | AUC ×100 | AUC opt ×100 | kept density % '
            '| kept error % | expected kept error % | kept EPE px | kept % (all) '
            '| predicted kept error % (all) | note |',
            '|---|---|---|---|---|---|---|---|---|---|---|---|',
        ]
        for record in frames[:max_rows]:
            lines.append(
                f"| {record['frame']} | {record['stamp_ns']} "
                f"| {_fmt(record['error_rate'], True)} | {_fmt(record['auc'], True)} "
                f"| {_fmt(record['auc_opt'], True)} | {_fmt(record['kept_density'], True)} "
                f"| {_fmt(record['kept_error_rate'], True)} "
                f"| {_fmt(record.get('expected_kept_error'), True)} "
                f"| {_fmt(record.get('kept_epe'), digits=3)} "
                f"| {_fmt(record.get('kept_fraction'), True)} "
                f"| {_fmt(record.get('predicted_kept_error'), True)} | {record['note']} |"
            )
        if len(frames) > max_rows:
            lines.append(f'\n({len(frames) - max_rows} more frames in report.csv)')
    return '\n'.join(lines) + '\n'

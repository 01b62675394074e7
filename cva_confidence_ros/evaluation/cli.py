"""``cva-evaluate``: score confidence methods on stereo data sets with ground truth.

For every scene of the chosen data sets, every matcher and every confidence method, computes
the error rate, the AUC of the ROC curve and the optimal AUC (Mehltretter & Heipke 2019,
Sec. 4.1), then writes

* ``--json PATH``: a list of records with keys ``dataset``, ``scene``, ``matcher``, ``method``,
  ``auc``, ``auc_opt``, ``error_rate``, ``n_pixels``;
* a Markdown table in the layout of the paper's Table 1 (AUC × 10², mean over scenes, best
  method per row in bold) to stdout and, with ``--out DIR``, to ``DIR/table.md``;
* with ``--out DIR``: PNGs under ``DIR/<dataset>/<scene>/<matcher>/``: ``disparity.png``;
  per method ``confidence_<method>.png`` (black = low, white = high: [0, 1] for a
  probability, else the map's 1st–99th percentile; the values, and τ, are in the PNG's
  text chunks ``vmin``, ``vmax``, ``Description``) and ``correct_<method>.png``;
  ``roc.png`` (all methods and the optimal curve); for the networks, whose confidence is
  meant as a probability, ``reliability.png`` there and, over the scenes,
  ``DIR/calibration.md``, ``DIR/calibration.json`` and ``DIR/reliability_<dataset>_<matcher>.png``
  (:mod:`cva_confidence_ros.evaluation.reliability`).

The correctness overlay follows the paper's Fig. 4: a scored pixel is green if its disparity is
correct and its confidence > τ, or wrong and confidence ≤ τ; red otherwise. τ = 0.5 for
confidences in [0, 1]; for hand-crafted measures on other scales τ is the ε-quantile of their
values (as many "confident" pixels as correct ones). With ``--max-pixels`` only the sampled
pixels are coloured, and CVA-Net's confidence map (computed only there) shows its values at
those pixels, the rest in ``plots.UNKNOWN_RGB``; the hand-crafted maps stay dense.

Progress goes to stderr: per scene ``[i/N]``, the time so far and an estimate of the time
left. ``--json`` is rewritten (atomically) after every scene, so a run that ends early (Ctrl-C,
SIGTERM, a kill or a crash) keeps the scenes done; ``--resume`` continues it (see
:func:`run`). A scene whose data cannot be used is reported and left out (of every method
alike); the others go on, and the run ends with exit code 2. So does a run that left out a
scene with ground truth but a file missing (a right image; named on stderr and in the table's
**Partial** line), unless ``--allow-missing-files`` is given. Bad input (unknown names, empty
data root, weights for another matcher or depth) ends with a one-line message and exit code 2;
Ctrl-C with 130, SIGTERM with 143, after writing what was done.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
import math
import os
from pathlib import Path
import sys
import time
from typing import Any, cast

from cva_confidence_ros.errors import (
    ConfigError,
    CVAError,
    DataError,
    InputError,
    closed_stdout,
    from_interrupt,
    interrupted_exit,
    sigterm_as_interrupt,
    stdout_closed,
)
from cva_confidence_ros.outputs import check_output_dir, check_output_file, write_text_atomic

__all__ = [
    'SceneRun',
    'exit_code',
    'main',
    'parse_dataset_names',
    'parse_splits',
    'parse_weights',
    'run_scenes',
]

PROG = 'cva-evaluate'


def _split_names(text: str, what: str) -> list[str]:
    names = [item.strip() for item in text.split(',') if item.strip()]
    if not names:
        raise ConfigError(f'expected a comma-separated list of {what}; got {text!r}')
    return list(dict.fromkeys(names))


def parse_dataset_names(text: str) -> list[str]:
    """Expand ``--dataset``: comma-separated names; ``develop`` = ``DEVELOP_DATASETS``.

    Raises:
        ConfigError: An unknown data set name.
    """
    from cva_confidence_ros.datasets import DATASETS, DEVELOP_DATASETS

    names: list[str] = []
    for name in _split_names(text, 'data sets'):
        expanded = list(DEVELOP_DATASETS) if name == 'develop' else [name]
        for item in expanded:
            if item not in DATASETS:
                raise ConfigError(
                    f'unknown data set {item!r}; expected one of {DATASETS.names()} or develop'
                )
            names.append(item)
    return list(dict.fromkeys(names))


def parse_splits(text: str | None, datasets: Sequence[str]) -> dict[str, str | None]:
    """Map each data set to its split from ``--split``.

    Args:
        text: None (each data set's default), ``SPLIT`` (every given data set that has that
            split; the others keep their default, so ``--dataset develop --split trainingH``
            reads Middlebury v3 at half size and KITTI 2015 as always), or
            ``NAME=SPLIT[,NAME=SPLIT...]`` (those data sets only).
        datasets: The data sets being evaluated.

    Returns:
        Data set → split, None where its default applies.

    Raises:
        ConfigError: A bare split that none of the data sets has, a ``NAME=SPLIT`` pair naming
            a data set that is not evaluated, one it does not have, or a pair without a split.
    """
    from cva_confidence_ros.datasets import DATASETS

    chosen: dict[str, str | None] = {name: None for name in datasets}
    if text is None:
        return chosen
    splits = {name: DATASETS.get(name).splits for name in datasets}
    items = [item.strip() for item in text.split(',') if item.strip()]
    if not items:
        raise ConfigError(f'--split names no split; got {text!r}')
    if len(items) == 1 and '=' not in items[0]:
        split = items[0]
        having = [name for name in datasets if split in splits[name]]
        if len(datasets) == 1:
            DATASETS.get(datasets[0]).resolve_split(split)  # its own error, naming its splits
        elif not having:
            held = ', '.join(f'{name}: {list(splits[name]) or "none"}' for name in datasets)
            raise ConfigError(f'--split {split!r}: no data set evaluated has it ({held})')
        chosen.update({name: split for name in having})
        return chosen
    for item in items:
        name, sep, split = (part.strip() for part in item.partition('='))
        if not sep:
            raise ConfigError(
                f'--split: expected NAME=SPLIT pairs (or one SPLIT for every data set); '
                f'got {item!r} in {text!r}'
            )
        if name not in chosen:
            raise ConfigError(
                f'--split names data set {name!r}, which is not among --dataset {list(datasets)}'
            )
        if not split:
            raise ConfigError(f'--split pair {item!r} lacks a split after "="')
        chosen[name] = DATASETS.get(name).resolve_split(split)
    return chosen


def parse_weights(text: str | None, matchers: Sequence[str]) -> dict[str, str | None]:
    """Map each matcher to its weights file from ``--weights``.

    Args:
        text: ``PATH`` (for every matcher), ``matcher=PATH[,matcher=PATH...]``, or None. A
            PATH may hold ``=`` (``runs/lr=1e-3/w.pt``): an existing file, or text whose part
            before the first ``=`` is a folder path, is one PATH.
        matchers: The matchers being evaluated.

    Returns:
        Matcher → path, None where the shipped default weights are to be used.

    Raises:
        ConfigError: A ``matcher=PATH`` pair names an unknown or unevaluated matcher.
    """
    if not text:
        return {m: None for m in matchers}
    items = [item.strip() for item in text.split(',') if item.strip()]

    def pair(item: str) -> bool:
        name = item.partition('=')[0]
        return '=' in item and '/' not in name and os.sep not in name

    if Path(text).is_file() or not all(pair(item) for item in items):
        return {m: text for m in matchers}
    chosen: dict[str, str | None] = {m: None for m in matchers}
    for item in items:
        name, _, path = item.partition('=')
        name = name.strip()
        if name not in chosen:
            raise ConfigError(
                f'--weights names matcher {name!r}, which is not among --matchers {list(matchers)}'
            )
        if not path.strip():
            raise ConfigError(f'--weights pair {item!r} lacks a path after "="')
        chosen[name] = path.strip()
    return chosen


def _build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=PROG,
        description='Score stereo confidence methods (CVA-Net and hand-crafted measures) on '
        'data sets with ground truth: per-scene JSON, a Table-1 Markdown table, PNGs.',
        epilog='Exit codes: 0 done, 2 bad input or an output that cannot be written (one line '
        'on stderr), or a partial run (scenes that could not be used; scenes left out for a '
        'missing file, unless --allow-missing-files: the records and table of the others are '
        'written), 130 stopped by Ctrl-C, 143 by SIGTERM (the scenes done are '
        'written; --resume goes on). The table goes to stdout, progress to stderr.',
    )
    parser.add_argument('--data-root', type=Path, default=None,
                        help='folder holding the data sets (not needed for motorcycle)')
    parser.add_argument('--dataset', required=True,
                        help='data set name(s), comma-separated, or "develop"; '
                        'stereo_folder reads your own pairs (<scene>/left.png, right.png, '
                        'disparity.pfm|npy|png)')
    parser.add_argument('--split', default=None,
                        help='data set split (default per data set, e.g. trainingQ): SPLIT '
                        'for every data set that has it, or NAME=SPLIT[,NAME=SPLIT...]')
    parser.add_argument('--matchers', required=True,
                        help='comma-separated matchers: census_bm,census_sgm,mccnn_fast')
    parser.add_argument('--methods', required=True,
                        help='comma-separated confidence methods, e.g. cva_net,pkrn,mlm')
    parser.add_argument('--weights', default=None,
                        help='CVA-Net weights: one PATH, or matcher=PATH pairs (comma-separated);'
                        ' default the shipped weights for each matcher and depth')
    parser.add_argument('--max-disparity', type=int, default=64,
                        help='cost-volume depth D (default 64, that of the shipped weights)')
    parser.add_argument('--max-pixels', type=int, default=None,
                        help='score a fixed random subset of N ground-truth pixels per scene; '
                        'CVA-Net then runs only there (patch mode)')
    parser.add_argument('--seed', type=int, default=0, help='seed of the pixel subset')
    parser.add_argument('--json', type=Path, required=True, help='output JSON file')
    parser.add_argument('--out', type=Path, default=None,
                        help='output folder for table.md and PNGs')
    parser.add_argument('--max-scenes', type=int, default=None,
                        help='evaluate at most this many scenes per data set')
    parser.add_argument('--downsample', type=int, default=1,
                        help='shrink every pair by this integer factor first (quick runs)')
    parser.add_argument('--device', default='cpu', choices=('cpu', 'cuda', 'auto'),
                        help='device of learned methods')
    parser.add_argument('--tile-budget-mb', type=float, default=512.0,
                        help='memory budget of one network tile')
    parser.add_argument('--allow-missing-files', action='store_true',
                        help='a scene with ground truth but a file missing (a right image) is '
                        'left out and the run marked partial (table.md, stderr) with exit '
                        'status 2; with this option the exit status is 0 all the same')
    parser.add_argument('--resume', action='store_true',
                        help='continue a run that ended early: take over the scenes whose '
                        'records --json already holds (written after every scene) and score '
                        'the rest; the first such scene is scored again and must agree (same '
                        'D, --max-pixels, --seed, --downsample, weights)')
    return parser


def _log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


@dataclass
class SceneRun:
    """What a loop over scenes got done (:func:`run_scenes`).

    Attributes:
        records: The records of every scene that finished, in order.
        failed: ``(scene label, reason)`` of each scene whose data could not be used.
        total: Scenes there were to do.
        done: Scenes that finished.
        interrupted: Ctrl-C ended the loop early.
        left_out: ``(scene label, 'no <file>')`` of each scene the loader left out for a
            missing file (``datasets.skipped_scenes``); not in :attr:`total`.
        allow_left_out: Such scenes still make the run partial (noted), but exit status 0
            (``--allow-missing-files``).
    """

    records: list[Any] = field(default_factory=list)
    failed: list[tuple[str, str]] = field(default_factory=list)
    total: int = 0
    done: int = 0
    interrupted: bool = False
    left_out: list[tuple[str, str]] = field(default_factory=list)
    allow_left_out: bool = False

    @property
    def partial(self) -> bool:
        """Whether some scenes are missing from :attr:`records`."""
        return self.done < self.total or bool(self.left_out)

    @property
    def wanted(self) -> int:
        """Scenes there were to score: :attr:`total` and those left out."""
        return self.total + len(self.left_out)

    def note(self) -> str:
        """One Markdown line on what is missing, for the written table ('' when complete)."""
        if not self.partial:
            return ''
        parts = []
        if self.interrupted:
            parts.append(f'interrupted after {self.done} of {self.total} scenes')
        if self.failed:
            parts.append('could not use ' + '; '.join(f'{s} ({r})' for s, r in self.failed))
        if self.left_out:
            parts.append('left out for a missing file '
                         + '; '.join(f'{s} ({r})' for s, r in self.left_out))
        return f'**Partial: {self.done} of {self.wanted} scenes** — ' + '; '.join(parts) + '.'

    def ending(self, prog: str, written: str) -> int:
        """Say on stderr what was left out and return the exit status (0, 2 or 130)."""
        for scene, reason in self.failed:
            print(f'{prog}: error: {scene}: {reason}', file=sys.stderr)
        if self.interrupted:
            print(f'{prog}: interrupted after {self.done} of {self.total} scenes; '
                  f'{written}', file=sys.stderr)
            return 130
        if self.failed:
            print(f'{prog}: error: {len(self.failed)} of {self.total} scenes could not be used; '
                  f'{written}', file=sys.stderr)
            return 2
        if self.left_out:
            # A data set with a file missing scored fewer scenes under exit status 0: a
            # script took the table for one of the whole data set.
            kind = 'warning' if self.allow_left_out else 'error'
            print(f'{prog}: {kind}: {len(self.left_out)} of {self.wanted} scenes left out for a '
                  f'missing file ({_describe_left_out(self.left_out)}); {written}'
                  + ('' if self.allow_left_out else
                     '; --allow-missing-files accepts that (exit status 0)'), file=sys.stderr)
            return 0 if self.allow_left_out else 2
        return 0


def _describe_left_out(left_out: Sequence[tuple[str, str]], limit: int = 3) -> str:
    shown = '; '.join(f'{scene}: {why}' for scene, why in left_out[:limit])
    return shown + (f' (and {len(left_out) - limit} more)' if len(left_out) > limit else '')


def _duration(seconds: float) -> str:
    seconds = round(seconds)
    return f'{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}'


def run_scenes(
    jobs: Sequence[Any],
    label: Callable[[Any], str],
    work: Callable[[int, Any], list[Any]],
    after: Callable[[SceneRun], None] | None = None,
    held: Callable[[Any], list[Any] | None] | None = None,
) -> SceneRun:
    """Run ``work(number, job)`` for each scene and keep what finished.

    A scene whose data cannot be used (:class:`DataError`, :class:`InputError`: an unreadable
    image, a ground truth that does not fit) is logged and skipped, and the loop goes on; Ctrl-C
    (and SIGTERM, under :func:`exit_code`) ends it after the records so far. Either way the
    caller writes what finished, so an hour of evaluation is not lost to one bad file or a late
    Ctrl-C. Option faults (:class:`ConfigError`, :class:`ModelError`) end the run as before:
    they would fail every scene alike. After each scene a line gives the time so far and an
    estimate of the time left (from the scenes computed in this loop).

    Args:
        jobs: The scenes, in order.
        label: A scene's name for the log.
        work: Computes the records of scene ``job``, the ``number``-th.
        after: Called with the result so far after each scene that finished (to write the
            records as they come: a SIGKILL or a crash then loses one scene, not the run).
        held: Records of a scene already scored (``--resume``) or None; such a scene is taken
            over without calling ``work``.

    Returns:
        The records and what was left out.
    """
    result = SceneRun(total=len(jobs))
    started = time.perf_counter()
    computed, spent = 0, 0.0
    for number, job in enumerate(jobs, start=1):
        taken = held(job) if held is not None else None
        if taken is not None:
            _log(f'[{number}/{len(jobs)}] {label(job)} taken over from the earlier run')
            result.records.extend(taken)
            result.done += 1
            if after is not None:
                after(result)
            continue
        tic = time.perf_counter()
        try:
            records = work(number, job)
        except (DataError, InputError) as error:
            _log(f'[{number}/{len(jobs)}] {label(job)} skipped: {error}')
            result.failed.append((label(job), str(error)))
            continue
        except (KeyboardInterrupt, SystemError) as exc:
            if not from_interrupt(exc):
                raise
            _log(f'[{number}/{len(jobs)}] {label(job)} interrupted; writing the '
                 f'{result.done} scene(s) done')
            result.interrupted = True
            break
        result.records.extend(records)
        result.done += 1
        computed += 1
        spent += time.perf_counter() - tic
        left = spent / computed * (len(jobs) - number)
        _log(f'[{number}/{len(jobs)}] {label(job)} done; '
             f'{_duration(time.perf_counter() - started)} so far, about {_duration(left)} left')
        if after is not None:
            after(result)
    if not result.records and result.failed:
        scene, reason = result.failed[0]
        more = f' (and {len(result.failed) - 1} more)' if len(result.failed) > 1 else ''
        raise DataError(f'no scene could be evaluated; {scene}: {reason}{more}')
    return result


#: Text files written into ``--out`` besides the per-scene PNGs.
_OUT_TEXTS = ('table.md', 'calibration.md', 'calibration.json')


def _check_args(args: argparse.Namespace) -> None:
    if not 1 <= args.max_disparity <= 1024:
        raise ConfigError(f'--max-disparity must be in [1, 1024]; got {args.max_disparity}')
    if args.max_pixels is not None and args.max_pixels < 1:
        raise ConfigError(f'--max-pixels must be ≥ 1; got {args.max_pixels}')
    if args.max_scenes is not None and args.max_scenes < 1:
        raise ConfigError(f'--max-scenes must be ≥ 1; got {args.max_scenes}')
    if args.downsample < 1:
        raise ConfigError(f'--downsample must be ≥ 1; got {args.downsample}')
    if not (math.isfinite(args.tile_budget_mb) and args.tile_budget_mb > 0):
        raise ConfigError(f'--tile-budget-mb must be finite and > 0; got {args.tile_budget_mb}')
    if args.seed < 0:
        raise ConfigError(f'--seed must be ≥ 0; got {args.seed}')
    check_output_file(args.json, '--json')
    if args.out is not None:
        check_output_dir(args.out, '--out')
        # The records were written first, then silently overwritten by the table.
        for name in _OUT_TEXTS:
            if args.json.resolve() == (args.out / name).resolve():
                raise ConfigError(
                    f'--json {args.json} is the {name} that --out {args.out} writes; '
                    'expected another file'
                )


def _build_methods(
    args: argparse.Namespace, matchers: Sequence[str], methods: Sequence[str]
) -> dict[str, dict[str, Any]]:
    """Matcher → method name → confidence method; loads (and checks) every weights file once."""
    from cva_confidence_ros.confidence import CONFIDENCE_METHODS

    weights = parse_weights(args.weights, matchers)
    built: dict[str, dict[str, Any]] = {}
    for matcher in matchers:
        built[matcher] = {}
        for name in methods:
            factory = CONFIDENCE_METHODS.get(name)
            built[matcher][name] = factory(
                matcher=matcher,
                max_disparity=args.max_disparity,
                weights=weights[matcher],
                device=args.device,
                tile_budget_mb=args.tile_budget_mb,
            )
    return built


def _scene_lists(
    datasets: Sequence[str],
    root: Path | None,
    splits: dict[str, str | None],
    max_scenes: int | None,
) -> tuple[list[tuple[str, str]], list[tuple[str, str]]]:
    """The (data set, scene) jobs, and ``('<data set>/<scene>', 'no <file>')`` of each scene
    the loader leaves out for a missing file among them (with ``max_scenes``: those sorted
    before the last scene taken, which the first ``max_scenes`` would have held)."""
    from cva_confidence_ros.datasets import list_scenes, skipped_notice, skipped_scenes

    jobs: list[tuple[str, str]] = []
    left_out: list[tuple[str, str]] = []
    for name in datasets:
        scenes = list(list_scenes(name, root, split=splits[name]))
        if not scenes:
            where = root if root is not None else '(no --data-root)'
            raise DataError(f'no stereo pairs of data set {name!r} found under {where}')
        # A partial download (a scene without its right image) ran on fewer scenes unsaid.
        if notice := skipped_notice(name, root, split=splits[name]):
            _log(notice)
        taken = scenes[:max_scenes]
        jobs.extend((name, scene) for scene in taken)
        # ... and was no partial run: exit status 0, a table with no mark.
        last = taken[-1] if max_scenes is not None and len(scenes) > max_scenes else None
        left_out.extend(
            (f'{name}/{scene}', why)
            for scene, why in skipped_scenes(name, root, split=splits[name])
            if last is None or scene < last
        )
    return jobs, left_out


#: How far a record of ``--resume``'s file may be from the same scene scored again: the
#: networks' AUC moves in the last digits between devices and thread counts; other settings
#: (D, pixels, seed, downsampling, weights) move it far more.
RESUME_TOLERANCE = 1e-5


def _previous_records(
    path: Path, jobs: Sequence[tuple[str, str]], matchers: Sequence[str], methods: Sequence[str]
) -> dict[tuple[str, str], list[Any]]:
    """(data set, scene) → the records ``path`` holds of it, for ``--resume``.

    Raises:
        DataError, InputError: As :func:`read_records`.
        ConfigError: A record of a scene, matcher or method this run does not score: it would
            be dropped from the file, or its scene left out of the table.
    """
    from cva_confidence_ros.evaluation.records import read_records

    if not path.exists():
        _log(f'--resume: no {path} yet; starting from the first scene')
        return {}
    wanted = set(jobs)
    held: dict[tuple[str, str], list[Any]] = {}
    for record in read_records(path):
        if ((record.dataset, record.scene) not in wanted or record.matcher not in matchers
                or record.method not in methods):
            raise ConfigError(
                f'--resume: {path} holds a record of {record.dataset}/{record.scene} '
                f'{record.matcher} {record.method}, which this run does not score; resume with '
                'the data sets, --max-scenes, --matchers and --methods of the earlier run, or '
                'write to another --json'
            )
        held.setdefault((record.dataset, record.scene), []).append(record)
    return held


def _check_resumed(path: Path, old: Sequence[Any], new: Sequence[Any]) -> None:
    """Refuse the ``--resume`` file when a scene scored again disagrees with its records.

    Raises:
        ConfigError: The message names the record and both values.
    """
    fresh = {(r.matcher, r.method): r for r in new}
    for r in old:
        now = fresh.get((r.matcher, r.method))
        if now is None:
            continue
        same = (now.n_pixels == r.n_pixels
                and abs(now.error_rate - r.error_rate) <= 1e-9
                and abs(now.auc - r.auc) <= RESUME_TOLERANCE)
        if not same:
            raise ConfigError(
                f'--resume: {path} was written with other settings or data: '
                f'{r.dataset}/{r.scene} {r.matcher} {r.method} has auc {r.auc}, error_rate '
                f'{r.error_rate}, n_pixels {r.n_pixels} there and auc {now.auc}, error_rate '
                f'{now.error_rate}, n_pixels {now.n_pixels} now; use the same D, --max-pixels, '
                '--seed, --downsample and --weights, or write to another --json'
            )


def run(args: argparse.Namespace) -> int:
    """Run the evaluation for parsed arguments; raises ``CVAError`` on bad input.

    ``--json`` is rewritten after every scene: the records of the scenes done, in scene order.
    With ``--resume`` the records it already holds are read first (every one must belong to
    this run's scenes, matchers and methods); a scene held for every matcher and method is
    taken over without being loaded, the others are scored. The first held scene is scored
    again all the same and must agree (``n_pixels`` and ``error_rate`` exactly, ``auc`` within
    :data:`RESUME_TOLERANCE`): a file of another D, pixel subset, seed, downsampling or weights
    is refused, and nothing is written before. The finished file is the one a run without
    interruption writes. Calibration outputs need every scene scored in one run: they are not
    written when scenes were taken over.
    """
    from cva_confidence_ros.calibration import add_table
    from cva_confidence_ros.confidence import CONFIDENCE_METHODS
    from cva_confidence_ros.datasets import load_scene, resize_sample
    from cva_confidence_ros.evaluation.records import format_table, write_records
    from cva_confidence_ros.evaluation.scene import evaluate_scene
    from cva_confidence_ros.matching import MATCHERS

    _check_args(args)
    datasets = parse_dataset_names(args.dataset)
    splits = parse_splits(args.split, datasets)
    matchers = _split_names(args.matchers, 'matchers')
    for matcher in matchers:
        MATCHERS.get(matcher)
    methods = _split_names(args.methods, 'confidence methods')
    # Every name before any weights are loaded: a bad name after cva_net was reported as
    # cva_net's missing weights.
    for method in methods:
        CONFIDENCE_METHODS.get(method)
    built = _build_methods(args, matchers, methods)
    jobs, left_out = _scene_lists(datasets, args.data_root, splits, args.max_scenes)
    calibration: dict[tuple[str, str, str], Any] = {}
    previous = _previous_records(args.json, jobs, matchers, methods) if args.resume else {}
    whole = len(matchers) * len(methods)
    # Until a scene of the file has been scored again and agreed with it, its scenes are
    # scored, not taken over, and nothing is written: the file of a run with other settings
    # is refused as it was.
    unchecked = bool(previous)
    taken: list[tuple[str, str]] = []
    # A scene's records in the order a run scores them: matcher by matcher, method by method.
    order = {pair: index for index, pair in enumerate(
        (matcher, method) for matcher in matchers for method in methods)}

    def held(job: tuple[str, str]) -> list[Any] | None:
        old = previous.get(job, [])
        if unchecked or len(old) != whole:
            return None
        taken.append(job)
        return sorted(old, key=lambda r: order[(r.matcher, r.method)])  # as if scored now

    def merged(outcome: SceneRun) -> list[Any]:
        """This run's records and, for scenes it has not (yet) done, those of the file."""
        done: dict[tuple[str, str], list[Any]] = {}
        for record in outcome.records:
            done.setdefault((record.dataset, record.scene), []).append(record)
        return [r for job in jobs for r in done.get(job, previous.get(job, []))]

    def work(index: int, job: tuple[str, str]) -> list[Any]:
        nonlocal unchecked
        dataset, scene = job
        prefix = f'[{index}/{len(jobs)}] {dataset}/{scene}'
        tic = time.perf_counter()
        sample = load_scene(dataset, args.data_root, scene, split=splits[dataset])
        if args.downsample > 1:
            sample = resize_sample(sample, args.downsample)
        _log(f'{prefix} loaded {sample.left.shape[1]}x{sample.left.shape[0]} '
             f'{time.perf_counter() - tic:.2f} s')
        records: list[Any] = []
        tables: dict[tuple[str, str, str], Any] = {}
        for matcher in matchers:
            plot_dir = None
            if args.out is not None:
                plot_dir = args.out / dataset / scene / matcher
            records.extend(
                evaluate_scene(
                    sample,
                    matcher,
                    built[matcher],
                    max_disparity=args.max_disparity,
                    max_pixels=args.max_pixels,
                    seed=args.seed,
                    plot_dir=plot_dir,
                    log=cast('Callable[[str], None]',
                             lambda message, p=prefix: _log(f'{p} {message}')),
                    method_order=methods,
                    progress=True,
                    reliability=tables,
                )
            )
        if previous.get(job):
            _check_resumed(args.json, previous[job], records)
            unchecked = False
        # Only a scene that finished counts, as for its records.
        for key, table in tables.items():
            add_table(calibration, key, table)
        return records

    # The file is rewritten (atomically) after every scene: a SIGKILL, an out-of-memory kill
    # or a crash loses the scene under way, not the run; --resume continues from it.
    def save(so_far: SceneRun) -> None:
        if not unchecked:
            write_records(merged(so_far), args.json)

    outcome = run_scenes(jobs, lambda job: f'{job[0]}/{job[1]}', work, after=save, held=held)
    outcome.left_out = left_out
    outcome.allow_left_out = args.allow_missing_files
    if not outcome.records:
        return outcome.ending(PROG, 'nothing written')
    records = outcome.records
    save(outcome)
    table = format_table(records, methods=methods)
    if outcome.partial:
        table += f'\n{outcome.note()}\n'
    if args.out is not None:
        write_text_atomic(args.out / 'table.md', table)
        if taken and calibration:
            # The scenes taken over left no reliability tables: a summary of the rest would
            # pass for one of every scene.
            _log(f'calibration not written: {len(taken)} scene(s) were taken over from '
                 f'{args.json}; run without --resume for it')
            _clear_calibration(args.out, [])
        else:
            _clear_calibration(args.out, _write_calibration(calibration, args.out))
    sys.stdout.write(table)
    sys.stdout.flush()
    if unchecked:
        _log(f'{args.json} left as it was: no scene of it could be scored again to check it')
    else:
        _log(f'wrote {len(merged(outcome))} records to {args.json}')
    return outcome.ending(PROG, f'the records of the {outcome.done} done are in {args.json}')


def _write_calibration(tables: dict[tuple[str, str, str], Any], out: Path) -> list[Path]:
    """Write the calibration files of ``tables`` (none without tables); the paths written."""
    from cva_confidence_ros.evaluation.reliability import ALL_DATASETS, pooled, write_calibration

    if not tables:
        return []
    written = write_calibration(tables, out)
    rows = pooled(tables)
    # One line per matcher and method: the rows over all data sets where there are several.
    summary = {k: t for k, t in rows.items() if k[0] == ALL_DATASETS} or rows
    for (dataset, matcher, method), table in summary.items():
        _log(f'calibration {dataset} {matcher} {method}: mean confidence '
             f'{100 * table.overall_confidence:.1f} %, correct '
             f'{100 * table.overall_accuracy:.1f} %, ECE {100 * table.ece:.2f} %')
    _log(f'wrote {out / "calibration.md"}, calibration.json and reliability PNGs')
    return written


def _clear_calibration(out: Path, written: Sequence[Path]) -> None:
    """Remove the calibration files of an earlier run in ``out`` that this run did not write:
    they sat beside a fresh table.md as if they summed up this run (a run of hand-crafted
    measures only, a --resume, a matcher fewer)."""
    keep = {path.resolve() for path in written}
    stale = [
        path
        for pattern in ('calibration.json', 'calibration.md', 'reliability_*.png')
        for path in sorted(out.glob(pattern))
        if path.is_file() and path.resolve() not in keep
    ]
    for path in stale:
        path.unlink(missing_ok=True)
    if stale:
        _log(f'removed {len(stale)} calibration file(s) of an earlier run in {out}: '
             f'{", ".join(path.name for path in stale)}')


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``cva-evaluate`` (and ``ros2 run cva_confidence_ros evaluate``).

    Returns:
        0 on success, 2 on bad input (after one line on stderr), when the records or
        ``table.md`` cannot be written (an older file there is kept) or the run is partial
        (scenes that could not be used; scenes left out for a missing file, unless
        ``--allow-missing-files``), 1 if another output file cannot be written.
    """
    args = _build_parser().parse_args(argv)
    return exit_code(PROG, lambda: run(args))


def exit_code(prog: str, command: Callable[[], int]) -> int:
    """Run ``command`` the way the evaluation tools end: its own code, or one line on stderr
    and 2 for bad input (:class:`CVAError`), 1 for an output that cannot be written, 141
    without a word for a closed stdout (:func:`closed_stdout`), 130 on
    Ctrl-C (also when it surfaced inside a numba kernel, see :func:`from_interrupt`). Large
    freed blocks are kept for the next scene first (:mod:`cva_confidence_ros.memory`)."""
    from cva_confidence_ros.memory import keep_freed_memory

    keep_freed_memory()
    with sigterm_as_interrupt() as terminated:
        try:
            code = command()
        except CVAError as exc:
            print(f'{prog}: error: {exc}', file=sys.stderr)
            return 2
        except BrokenPipeError as exc:
            if not stdout_closed():  # another pipe: an error as any other OSError
                print(f'{prog}: error: {exc}', file=sys.stderr)
                return 1
            # The table's reader went away (`| head -1`); the records were written before it.
            return closed_stdout()
        except OSError as exc:
            print(f'{prog}: error: {exc}', file=sys.stderr)
            return 1
        except (KeyboardInterrupt, SystemError) as exc:
            if not from_interrupt(exc):
                raise
            return interrupted_exit(prog, terminated)
        # 128 + 15, as a shell reports a process that SIGTERM ended.
        return 143 if terminated and code == 130 else code


if __name__ == '__main__':
    sys.exit(main())

"""``cva-table1``: the paper's Table 1 in one command (every learned and hand-crafted method,
every matcher, every test data set).

Rows: KITTI 2012, KITTI 2015, Middlebury v3 × Census-BM, Census-SGM, MC-CNN; columns: Opt.,
CCNN, LFN, LGC-Net, CVA-Net, then the hand-crafted measures PKRN, MLM, LRD, LRC, Score; each
cell the AUC × 10² averaged over the scenes of the data set (paper Sec. 4.1); the best
non-optimal value of each row in bold. Written to ``OUT/``: ``table1.md`` (with the paper's
own numbers beside it), ``table1.json`` (cells and per-scene records), ``table1.png``.

Protocols (``--protocol``; ``auto`` picks ``paper`` when the KITTI 2012 folder holds more than
``--kitti2012-train`` pairs):

* ``paper``: full KITTI / Middlebury downloads. Learned methods are trained on the first 20
  KITTI 2012 pairs; the KITTI 2012 row leaves out the paper's 23 training and validation pairs
  (the first 20 and the next 3) and scores the other 171, KITTI 2015 all 200, and Middlebury
  v3 the 15 ``trainingQ`` (quarter size) scenes.
* ``develop``: a data root with a train/develop split such as ``../shared/data``. Only the
  develop data sets are scored: KITTI 2015, Middlebury v3 (``middlebury2014`` trainingQ) and,
  as an extra row the paper does not have, Middlebury 2003. The KITTI 2012 row stays empty:
  every KITTI 2012 pair of such a root is training data. Learned methods use the shipped
  weights (trained on the training half of the split; see their model cards).

Weights: ``--weights-dir DIR/<arch>_<matcher>_d<D>.pt`` when present, else the shipped file;
a missing one is an error unless ``--train-missing``, which trains it into ``--weights-dir``
with ``cva-train``'s code and the shipped weights' recipe (``--train-scale`` shrinks the
samples per epoch, for quick runs) on the protocol's training data.

As everywhere, every scene is halved until its ground truth fits D, and ``--max-pixels`` scores
a fixed random subset of ground-truth pixels per scene (the same pixels for every method).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
from dataclasses import dataclass
import json
import math
from pathlib import Path
import sys
from typing import Any, cast

from cva_confidence_ros.errors import ConfigError, DataError, InputError, ModelError, reason
from cva_confidence_ros.outputs import check_output_dir, naming, write_atomic, write_text_atomic

__all__ = [
    'COLUMNS',
    'MATCHER_LABELS',
    'PAPER_TABLE1',
    'TableRow',
    'format_table1',
    'main',
    'table_rows',
]

PROG = 'cva-table1'

#: (method name, column title), in the paper's order, this project's CVA-Net-Lite and
#: CVA-Net-Fast, then the hand-crafted measures.
COLUMNS: tuple[tuple[str, str], ...] = (
    ('ccnn', 'CCNN'),
    ('lfn', 'LFN'),
    ('lgc_net', 'LGC-Net'),
    ('cva_net', 'CVA-Net'),
    ('cva_net_lite', 'CVA-Net-Lite'),
    ('cva_net_fast', 'CVA-Net-Fast'),
    ('pkrn', 'PKRN'),
    ('mlm', 'MLM'),
    ('lrd', 'LRD'),
    ('lrc', 'LRC'),
    ('score', 'Score'),
)
#: method → architecture of its weights.
LEARNED: dict[str, str] = {
    'ccnn': 'ccnn',
    'lfn': 'lfn',
    'lgc_net': 'lgcnet',
    'cva_net': 'cvanet',
    'cva_net_lite': 'cvanet_lite',
    'cva_net_fast': 'cvanet_fast',
}
MATCHER_LABELS: dict[str, str] = {
    'census_bm': 'Census-BM',
    'census_sgm': 'Census-SGM',
    'mccnn_fast': 'MC-CNN',
}
#: The paper's Table 1 (AUC × 10²): data set → matcher → (Opt., CCNN, LFN, LGC-Net, CVA-Net).
PAPER_TABLE1: dict[str, dict[str, tuple[float, float, float, float, float]]] = {
    'KITTI 2012': {
        'census_bm': (10.94, 12.37, 12.30, 11.97, 11.52),
        'census_sgm': (0.92, 2.41, 2.44, 2.31, 2.25),
        'mccnn_fast': (2.24, 2.89, 2.91, 2.71, 2.55),
    },
    'KITTI 2015': {
        'census_bm': (9.07, 10.59, 10.49, 10.18, 9.86),
        'census_sgm': (0.84, 2.36, 2.40, 2.39, 2.31),
        'mccnn_fast': (2.46, 3.35, 3.35, 3.19, 3.02),
    },
    'Middlebury v3': {
        'census_bm': (6.69, 9.01, 9.12, 8.36, 8.21),
        'census_sgm': (2.26, 5.58, 6.14, 5.33, 5.40),
        'mccnn_fast': (3.54, 5.22, 5.27, 4.91, 4.85),
    },
}
#: The training recipe per architecture for ``--train-missing`` on a CPU: that of the shipped
#: weights (see models/*.md), except CVA-Net, whose shipped weights used a GPU budget (13 M
#: samples, their cards) and which here keeps the budget of its first, CPU-trained weights.
RECIPES: dict[str, dict[str, Any]] = {
    # 16 crops of 8² per step: one 16² crop per step (the first shipped weights) learns far less.
    'cvanet': {'mode': 'dense', 'crop_size': 8, 'batch_size': 1024, 'epochs': 4,
               'epochs_low_lr': 1, 'lr': 1e-3, 'samples_per_epoch': 30_000},
    'cvanet_lite': {'mode': 'dense', 'crop_size': 8, 'batch_size': 1024, 'epochs': 3,
                    'epochs_low_lr': 1, 'lr': 1e-3, 'samples_per_epoch': 75_000},
    'cvanet_fast': {'mode': 'dense', 'crop_size': 8, 'batch_size': 1024, 'epochs': 3,
                    'epochs_low_lr': 1, 'lr': 1e-3, 'samples_per_epoch': 750_000},
    'ccnn': {'mode': 'dense', 'crop_size': 32, 'batch_size': 4096, 'epochs': 3,
             'epochs_low_lr': 1, 'lr': 1e-3, 'samples_per_epoch': 400_000},
    'lfn': {'mode': 'dense', 'crop_size': 32, 'batch_size': 4096, 'epochs': 3,
            'epochs_low_lr': 1, 'lr': 1e-3, 'samples_per_epoch': 400_000},
    # LGC-Net: 2 crops of 64² per step, as many steps as CCNN (2 crops of 80² and fewer steps
    # over-fitted).
    'lgcnet': {'mode': 'dense', 'crop_size': 64, 'batch_size': 8192, 'epochs': 3,
               'epochs_low_lr': 1, 'lr': 1e-3, 'samples_per_epoch': 800_000},
}
#: KITTI 2012 pairs after the ``--kitti2012-train`` training pairs that the paper protocol
#: leaves unscored: the paper (Sec. 4.2) excludes "the 23 images used for training and
#: validating", 20 + 3, and scores 171 of the 194. ``--train-missing`` validates on synthetic
#: pairs, not on these 3, but they stay out so that the row scores the paper's 171 pairs.
KITTI2012_VALIDATION = 3
DEVELOP_TRAIN = ('kitti2012', 'flyingthings3d', 'sceneflow_extra', 'tartanair', 'eth3d',
                 'middlebury2001', 'middlebury2006')


@dataclass(frozen=True)
class TableRow:
    """One data-set block of the table.

    Attributes:
        label: Row title (``KITTI 2012``, ...).
        dataset: Registered data set name.
        split: Data-set split (None = default).
        first: Index of the first scene scored (KITTI 2012 in the paper protocol: 23, after
            the paper's 20 training and 3 validation pairs).
        missing: Why the row is empty ('' = it is scored).
    """

    label: str
    dataset: str
    split: str | None = None
    first: int = 0
    missing: str = ''


def _scene_count(name: str, root: Path, split: str | None = None) -> int:
    from cva_confidence_ros.datasets import list_scenes

    try:
        return len(list_scenes(name, root, split))
    except (DataError, ConfigError):
        return 0


def resolve_protocol(protocol: str, root: Path, kitti2012_train: int) -> str:
    """``paper`` or ``develop`` (``auto``: paper when KITTI 2012 has more pairs than used for
    training and validation)."""
    if protocol != 'auto':
        return protocol
    held_out = kitti2012_train + KITTI2012_VALIDATION
    return 'paper' if _scene_count('kitti2012', root) > held_out else 'develop'


def table_rows(protocol: str, root: Path, kitti2012_train: int = 20) -> list[TableRow]:
    """The rows of ``protocol`` on ``root``, each scored or with the reason it is missing."""
    if protocol == 'paper':
        rows = [
            TableRow('KITTI 2012', 'kitti2012', first=kitti2012_train + KITTI2012_VALIDATION),
            TableRow('KITTI 2015', 'kitti2015'),
            TableRow('Middlebury v3', 'middlebury2014', 'trainingQ'),
        ]
    else:
        rows = [
            TableRow('KITTI 2012', 'kitti2012', missing=(
                'every KITTI 2012 pair of this data root belongs to the training split (the '
                'paper scores pairs 23–193 of the full download)')),
            TableRow('KITTI 2015', 'kitti2015'),
            TableRow('Middlebury v3', 'middlebury2014', 'trainingQ'),
            TableRow('Middlebury 2003 (extra)', 'middlebury2003'),
        ]
    checked = []
    for row in rows:
        if not row.missing:
            count = _scene_count(row.dataset, root, row.split)
            if count <= row.first:
                row = TableRow(row.label, row.dataset, row.split, row.first,
                               f'no {row.dataset} pairs to score under {root}')
        checked.append(row)
    return checked


def _mean(values: Sequence[float]) -> float:
    return math.fsum(values) / len(values)


def _cells(records: Sequence[dict[str, Any]]) -> dict[tuple[str, str], dict[str, float]]:
    """(row label, matcher) → {'opt': ..., method: mean AUC × 10²}.

    Raises:
        InputError: Two different records of one scene, matcher and method, or a method
            without records for some scenes of its row: its mean (over other scenes than the
            row's other cells and ``Opt.``) could take the bold it does not earn.
    """
    grouped: dict[tuple[str, str], dict[str, dict[str, float]]] = {}
    optimal: dict[tuple[str, str], dict[str, float]] = {}
    for r in records:
        key = (r['row'], r['matcher'])
        scenes = grouped.setdefault(key, {}).setdefault(r['method'], {})
        held = scenes.setdefault(r['scene'], r['auc'])  # a record given twice counts once
        if held != r['auc']:
            raise InputError(
                f'table 1 records: two different records of {key[0]} {r["scene"]} {key[1]} '
                f'{r["method"]}: auc {held} and {r["auc"]}; keep one of them'
            )
        optimal.setdefault(key, {}).setdefault(r['scene'], r['auc_opt'])
    cells = {}
    for key, methods in grouped.items():
        for name, scenes in methods.items():
            lacking = [scene for scene in optimal[key] if scene not in scenes]
            if lacking:
                raise InputError(
                    f'table 1 records: {name} has no record of {len(lacking)} of the '
                    f'{len(optimal[key])} scenes of {key[0]} {key[1]} ({lacking[:5]}); a mean '
                    'over other scenes than the rest of the row is no comparison'
                )
        cell = {name: _mean(list(scenes.values())) * 100.0 for name, scenes in methods.items()}
        cell['opt'] = _mean(list(optimal[key].values())) * 100.0
        cells[key] = cell
    return cells


def _bold_best(values: dict[str, float], decimals: int) -> set[str]:
    shown = {k: round(v, decimals) for k, v in values.items()}
    if not shown:
        return set()
    best = min(shown.values())
    return {k for k, v in shown.items() if v == best}


def format_table1(
    records: Sequence[dict[str, Any]],
    rows: Sequence[TableRow],
    matchers: Sequence[str],
    columns: Sequence[tuple[str, str]] = COLUMNS,
    decimals: int = 2,
) -> str:
    """Markdown in the layout of the paper's Table 1 (missing rows show ``–``).

    Args:
        records: Per-scene records with ``row``, ``scene``, ``matcher``, ``method``, ``auc``,
            ``auc_opt``.
        rows: The data-set blocks, in order.
        matchers: Matcher order within a block.
        columns: (method, title) pairs.
        decimals: Digits after the decimal point.

    Returns:
        The table, ending in a newline; the best method value of each row is bold (ties: all).

    Raises:
        InputError: Two different records of one scene, matcher and method, or a method
            with records for only some scenes of a row (its mean would cover other scenes).
    """
    cells = _cells(records)
    header = ['data set', 'matcher', 'Opt.', *[title for _, title in columns]]
    lines = [
        '| ' + ' | '.join(header) + ' |',
        '|' + '|'.join([':---', ':---'] + ['---:'] * (len(header) - 2)) + '|',
    ]
    for row in rows:
        for matcher in matchers:
            cell = cells.get((row.label, matcher), {})
            values = {m: cell[m] for m, _ in columns if m in cell}
            bold = _bold_best(values, decimals)
            texts = [f'{cell["opt"]:.{decimals}f}' if 'opt' in cell else '–']
            for method, _ in columns:
                if method not in values:
                    texts.append('–')
                else:
                    text = f'{values[method]:.{decimals}f}'
                    texts.append(f'**{text}**' if method in bold else text)
            label = MATCHER_LABELS.get(matcher, matcher)
            lines.append('| ' + ' | '.join([row.label, label, *texts]) + ' |')
    return '\n'.join(lines) + '\n'


def format_paper_table1() -> str:
    """The paper's own Table 1 (Opt., CCNN, LFN, LGC-Net, CVA-Net), best in bold."""
    header = ['data set', 'matcher', 'Opt.', 'CCNN', 'LFN', 'LGC-Net', 'CVA-Net']
    lines = ['| ' + ' | '.join(header) + ' |', '|:---|:---|' + '---:|' * 5]
    for label, block in PAPER_TABLE1.items():
        for matcher, values in block.items():
            best = min(values[1:])
            texts = [f'{values[0]:.2f}'] + [
                f'**{v:.2f}**' if v == best else f'{v:.2f}' for v in values[1:]
            ]
            lines.append('| ' + ' | '.join([label, MATCHER_LABELS[matcher], *texts]) + ' |')
    return '\n'.join(lines) + '\n'


def save_table_png(
    records: Sequence[dict[str, Any]],
    rows: Sequence[TableRow],
    matchers: Sequence[str],
    path: Path,
    title: str,
    columns: Sequence[tuple[str, str]] = COLUMNS,
) -> Path:
    """The table as a PNG: each cell shaded by its AUC relative to the row's best (green)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.transforms import Bbox

    cells = _cells(records)
    labels, texts, colours = [], [], []
    for row in rows:
        for matcher in matchers:
            cell = cells.get((row.label, matcher), {})
            values = {m: cell[m] for m, _ in columns if m in cell}
            bold = _bold_best(values, 2)
            best = min(values.values()) if values else 0.0
            labels.append(f'{row.label} · {MATCHER_LABELS.get(matcher, matcher)}')
            line = [f'{cell["opt"]:.2f}' if 'opt' in cell else '–']
            shade: list[str | tuple[float, float, float]] = ['#eeeeee']  # names or RGB
            for method, _ in columns:
                if method not in values:
                    line.append('–')
                    shade.append('#ffffff')
                    continue
                line.append(f'{values[method]:.2f}')
                ratio = min(1.0, (values[method] / best - 1.0) if best > 0 else 1.0)
                shade.append('#7fd17f' if method in bold else
                             (1.0, 1.0 - 0.45 * ratio, 1.0 - 0.45 * ratio))
            texts.append(line)
            colours.append(shade)
    figure = Figure(figsize=(1.0 * (len(columns) + 4), 0.32 * (len(labels) + 3)))
    FigureCanvasAgg(figure)
    axes = figure.add_subplot(111)
    axes.axis('off')
    table = axes.table(
        cellText=texts,
        cellColours=colours,
        rowLabels=labels,
        colLabels=['Opt.', *[t for _, t in columns]],
        bbox=Bbox.from_bounds(0.0, 0.0, 1.0, 1.0),  # the whole axes: title, note close by
    )
    table.auto_set_font_size(False)
    table.set_fontsize(8)
    axes.set_title(title, fontsize=9)
    # What the shades mean, under the table (the Markdown says it in its first line).
    axes.text(0.5, -0.02, 'green: best of the row; red: worse (full red at twice the best); '
              '–: not scored', transform=axes.transAxes, ha='center', va='top', fontsize=7,
              color='0.3')
    path.parent.mkdir(parents=True, exist_ok=True)
    # Cropped to what is drawn: sized by the columns, the figure cut a title longer than the
    # table off at the right (one method: "... AUC × 10², mea"), and the centred table left
    # a wide blank band under the title. Beside it first, then moved in place: written
    # directly, a full disk left a truncated PNG and an error that named no file.
    with naming(path):
        write_atomic(path, lambda handle: figure.savefig(
            handle, format='png', dpi=130, bbox_inches='tight', pad_inches=0.15))
    return path


def _build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=PROG,
        description="Reproduce the paper's Table 1: AUC of CCNN, LFN, LGC-Net, CVA-Net and "
        'the hand-crafted measures for every matcher on KITTI 2012 / 2015 and Middlebury v3.',
        epilog='Exit codes: 0 done, 2 bad input or an output that cannot be written (one line '
        'on stderr), or a partial table (scenes that could not be used; scenes left out for a '
        'missing file, unless --allow-missing-files), 130 stopped by Ctrl-C, 143 by SIGTERM '
        '(the scenes done are written). The table goes to stdout, progress to stderr.',
    )
    parser.add_argument('--data-root', type=Path, required=True,
                        help='folder holding the data sets (e.g. ../shared/data)')
    parser.add_argument('--protocol', choices=('auto', 'paper', 'develop'), default='auto',
                        help='paper = full downloads; develop = train/develop split')
    parser.add_argument('--out', type=Path, required=True,
                        help='folder for table1.md, table1.json, table1.png')
    parser.add_argument('--matchers', default='census_bm,census_sgm,mccnn_fast')
    parser.add_argument('--methods', default=','.join(m for m, _ in COLUMNS),
                        help='columns, in order (default all)')
    parser.add_argument('--max-disparity', type=int, default=64)
    parser.add_argument('--max-pixels', type=int, default=None,
                        help='score a fixed random subset of N ground-truth pixels per scene')
    parser.add_argument('--seed', type=int, default=0, help='seed of the pixel subsets')
    parser.add_argument('--max-scenes', type=int, default=None,
                        help='score at most this many scenes per data set')
    parser.add_argument('--kitti2012-train', type=int, default=20,
                        help='paper protocol: the first N KITTI 2012 pairs are training data '
                        '(not scored, nor are the next 3: the paper leaves out 23 pairs)')
    parser.add_argument('--weights-dir', type=Path, default=None,
                        help='look for <arch>_<matcher>_d<D>.pt here first (and train there)')
    parser.add_argument('--train-missing', action='store_true',
                        help='train missing weights with the shipped recipe')
    parser.add_argument('--train-scale', type=float, default=1.0,
                        help='scale the recipe samples per epoch (quick runs < 1)')
    parser.add_argument('--train-synthetic', type=int, default=None,
                        help='synthetic training pairs (default 24 develop, 0 paper)')
    parser.add_argument('--train-synthetic-size', default=None,
                        help='HxW of the synthetic training pairs (default by D)')
    parser.add_argument('--train-datasets', default=None,
                        help='comma-separated training data sets, or "none" (default by '
                        'protocol)')
    parser.add_argument('--reuse', type=Path, default=None,
                        help='records JSON of an earlier cva-evaluate / cva-table1 run with the '
                        'same D, --max-pixels and --seed: its (scene, matcher, method) '
                        'results are taken over after a consistency check, not recomputed')
    parser.add_argument('--allow-missing-files', action='store_true',
                        help='a scene of a row with ground truth but a file missing (a right '
                        'image) is left out and the table marked partial with exit status 2; '
                        'with this option the exit status is 0 all the same')
    parser.add_argument('--device', default='cpu', choices=('cpu', 'cuda', 'auto'))
    parser.add_argument('--threads', type=int, default=None, help='torch and numba threads')
    return parser


def _log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def _names(text: str, what: str) -> list[str]:
    names = [n.strip() for n in text.split(',') if n.strip()]
    if not names:
        raise ConfigError(f'expected a comma-separated list of {what}; got {text!r}')
    return list(dict.fromkeys(names))


def _weights_path(args: argparse.Namespace, arch: str, matcher: str) -> Path | None:
    from cva_confidence_ros.model import default_weights_path, weights_file_name

    name = weights_file_name(matcher, args.max_disparity, arch)
    if args.weights_dir is not None and (args.weights_dir / name).is_file():
        return args.weights_dir / name
    try:
        return default_weights_path(matcher, args.max_disparity, arch)
    except ModelError:
        return None


def _train(args: argparse.Namespace, protocol: str, arch: str, matcher: str) -> Path:
    from cva_confidence_ros.model import weights_file_name
    from cva_confidence_ros.training import TrainConfig
    from cva_confidence_ros.training.trainer import train

    folder = args.weights_dir if args.weights_dir is not None else args.out / 'weights'
    target = folder / weights_file_name(matcher, args.max_disparity, arch)
    recipe = dict(RECIPES[arch])
    recipe['samples_per_epoch'] = max(1, int(recipe['samples_per_epoch'] * args.train_scale))
    if args.train_datasets is not None:
        datasets = () if args.train_datasets == 'none' else tuple(
            _names(args.train_datasets, 'data sets'))
    else:
        datasets = DEVELOP_TRAIN if protocol == 'develop' else ('kitti2012',)
    synthetic = args.train_synthetic
    if synthetic is None:
        synthetic = 24 if protocol == 'develop' else 0
    size = None
    if args.train_synthetic_size:
        height, _, width = args.train_synthetic_size.partition('x')
        if not (height.isdigit() and width.isdigit()):
            raise ConfigError(
                '--train-synthetic-size must be HxW, e.g. 64x128; got '
                f'{args.train_synthetic_size!r}'
            )
        size = (int(height), int(width))
    config = TrainConfig(
        arch=arch,
        matcher=matcher,
        max_disparity=args.max_disparity,
        data_root=str(args.data_root) if datasets else None,
        datasets=datasets,
        max_scenes=args.kitti2012_train if protocol == 'paper' else None,
        synthetic=synthetic,
        synthetic_size=size,
        val_synthetic=2,
        val_pixels=1500,
        seed=1,
        device=args.device,
        threads=args.threads,
        out=str(args.out / 'runs' / target.stem),
        overwrite=True,  # its own scratch folder: a run that wrote no weights starts over
        weights_out=str(target),
        progress=False,
        **recipe,
    )
    command = (
        f'{PROG} --train-missing (arch {arch}, matcher {matcher}, data sets '
        f'{",".join(datasets) or "none"}, synthetic {synthetic}, recipe {recipe})'
    )
    _log(f'training {target.name}: {command}')
    train(config, command)
    return target


def _load_reusable(
    path: Path, methods: Sequence[str], settings: dict[str, Any] | None = None
) -> dict[tuple[str, str, str], dict[str, dict[str, Any]]]:
    """(dataset, scene, matcher) → method → record, from a records JSON (a list, or the
    ``records`` of a ``table1.json``).

    Args:
        path: The ``--reuse`` file.
        methods: Methods whose records are kept.
        settings: This run's ``max_disparity``, ``max_pixels`` and ``seed``; a ``table1.json``
            that states other ones is refused (a list of records states none: only the
            per-scene pixel check of :func:`run` applies).

    Raises:
        DataError: The file cannot be read, is not JSON, or holds neither a list nor an object
            with ``records``.
        InputError: A record is not valid, or two records of one scene, matcher and method
            differ (which to take?); the message names the file and the record's index.
        ConfigError: A ``table1.json`` of another D, ``--max-pixels`` or (for pixel subsets)
            ``--seed`` than ``settings``.
    """
    from cva_confidence_ros.evaluation.records import EvalRecord

    try:
        data = json.loads(path.read_text(encoding='utf-8'))
    except (OSError, ValueError, RecursionError) as exc:
        # ValueError: not UTF-8, not JSON, or an integer of more digits than Python converts;
        # RecursionError: nested deeper than the parser goes.
        raise DataError(f'cannot read --reuse records {path}: {reason(exc)}') from None
    if isinstance(data, dict) and 'records' not in data:
        # It was read as no records at all: every scene recomputed, no word said.
        raise DataError(
            f'--reuse {path}: a JSON object without "records" (keys {sorted(data)[:8]}); '
            'expected a list of records or a table1.json'
        )
    if isinstance(data, dict) and settings is not None:
        # The per-scene check (pixel count and error rate) let through records of another D
        # or seed wherever the WTA error count came out the same.
        options = {'max_disparity': '--max-disparity', 'max_pixels': '--max-pixels',
                   'seed': '--seed'}
        for setting, option in options.items():
            if setting not in data or (setting == 'seed' and settings['max_pixels'] is None):
                continue  # without a subset, the seed selects nothing
            if data[setting] != settings[setting]:
                old, new = (('none (all pixels)' if value is None else value)
                            for value in (data[setting], settings[setting]))
                raise ConfigError(
                    f'--reuse {path}: its records were scored with {option} {old}, this run '
                    f'uses {new}; use the same D, --max-pixels and --seed'
                )
    items = data['records'] if isinstance(data, dict) else data
    if not isinstance(items, list):
        raise DataError(
            f'--reuse {path}: expected a list of records (or a table1.json with "records"); '
            f'got {type(items).__name__}'
        )
    found: dict[tuple[str, str, str], dict[str, dict[str, Any]]] = {}
    for index, item in enumerate(items):
        try:
            record = EvalRecord.from_mapping(item).as_dict()
        except InputError as exc:
            raise InputError(f'--reuse {path}: record {index}: {exc}') from None
        if record['method'] in methods:
            key = (str(record['dataset']), str(record['scene']), str(record['matcher']))
            held = found.setdefault(key, {}).setdefault(str(record['method']), record)
            if held != record:  # the later one silently replaced the earlier one
                raise InputError(
                    f'--reuse {path}: record {index}: a second, different record of '
                    f'{"/".join(key[:2])} {key[2]} {record["method"]}: auc {held["auc"]} and '
                    f'{record["auc"]}; keep one of them'
                )
    return found


def run(args: argparse.Namespace) -> int:
    """Score every method on every row; write the outputs. Raises ``CVAError`` on bad input."""
    from cva_confidence_ros.confidence import CONFIDENCE_METHODS
    from cva_confidence_ros.datasets import (
        list_scenes,
        load_scene,
        skipped_notice,
        skipped_scenes,
    )
    from cva_confidence_ros.evaluation.cli import RESUME_TOLERANCE, SceneRun, run_scenes
    from cva_confidence_ros.evaluation.scene import evaluate_scene
    from cva_confidence_ros.matching import MATCHERS

    if args.max_pixels is not None and args.max_pixels < 1:
        raise ConfigError(f'--max-pixels must be ≥ 1; got {args.max_pixels}')
    if not 0 < args.train_scale <= 1e3:
        raise ConfigError(f'--train-scale must be in (0, 1000]; got {args.train_scale}')
    if not 1 <= args.max_disparity <= 1024:
        raise ConfigError(f'--max-disparity must be in [1, 1024]; got {args.max_disparity}')
    if args.seed < 0:
        raise ConfigError(f'--seed must be ≥ 0; got {args.seed}')
    if args.max_scenes is not None and args.max_scenes < 1:
        raise ConfigError(f'--max-scenes must be ≥ 1; got {args.max_scenes}')
    if args.kitti2012_train < 0:
        raise ConfigError(f'--kitti2012-train must be ≥ 0; got {args.kitti2012_train}')
    if args.threads is not None and args.threads < 1:
        raise ConfigError(f'--threads must be ≥ 1; got {args.threads}')
    if args.train_datasets not in (None, 'none'):
        from cva_confidence_ros.training.config import check_training_datasets

        check_training_datasets(_names(args.train_datasets, 'data sets'))
    check_output_dir(args.out, '--out')
    if args.weights_dir is not None:
        check_output_dir(args.weights_dir, '--weights-dir')
    if not args.data_root.is_dir():
        raise DataError(f'--data-root {args.data_root} is not a folder')
    if args.threads:
        import torch

        from cva_confidence_ros.training.trainer import _limit_numba_threads

        _limit_numba_threads(args.threads)
        torch.set_num_threads(args.threads)
    matchers = _names(args.matchers, 'matchers')
    for matcher in matchers:
        MATCHERS.get(matcher)
    methods = _names(args.methods, 'methods')
    for method in methods:
        CONFIDENCE_METHODS.get(method)
    titles = dict(COLUMNS)
    columns = [(m, titles.get(m, m)) for m in methods]
    protocol = resolve_protocol(args.protocol, args.data_root, args.kitti2012_train)
    rows = table_rows(protocol, args.data_root, args.kitti2012_train)
    if all(row.missing for row in rows):
        raise DataError(
            f'no test data under {args.data_root}: '
            + '; '.join(f'{r.label}: {r.missing}' for r in rows)
        )
    _log(f'protocol {protocol}; rows: ' + ', '.join(
        r.label + (' (missing)' if r.missing else '') for r in rows))

    weights: dict[tuple[str, str], Path] = {}
    missing = []
    for method in methods:
        arch = LEARNED.get(method)
        if arch is None:
            continue
        for matcher in matchers:
            path = _weights_path(args, arch, matcher)
            if path is None:
                missing.append((arch, matcher))
            else:
                weights[(method, matcher)] = path
    if missing and not args.train_missing:
        listed = ', '.join(f'{a}/{m}' for a, m in missing)
        raise ModelError(
            f'no weights for {listed} at D = {args.max_disparity}; train them with '
            f'--train-missing (or cva-train --arch ARCH) or give --weights-dir'
        )
    # Read before any training: a bad --reuse file fails now, not after hours of it.
    settings = {'max_disparity': args.max_disparity, 'max_pixels': args.max_pixels,
                'seed': args.seed}
    reusable = _load_reusable(args.reuse, methods, settings) if args.reuse else {}
    by_arch = {arch: method for method, arch in LEARNED.items()}
    for arch, matcher in missing:
        weights[(by_arch[arch], matcher)] = _train(args, protocol, arch, matcher)

    built: dict[str, dict[str, Any]] = {}
    for matcher in matchers:
        built[matcher] = {}
        for method in methods:
            path = weights.get((method, matcher))
            built[matcher][method] = CONFIDENCE_METHODS.get(method)(
                matcher=matcher, max_disparity=args.max_disparity,
                weights=str(path) if path else None, device=args.device,
            )

    jobs: list[tuple[TableRow, str]] = []
    left_out: list[tuple[str, str]] = []
    noticed: set[tuple[str, str | None]] = set()
    for row in rows:
        if row.missing:
            continue
        every_scene = list_scenes(row.dataset, args.data_root, row.split)
        scenes = every_scene[row.first :]
        # A partial download (a scene without its right image) ran on fewer scenes unsaid;
        # said once for a data set that fills two rows.
        if (row.dataset, row.split) not in noticed:
            noticed.add((row.dataset, row.split))
            if notice := skipped_notice(row.dataset, args.data_root, row.split):
                _log(notice)
        taken = scenes[: args.max_scenes]
        jobs.extend((row, scene) for scene in taken)
        # ... and the row was no partial one (exit status 0, no mark). Only the scenes the
        # row would have held count: not those among the training pairs before ``first``.
        low = every_scene[row.first - 1] if 0 < row.first <= len(every_scene) else None
        high = taken[-1] if len(taken) < len(scenes) and taken else None
        left_out.extend(
            (f'{row.dataset}/{scene}', why)
            for scene, why in skipped_scenes(row.dataset, args.data_root, row.split)
            if (low is None or scene > low) and (high is None or scene < high)
        )
    # Once one scene of --reuse has been scored again and agreed with it, a scene it holds
    # for every matcher and method is taken over as it is: an interrupted run's table1.json
    # continues where it stopped instead of scoring every scene again. Per matcher: each
    # matcher has weights of its own.
    checked: set[str] = set()

    def held(job: tuple[TableRow, str]) -> list[dict[str, Any]] | None:
        row, scene = job
        found = [reusable.get((row.dataset, scene, matcher), {}) for matcher in matchers]
        if checked != set(matchers) or not all(m in old for old in found for m in methods):
            return None
        return [{'row': row.label, **old[m], 'reused': True} for old in found for m in methods]

    def work(number: int, job: tuple[TableRow, str]) -> list[dict[str, Any]]:
        row, scene = job
        sample = load_scene(row.dataset, args.data_root, scene, split=row.split)
        prefix = f'[{number}/{len(jobs)}] {row.dataset}/{scene}'
        records: list[dict[str, Any]] = []
        for matcher in matchers:
            old = reusable.get((row.dataset, scene, matcher), {})
            todo = [m for m in methods if m not in old]
            if len(todo) == len(methods):
                old = {}
            elif not todo:
                todo = list(methods)  # scored again to check the file's records against
            fresh = {
                record.method: {'row': row.label, **record.as_dict()}
                for record in evaluate_scene(
                    sample, matcher, built[matcher], max_disparity=args.max_disparity,
                    max_pixels=args.max_pixels, seed=args.seed, method_order=todo,
                    log=cast('Callable[[str], None]',
                             lambda message, p=prefix: _log(f'{p} {message}')),
                    progress=True,
                )
            }
            check = next(iter(fresh.values()))
            for method, item in old.items():
                same = (item['n_pixels'] == check['n_pixels']
                        and abs(item['error_rate'] - check['error_rate']) < 1e-9)
                if not same:
                    raise ConfigError(
                        f'--reuse {args.reuse}: {row.dataset}/{scene} {matcher} {method} was '
                        f'scored on other pixels ({item["n_pixels"]} px, error rate '
                        f'{item["error_rate"]:.6f}; now {check["n_pixels"]} px, '
                        f'{check["error_rate"]:.6f}): use the same D, --max-pixels and --seed'
                    )
                now = fresh.get(method)
                if now is not None and abs(now['auc'] - item['auc']) > RESUME_TOLERANCE:
                    raise ConfigError(
                        f'--reuse {args.reuse}: {row.dataset}/{scene} {matcher} {method} has '
                        f'AUC {item["auc"]:.6f} there, {now["auc"]:.6f} scored now on the same '
                        f'pixels: it was scored with other weights or settings; give the '
                        f'weights it was scored with, or leave --reuse out'
                    )
                if now is not None:
                    # Records of other weights have the same pixels and error rate: only a
                    # scene held in full and scored again (its AUC compared) checks them.
                    checked.add(matcher)
                fresh[method] = {'row': row.label, **item, 'reused': True}
                _log(f'{prefix} {matcher} {method} reused: AUC {100 * item["auc"]:.2f}')
            records.extend(fresh[m] for m in methods)
        return records

    def summary_text(records: list[dict[str, Any]], partial: str | None) -> str:
        """The text of ``table1.json``."""
        cells = _cells(records)
        summary = {
            'protocol': protocol,
            'max_disparity': args.max_disparity,
            'max_pixels': args.max_pixels,
            'seed': args.seed,
            'matchers': matchers,
            'methods': methods,
            'rows': [{'label': r.label, 'dataset': r.dataset, 'split': r.split,
                      'first': r.first, 'missing': r.missing} for r in rows],
            'weights': {f'{m}/{k}': str(p) for (m, k), p in weights.items()},
            'cells_are': 'AUC x 10^2 (and Opt.), mean of the per-scene values over the scenes '
                         'of the row',
            'cells': [{'row': label, 'matcher': matcher, **values}
                      for (label, matcher), values in cells.items()],
            'records': records,
            'partial': partial,
            'paper': {label: {m: dict(zip(['opt', 'ccnn', 'lfn', 'lgc_net', 'cva_net'], v,
                                          strict=True)) for m, v in block.items()}
                      for label, block in PAPER_TABLE1.items()},
        }
        return json.dumps(summary, indent=2, allow_nan=False) + '\n'

    def save(so_far: SceneRun) -> None:
        """``table1.json`` after every scene: a kill or a crash keeps the scenes done, and
        ``--reuse`` of it continues the run."""
        args.out.mkdir(parents=True, exist_ok=True)
        note = f'in progress: {so_far.done} of {so_far.total} scenes done'
        write_text_atomic(args.out / 'table1.json', summary_text(so_far.records, note))

    outcome = run_scenes(jobs, lambda job: f'{job[0].dataset}/{job[1]}', work, after=save,
                         held=held)
    outcome.left_out = left_out
    outcome.allow_left_out = args.allow_missing_files
    if not outcome.records:
        return outcome.ending(PROG, 'nothing written')
    records = outcome.records
    table = format_table1(records, rows, matchers, columns)
    missing_rows = [r for r in rows if r.missing]
    notes = [f'- {r.label}: not scored — {r.missing}.' for r in missing_rows]
    if outcome.partial:
        notes.append(outcome.note())
    subset = f'{args.max_pixels} ground-truth pixels per scene (seed {args.seed})' if (
        args.max_pixels) else 'all ground-truth pixels'
    reused = sorted({r['method'] for r in records if r.get('reused')})
    if reused:
        subset += (f'; {", ".join(reused)} taken over from `{args.reuse.name}` (same pixels, '
                   'checked by their error rate)')
    markdown = '\n'.join([
        f'AUC × 10², mean over scenes; protocol `{protocol}`, D = {args.max_disparity}, '
        f'{subset}; bold = best non-optimal value of the row.',
        '',
        table,
        *notes,
        '',
        "The paper's Table 1 (Mehltretter & Heipke 2019, D = 256, full data sets):",
        '',
        format_paper_table1(),
    ])
    args.out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(args.out / 'table1.md', markdown)
    write_text_atomic(args.out / 'table1.json', summary_text(records, outcome.note() or None))
    # Marked partial as the Markdown is: the PNG goes into reports without it.
    partial_mark = (f'\nPartial: {outcome.done} of {outcome.wanted} scenes (see table1.md)'
                    if outcome.partial else '')
    save_table_png(records, rows, matchers, args.out / 'table1.png',
                   f'Table 1 reproduction ({protocol}, D = {args.max_disparity}): AUC × 10², '
                   f'mean over scenes{partial_mark}',
                   columns)
    sys.stdout.write(markdown)
    sys.stdout.flush()
    _log(f'wrote {args.out / "table1.md"}, table1.json, table1.png')
    return outcome.ending(PROG, f'the records of the {outcome.done} done are in {args.out}')


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``cva-table1`` (``ros2 run cva_confidence_ros table1``).

    Returns:
        0 on success, 2 on bad input (one line on stderr) or a partial table (scenes that
        could not be used; scenes left out for a missing file, unless
        ``--allow-missing-files``), 1 if an output cannot be written.
    """
    from cva_confidence_ros.evaluation.cli import exit_code

    args = _build_parser().parse_args(argv)
    return exit_code(PROG, lambda: run(args))


if __name__ == '__main__':
    sys.exit(main())

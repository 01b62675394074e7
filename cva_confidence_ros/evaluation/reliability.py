"""Calibration report of an evaluation: is each network's confidence a probability?

``cva-evaluate --out DIR`` collects the reliability table (:mod:`cva_confidence_ros.calibration`)
of every probabilistic method per data set and matcher over all its scenes, and writes

* ``DIR/calibration.json``: a list of ``{dataset, matcher, method, n_pixels, ece, max_gap,
  brier, mean_confidence, accuracy, bins}``, one per data set, matcher and method, and (with
  more than one data set) one with ``dataset: "all"`` over every scored pixel;
* ``DIR/calibration.md``: the same as a Markdown table (percentages), with what is kept at
  the thresholds 0.5 and 0.8: the share, its error rate and the error rate the confidence
  predicts for it;
* ``DIR/reliability_<dataset>_<matcher>.png``: the reliability diagrams of the methods.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from cva_confidence_ros import strict_json
from cva_confidence_ros.calibration import ReliabilityTable
from cva_confidence_ros.errors import InputError
from cva_confidence_ros.evaluation.records import _cell

__all__ = [
    'ALL_DATASETS',
    'KEPT_THRESHOLDS',
    'format_calibration_table',
    'pooled',
    'write_calibration',
]

#: ``dataset`` of the rows over every data set.
ALL_DATASETS = 'all'

Key = tuple[str, str, str]


def pooled(tables: Mapping[Key, ReliabilityTable]) -> dict[Key, ReliabilityTable]:
    """The tables per (dataset, matcher, method) plus one per (matcher, method) over all data
    sets (``dataset`` = :data:`ALL_DATASETS`), in a stable order.

    Raises:
        InputError: A data set is named :data:`ALL_DATASETS` beside others (its row and the
            pooled one would be one key), a matcher and method lack a table of some data set
            (their row over all data sets would cover only some of them), or tables to pool
            differ in their bins (the message names the matcher, method and the bins of each
            data set).
    """
    rows: dict[Key, ReliabilityTable] = dict(sorted(tables.items()))
    datasets = {key[0] for key in tables}
    if len(datasets) > 1:
        if ALL_DATASETS in datasets:
            raise InputError(
                f'a data set named {ALL_DATASETS!r} cannot be pooled with others '
                f'({sorted(datasets - {ALL_DATASETS})}): the rows over all data sets have '
                'that name'
            )
        for matcher, method in sorted({(key[1], key[2]) for key in tables}):
            parts = {key[0]: t for key, t in tables.items() if key[1:] == (matcher, method)}
            if len(parts) < len(datasets):
                raise InputError(
                    f'cannot pool the reliability tables of {matcher} {method} over the data '
                    f'sets: it has tables of {sorted(parts)} only, none of '
                    f'{sorted(datasets - set(parts))}; its row {ALL_DATASETS!r} would cover '
                    'other pixels than those of the other methods'
                )
            if len({t.bins for t in parts.values()}) > 1:  # merge named neither row
                bins = ', '.join(f'{name} {t.bins}' for name, t in sorted(parts.items()))
                raise InputError(
                    f'cannot pool the reliability tables of {matcher} {method} over the data '
                    f'sets: their bins differ ({bins})'
                )
            rows[(ALL_DATASETS, matcher, method)] = ReliabilityTable.combine(parts.values())
    return rows


#: Thresholds at which the table shows what is kept (bin edges of the default 10 bins).
KEPT_THRESHOLDS = (0.5, 0.8)


def _percent(value: float | None, decimals: int = 1) -> str:
    return '–' if value is None else f'{100 * value:.{decimals}f}'


def format_calibration_table(
    tables: Mapping[Key, ReliabilityTable], thresholds: tuple[float, ...] = KEPT_THRESHOLDS
) -> str:
    """Markdown table of the calibration of each data set, matcher and method.

    Columns: pixels; ECE, the largest gap of a bin and the Brier score; then per threshold τ
    (bin edges) the share of pixels with confidence ≥ τ, their error rate (ground truth) and
    the error rate their confidence predicts, mean(1 − confidence) — what the node reports in
    ``/diagnostics`` as ``expected_kept_error``. All in percent. A ``|`` in a name is
    written ``\\|``.

    Raises:
        InputError: As :func:`pooled`; a table holds no pixels, or a threshold is no bin edge
            below 1 of its bins (the message names the row).
    """
    head = '| data set | matcher | method | pixels | ECE % | max bin gap % | Brier % |'
    rule = '|:---|:---|:---|---:|---:|---:|---:|'
    for tau in thresholds:
        head += f' kept ≥ {tau:g} % | its error % | predicted % |'
        rule += '---:|---:|---:|'
    lines = [head, rule]
    for (dataset, matcher, method), table in pooled(tables).items():
        names = ' | '.join(_cell(name) for name in (dataset, matcher, method))
        try:
            row = (
                f'| {names} | {table.n_pixels} | {100 * table.ece:.2f} '
                f'| {100 * table.max_gap:.1f} | {100 * table.brier:.2f} |'
            )
            for tau in thresholds:
                kept, measured, predicted = table.kept_at(tau)
                row += (
                    f' {_percent(kept)} | {_percent(measured, 2)} | {_percent(predicted, 2)} |'
                )
        except InputError as exc:  # 'the reliability table holds no pixels' named no row
            raise InputError(f'calibration of {dataset} {matcher} {method}: {exc}') from None
        lines.append(row)
    return '\n'.join(lines) + '\n'


def write_calibration(tables: Mapping[Key, ReliabilityTable], out_dir: str | Path) -> list[Path]:
    """Write ``calibration.json``, ``calibration.md`` and the reliability PNGs into ``out_dir``.

    Returns:
        The paths written (none if ``tables`` is empty).

    Raises:
        InputError: As :func:`pooled` and :func:`format_calibration_table` (e.g. tables whose
            bins do not have 0.5 and 0.8 as edges, or that hold no pixels); raised before any
            file is written.
        DataError: ``calibration.json`` or ``.md`` cannot be written (an old one is left as
            it was: each is written beside, synced, then moved in place).
    """
    from cva_confidence_ros.outputs import naming, write_text_atomic
    from cva_confidence_ros.plots import save_reliability_diagram

    if not tables:
        return []
    rows = pooled(tables)
    # The table first: its errors name the row (as_dict's do not).
    table_text = format_calibration_table(tables)
    records: list[dict[str, Any]] = [
        {'dataset': dataset, 'matcher': matcher, 'method': method, **table.as_dict()}
        for (dataset, matcher, method), table in rows.items()
    ]
    # Both texts first: an error in the table must not leave a new JSON beside an old table.
    texts = (strict_json.dumps(records, indent=1) + '\n', table_text)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = [out / 'calibration.json', out / 'calibration.md']
    for path, text in zip(written, texts, strict=True):
        write_text_atomic(path, text)  # whole or not at all: an old file stays as it was
    for dataset, matcher in sorted({(key[0], key[1]) for key in rows}):
        per_method = {key[2]: t for key, t in rows.items() if key[:2] == (dataset, matcher)}
        path = out / f'reliability_{dataset}_{matcher}.png'
        with naming(path):  # a full disk's error named no file
            written.append(
                save_reliability_diagram(per_method, path, title=f'{dataset}  {matcher}')
            )
    return written

"""Per-scene evaluation records, their JSON file and the Table-1 Markdown layout."""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass
import json
import math
from numbers import Integral, Real
import os
from pathlib import Path

from cva_confidence_ros.errors import DataError, InputError
from cva_confidence_ros.metrics import DENSITY_STEPS, optimal_auc
from cva_confidence_ros.outputs import write_text_atomic

__all__ = [
    'RECORD_KEYS',
    'EvalRecord',
    'format_table',
    'read_records',
    'write_records',
]

RECORD_KEYS = (
    'dataset',
    'scene',
    'matcher',
    'method',
    'auc',
    'auc_opt',
    'error_rate',
    'n_pixels',
)
"""Keys of one JSON record, in file order."""


@dataclass(frozen=True)
class EvalRecord:
    """Score of one confidence method on one scene and matcher.

    Attributes:
        dataset: Data set name (``kitti2015``, ``motorcycle``, ...).
        scene: Scene name within the data set.
        matcher: Matcher that produced the cost volume and disparity map.
        method: Confidence method name (``cva_net``, ``pkrn``, ...).
        auc: Area under the ROC curve (error rate over density), in [0, 1]; lower = better.
        auc_opt: The optimal AUC for this disparity map (paper Eq. (1)); same for all methods
            of a scene and matcher.
        error_rate: Fraction of scored pixels whose disparity is wrong (KITTI criterion).
        n_pixels: Number of scored pixels (ground truth known; the subset if one was drawn).
    """

    dataset: str
    scene: str
    matcher: str
    method: str
    auc: float
    auc_opt: float
    error_rate: float
    n_pixels: int

    def __post_init__(self) -> None:
        """Check the values where a record is made, so that no file gets one it cannot read.

        Raises:
            InputError: As :meth:`from_mapping`.
        """
        names = [key for key in RECORD_KEYS[:4] if not isinstance(getattr(self, key), str)]
        if names:
            raise InputError(
                'evaluation record: '
                + ', '.join(f'{key} must be a string; got {getattr(self, key)!r}' for key in names)
            )
        where = f'evaluation record {self.dataset}/{self.scene} {self.method}'
        for key in ('auc', 'auc_opt', 'error_rate'):
            value: object = getattr(self, key)
            number = _real(value)
            # A NaN would average into every row of the table that holds it.
            if number is None or not 0.0 <= number <= 1.0:
                kind = '' if number is not None else f' (a {type(value).__name__})'
                raise InputError(f'{where}: {key} must be a number in [0, 1]; got {value}{kind}')
            object.__setattr__(self, key, number)  # a numpy scalar is no JSON number
        pixels: object = self.n_pixels
        number = _real(pixels)
        if number is None or not (number >= 1 and number.is_integer()):
            raise InputError(f'{where}: n_pixels must be a whole number ≥ 1; got {pixels!r}')
        whole = int(pixels) if isinstance(pixels, Integral) else int(number)
        object.__setattr__(self, 'n_pixels', whole)

    def as_dict(self) -> dict[str, str | float | int]:
        """The record as a JSON-ready dict with exactly :data:`RECORD_KEYS`."""
        return asdict(self)

    @classmethod
    def from_mapping(cls, item: Mapping[str, object]) -> EvalRecord:
        """Build a record from a dict with :data:`RECORD_KEYS` (extra keys are ignored).

        Raises:
            InputError: A key is missing, a value has the wrong type (the names must be
                strings, the rest numbers; a number in a string is refused), a rate or AUC is
                not a number in [0, 1] (NaN included), or ``n_pixels`` is not a whole number
                ≥ 1.
        """
        if not isinstance(item, Mapping):
            raise InputError(
                f'an evaluation record must be a JSON object; got {type(item).__name__}'
            )
        missing = [key for key in RECORD_KEYS if key not in item]
        if missing:
            raise InputError(f'evaluation record lacks keys {missing}; got {sorted(item)}')
        return cls(**{key: item[key] for key in RECORD_KEYS})  # type: ignore[arg-type]


def _real(value: object) -> float | None:
    """``value`` as a float if it is a real number (not a bool, not a string), else None."""
    if isinstance(value, bool) or not isinstance(value, Real):
        return None
    try:
        return float(value)
    except OverflowError:  # an integer of 309 digits or more
        return math.inf if isinstance(value, int) and value > 0 else -math.inf


RecordLike = EvalRecord | Mapping[str, object]


def _as_records(records: Iterable[RecordLike]) -> list[EvalRecord]:
    return [r if isinstance(r, EvalRecord) else EvalRecord.from_mapping(r) for r in records]


def write_records(records: Iterable[RecordLike], path: str | os.PathLike[str]) -> Path:
    """Write records as a JSON list of objects with :data:`RECORD_KEYS`.

    Args:
        records: :class:`EvalRecord` objects or equivalent dicts.
        path: Output file; parent folders are created.

    Returns:
        The path written.

    Raises:
        InputError: A record is not valid (checked before the file is touched).
        DataError: The file cannot be written (a full disk, no permission); an older file at
            ``path`` is left as it was (the new one is written beside it, synced to the disk,
            then moved in place).
    """
    items = [r.as_dict() for r in _as_records(records)]
    return write_text_atomic(path, json.dumps(items, indent=2, allow_nan=False) + '\n',
                             'records ')


def read_records(path: str | os.PathLike[str]) -> list[EvalRecord]:
    """Read a file written by :func:`write_records`.

    Raises:
        DataError: The file is missing, not UTF-8 text (e.g. binary) or not a JSON list.
        InputError: A record is not valid (see :meth:`EvalRecord.from_mapping`); the message
            names the file and the record's index.
    """
    try:
        items = json.loads(Path(path).read_text(encoding='utf-8'))
    # ValueError: not JSON, not UTF-8, or an integer of more than 4300 digits;
    # RecursionError: arrays nested thousands deep.
    except (OSError, ValueError, RecursionError) as exc:
        raise DataError(f'cannot read evaluation records from {path}: {exc}') from None
    if not isinstance(items, list):
        raise DataError(f'{path} must hold a JSON list of records; got {type(items).__name__}')
    records = []
    for index, item in enumerate(items):
        try:
            records.append(EvalRecord.from_mapping(item))
        except InputError as exc:
            raise InputError(f'{path}: record {index}: {exc}') from None
    return records


def _mean(values: Sequence[float]) -> float:
    return math.fsum(values) / len(values)


def _cell(text: str) -> str:
    """``text`` for a Markdown table cell: a ``|`` in a name would start a new column."""
    return text.replace('|', '\\|')


def _unique(items: Sequence[EvalRecord]) -> list[EvalRecord]:
    """``items`` with each (data set, scene, matcher, method) once: a scene listed twice was
    counted twice in its method's mean.

    Raises:
        InputError: Two records of one scene, matcher and method differ.
    """
    seen: dict[tuple[str, str, str, str], EvalRecord] = {}
    for r in items:
        key = (r.dataset, r.scene, r.matcher, r.method)
        first = seen.setdefault(key, r)
        if first != r:
            raise InputError(
                f'two different evaluation records of {r.dataset}/{r.scene} {r.matcher} '
                f'{r.method}: auc {first.auc} and {r.auc} (n_pixels {first.n_pixels} and '
                f'{r.n_pixels}); keep one of them'
            )
    return list(seen.values())


def _check_same_pixels(items: Sequence[EvalRecord]) -> None:
    """Refuse records of one scene and matcher that were not scored on the same pixels.

    ``auc_opt``, ``error_rate`` and ``n_pixels`` belong to the disparity map and the scored
    pixels, not to the method: records of one run agree on them. Records of other runs (other
    D, ``--max-pixels`` or ``--seed``) need not; the ``Opt.`` cell took the value of whichever
    came first, and the methods of a row were compared on different pixels.

    Raises:
        InputError: Two such records differ; the message names the scene and the values.
    """
    first: dict[tuple[str, str, str], EvalRecord] = {}
    for r in items:
        held = first.setdefault((r.dataset, r.scene, r.matcher), r)
        same = (
            held.n_pixels == r.n_pixels
            # 1e-9: the same pixels give equal values, up to the last digit of a logarithm.
            and abs(held.auc_opt - r.auc_opt) <= 1e-9
            and abs(held.error_rate - r.error_rate) <= 1e-9
        )
        if not same:
            raise InputError(
                f'evaluation records of {r.dataset}/{r.scene} {r.matcher} were scored on '
                f'different pixels: {held.method} has auc_opt {held.auc_opt}, error_rate '
                f'{held.error_rate}, n_pixels {held.n_pixels}; {r.method} has auc_opt '
                f'{r.auc_opt}, error_rate {r.error_rate}, n_pixels {r.n_pixels}; tabulate '
                'the records of one run (same D, --max-pixels and --seed)'
            )


def _lowest_auc(error_rate: float, n_pixels: int) -> float:
    """The AUC that :func:`cva_confidence_ros.metrics.roc_auc` gives a perfect confidence map
    (the correct pixels in one group of equal values above the wrong ones): no map of
    ``n_pixels`` pixels at this error rate scores lower.

    The trapezoid rule over the curve's 5 % samples falls below Eq. (1) (``auc_opt``) by up to
    0.004, and by up to 0.03 for a few pixels.
    """
    right = n_pixels - round(error_rate * n_pixels)
    counts = {-(-k * n_pixels // DENSITY_STEPS) for k in range(1, DENSITY_STEPS + 1)}
    if right >= min(counts):
        counts.add(right)  # the end of the group of correct pixels, at error rate 0
    points = sorted(counts)
    rates = [max(0, count - right) / count for count in points]
    return math.fsum(
        (points[i + 1] - points[i]) / n_pixels * (rates[i] + rates[i + 1]) / 2.0
        for i in range(len(points) - 1)
    )


def _check_possible(items: Sequence[EvalRecord]) -> None:
    """Refuse a record whose AUC is below its ``auc_opt`` by more than the sampling of the
    ROC curve allows: no confidence map scores that (``auc`` and ``auc_opt`` swapped, or
    taken from other runs), and its cell would beat ``Opt.`` in the table.

    Raises:
        InputError: The message names the record and both values.
    """
    for r in items:
        slack = max(0.0, optimal_auc(r.error_rate, r.n_pixels)
                    - _lowest_auc(r.error_rate, r.n_pixels))
        if r.auc < r.auc_opt - slack - 1e-9:
            raise InputError(
                f'evaluation record {r.dataset}/{r.scene} {r.matcher} {r.method}: auc '
                f'{r.auc} is below auc_opt {r.auc_opt} by more than the {slack:.2g} a '
                f'perfect confidence map can reach (error_rate {r.error_rate}, n_pixels '
                f'{r.n_pixels}); no confidence scores that: are auc and auc_opt swapped?'
            )


def format_table(
    records: Iterable[RecordLike],
    methods: Sequence[str] | None = None,
    decimals: int = 2,
) -> str:
    """Render records in the layout of the paper's Table 1 as a Markdown table.

    One row per (data set, matcher), in order of first appearance; the columns are ``Opt.``
    (the mean optimal AUC) and one per method. Each cell is the AUC × 10² averaged over the
    scenes of that data set (the mean of per-scene AUCs, as in the paper; a record given twice
    counts once). In every row the smallest method value, compared after rounding to
    ``decimals``, is bold (ties: all of them); ``Opt.`` is never bold. A method without
    records for a row shows ``–``; one with records for only some of the row's scenes
    shows its mean over those, takes no part in the bold (it covers other scenes than
    ``Opt.`` and the rest of the row) and is named in a note below the table.

    Args:
        records: :class:`EvalRecord` objects or dicts with :data:`RECORD_KEYS`.
        methods: Column order; default the order of first appearance. Methods named here
            but absent from the records get a column of ``–``.
        decimals: Digits after the decimal point.

    Returns:
        The Markdown table, lines joined with ``\\n``, ending in a newline; after it, where a
        method lacks scenes of a row, an empty line and a note naming those cells. An empty
        input gives a header-only table. A ``|`` in a name is written ``\\|``.

    Raises:
        InputError: ``methods`` is one string, holds a non-string or a name twice;
            ``decimals`` is not an integer ≥ 0; two records of one scene, matcher and method
            differ; two records of one scene and matcher differ in ``auc_opt``,
            ``error_rate`` or ``n_pixels`` (scored on other pixels, e.g. in another run); a
            record's ``auc`` is below its ``auc_opt`` by
            more than a perfect confidence map can be (up to 0.004; 0.03 for a few pixels).
    """
    if isinstance(decimals, bool) or not isinstance(decimals, Integral) or decimals < 0:
        # -1 or 2.5 failed in the format as 'ValueError: Format specifier missing precision'.
        raise InputError(f'decimals must be an integer ≥ 0; got {decimals!r}')
    items = _unique(_as_records(records))
    _check_same_pixels(items)
    _check_possible(items)
    if methods is None:
        methods = list(dict.fromkeys(r.method for r in items))
    elif isinstance(methods, str) or not all(isinstance(m, str) for m in methods):
        # One string is a sequence of one-letter columns ('mlm' gave m, l, m).
        raise InputError(f'methods must be a sequence of method names; got {methods!r}')
    elif len(set(methods)) != len(methods):
        raise InputError(f'methods must name each method once; got {list(methods)!r}')
    rows = list(dict.fromkeys((r.dataset, r.matcher) for r in items))

    aucs: dict[tuple[str, str, str], list[float]] = {}
    optimal: dict[tuple[str, str], dict[str, float]] = {}
    for r in items:
        aucs.setdefault((r.dataset, r.matcher, r.method), []).append(r.auc)
        # AUC_opt belongs to the scene and matcher, not the method: count each scene once.
        optimal.setdefault((r.dataset, r.matcher), {}).setdefault(r.scene, r.auc_opt)

    header = ['data set', 'matcher', 'Opt.', *(_cell(m) for m in methods)]
    lines = [
        '| ' + ' | '.join(header) + ' |',
        '|' + '|'.join([':---', ':---'] + ['---:'] * (len(header) - 2)) + '|',
    ]
    partial: list[str] = []
    for dataset, matcher in rows:
        scenes = len(optimal[(dataset, matcher)])
        opt = _mean(list(optimal[(dataset, matcher)].values())) * 100.0
        cells, compared = {}, []
        for method in methods:
            values = aucs.get((dataset, matcher, method))
            if values:
                cells[method] = f'{_mean(values) * 100.0:.{decimals}f}'
                if len(values) == scenes:
                    compared.append(float(cells[method]))
                else:  # a mean over other scenes than Opt. and the rest of the row
                    partial.append(f'{method} in {dataset} {matcher} ({len(values)} of '
                                   f'{scenes} scenes)')
        best = min(compared, default=None)
        row = [_cell(dataset), _cell(matcher), f'{opt:.{decimals}f}']
        for method in methods:
            text = cells.get(method)
            if text is None:
                row.append('–')
            elif float(text) == best and len(aucs[(dataset, matcher, method)]) == scenes:
                row.append(f'**{text}**')
            else:
                row.append(text)
        lines.append('| ' + ' | '.join(row) + ' |')
    if partial:
        lines += ['', 'Not compared (no bold), a mean over only some scenes of the row: '
                  + '; '.join(partial) + '.']
    return '\n'.join(lines) + '\n'

"""Review regressions (32): the per-scene evaluation (``evaluation.scene``) and ``cva-table1``
(its cells and ``--reuse``)."""

from __future__ import annotations

import json
from pathlib import Path
import re

import cv2
import numpy as np
import pytest

from cva_confidence_ros.datasets import StereoSample
from cva_confidence_ros.datasets.io import write_pfm
from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.evaluation.scene import evaluate_scene, select_pixels
from cva_confidence_ros.evaluation.table1 import (
    TableRow,
    _load_reusable,
    format_table1,
    main,
)

D = 16


class _Constant:
    """A dense confidence method: 0.5 everywhere, NaN at the pixels in ``nan_at``."""

    needs_right = False

    def __init__(self, nan_at: tuple[int, int] | None = None) -> None:
        self.nan_at = nan_at

    def __call__(self, inputs):
        out = np.full(inputs.disparity.shape, 0.5, dtype=np.float32)
        if self.nan_at is not None:
            out[self.nan_at] = np.nan
        return out


def _shifted_sample(largest: float | None = None) -> StereoSample:
    """Random texture shifted by 4 px; ``largest`` puts one ground-truth pixel at that value."""
    rng = np.random.default_rng(32)
    texture = rng.integers(0, 256, (32, 68), dtype=np.uint8)
    left = np.ascontiguousarray(texture[:, :64])
    right = np.ascontiguousarray(texture[:, 4:])
    gt = np.full((32, 64), 4.0, dtype=np.float32)
    gt[:, :4] = np.nan
    if largest is not None:
        gt[0, 10] = largest
    return StereoSample('synthetic', 'shift4', left, right, gt)


# --- evaluation/scene.py ---------------------------------------------------------------------


def test_select_pixels_refuses_a_disparity_map_given_as_the_mask() -> None:
    gt = np.array([[np.nan, 0.0, 5.0], [np.nan, 3.0, 0.0]], dtype=np.float32)
    # Before: cast to bool, NaN (unknown) read as known and 0 (known) as unknown.
    with pytest.raises(InputError, match='known must be an .* bool mask .*got dtype float32'):
        select_pixels(gt)
    ys, xs = select_pixels(np.isfinite(gt))
    assert list(zip(ys.tolist(), xs.tolist(), strict=True)) == [(0, 1), (0, 2), (1, 1), (1, 2)]


def test_halving_log_says_the_ground_truth_exceeds_d_minus_one() -> None:
    logs: list[str] = []
    # D − 1 = 15 fits (the cost volume holds 0 … 15): no halving.
    records = evaluate_scene(_shifted_sample(15.0), 'census_bm', {'c': _Constant()},
                             max_disparity=D, log=logs.append)
    assert records[0].n_pixels == 32 * 60 and not any('resolution' in line for line in logs)
    # 15.5 does not exceed D = 16, yet it is halved; the log said 'exceeds D = 16'.
    logs.clear()
    records = evaluate_scene(_shifted_sample(15.5), 'census_bm', {'c': _Constant()},
                             max_disparity=D, log=logs.append)
    assert records[0].n_pixels < 32 * 60
    assert 'ground truth reaches 15.5 px > D − 1 = 15: evaluating at 1/2 resolution' in logs


def test_a_nan_confidence_names_the_method_and_the_scene() -> None:
    methods = {'fine': _Constant(), 'broken': _Constant(nan_at=(5, 20))}
    # Before: 'confidence must not be NaN at scored pixels; got 1 NaN values' (which method?).
    with pytest.raises(InputError, match=r"confidence method 'broken' on synthetic/shift4: "
                                         r'confidence must not be NaN .*got 1 NaN'):
        evaluate_scene(_shifted_sample(), 'census_bm', methods, max_disparity=D)


# --- evaluation/table1.py: cells -------------------------------------------------------------

ROWS = [TableRow('KITTI 2015', 'kitti2015')]
COLUMNS = [('ccnn', 'CCNN'), ('pkrn', 'PKRN')]


def _row(scene: str, method: str, auc: float, auc_opt: float = 0.01) -> dict[str, object]:
    return {'row': 'KITTI 2015', 'scene': scene, 'matcher': 'census_bm', 'method': method,
            'auc': auc, 'auc_opt': auc_opt}


def test_a_method_missing_from_some_scenes_of_a_row_is_refused() -> None:
    # PKRN only on scene a (0.06, worse than CCNN's 0.05 there); CCNN also on the hard scene b.
    records = [_row('a', 'ccnn', 0.05), _row('b', 'ccnn', 0.20, 0.1), _row('a', 'pkrn', 0.06)]
    # Before: '| 5.50 | 12.50 | **6.00** |', PKRN bold on a mean over other scenes.
    with pytest.raises(InputError, match=r"pkrn has no record of 1 of the 2 scenes of "
                                         r"KITTI 2015 census_bm \(\['b'\]\)"):
        format_table1(records, ROWS, ['census_bm'], COLUMNS)
    # A method with no records in the row at all is a '–' cell, as before.
    table = format_table1(records[:2], ROWS, ['census_bm'], COLUMNS)
    assert '| KITTI 2015 | Census-BM | 5.50 | **12.50** | – |' in table


def test_a_record_given_twice_counts_once_in_the_table1_mean() -> None:
    records = [_row('a', 'ccnn', 0.05), _row('a', 'ccnn', 0.05), _row('b', 'ccnn', 0.08)]
    # Before: (5 + 5 + 8) / 3 = 6.00; the mean over the two scenes is 6.50.
    table = format_table1(records, ROWS, ['census_bm'], COLUMNS[:1])
    assert '| KITTI 2015 | Census-BM | 1.00 | **6.50** |' in table
    with pytest.raises(InputError, match=r'two different records of KITTI 2015 a census_bm '
                                         r'ccnn: auc 0.05 and 0.07'):
        format_table1([*records, _row('a', 'ccnn', 0.07)], ROWS, ['census_bm'], COLUMNS[:1])


# --- evaluation/table1.py: --reuse -----------------------------------------------------------


def _record(method: str = 'pkrn') -> dict[str, object]:
    return {'dataset': 'middlebury2014', 'scene': 'Synth', 'matcher': 'census_bm',
            'method': method, 'auc': 0.05, 'auc_opt': 0.01, 'error_rate': 0.1, 'n_pixels': 500}


def _summary(path: Path, **settings: object) -> Path:
    """A ``table1.json`` as ``cva-table1`` writes it: its settings and its records."""
    base = {'max_disparity': D, 'max_pixels': 500, 'seed': 0}
    path.write_text(json.dumps({**base, **settings, 'records': [_record()]}), encoding='utf-8')
    return path


def test_a_reuse_summary_of_another_d_pixel_count_or_seed_is_refused(tmp_path: Path) -> None:
    # The per-scene check compares only the pixel count and the error rate: D = 16 and D = 20
    # (or seeds 3 and 5) gave the same WTA error count on a 500-pixel subset and different
    # AUCs, and the other run's AUCs went into the table unnoticed.
    run = {'max_disparity': D, 'max_pixels': 500, 'seed': 0}
    path = tmp_path / 'table1.json'
    for key, value, message in [('max_disparity', 20, '--max-disparity 20, this run uses 16'),
                                ('max_pixels', None, '--max-pixels none (all pixels), this '
                                                     'run uses 500'),
                                ('seed', 3, '--seed 3, this run uses 0')]:
        with pytest.raises(ConfigError, match=f'--reuse .*table1.json: its records were scored '
                                              f'with {re.escape(message)}'):
            _load_reusable(_summary(path, **{key: value}), ['pkrn'], run)
    assert list(_load_reusable(_summary(path), ['pkrn'], run)) == [
        ('middlebury2014', 'Synth', 'census_bm')]
    # Without a subset the seed selects nothing; a plain list states no settings.
    every = {**run, 'max_pixels': None}
    assert _load_reusable(_summary(path, max_pixels=None, seed=7), ['pkrn'], every)
    path.write_text(json.dumps([_record()]), encoding='utf-8')
    assert _load_reusable(path, ['pkrn'], run)


def test_table1_refuses_a_reuse_summary_of_another_d_before_any_work(
    tmp_path: Path, capsys
) -> None:
    folder = tmp_path / 'data' / 'middlebury2014' / 'trainingQ' / 'Synth'
    folder.mkdir(parents=True)
    sample = _shifted_sample()
    cv2.imwrite(str(folder / 'im0.png'), sample.left)
    cv2.imwrite(str(folder / 'im1.png'), sample.right)
    write_pfm(folder / 'disp0GT.pfm', np.where(np.isfinite(sample.disparity),
                                               sample.disparity, np.inf).astype(np.float32))
    reuse = _summary(tmp_path / 'table1.json', max_disparity=24)
    out = tmp_path / 'out'
    code = main(['--data-root', str(tmp_path / 'data'), '--out', str(out), '--matchers',
                 'census_bm', '--methods', 'pkrn,score', '--max-disparity', str(D),
                 '--max-pixels', '500', '--protocol', 'develop', '--reuse', str(reuse)])
    err = capsys.readouterr().err
    assert code == 2
    assert err.splitlines()[-1] == (
        f'cva-table1: error: --reuse {reuse}: its records were scored with --max-disparity 24, '
        'this run uses 16; use the same D, --max-pixels and --seed')
    assert not (out / 'table1.md').exists()

"""Review regressions (31): the records' table and file, the calibration report, the scene
evaluation and ``cva-table1 --reuse``."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from cva_confidence_ros.calibration import reliability
from cva_confidence_ros.datasets import StereoSample
from cva_confidence_ros.errors import DataError, InputError
from cva_confidence_ros.evaluation import records as records_module
from cva_confidence_ros.evaluation.records import (
    EvalRecord,
    format_table,
    read_records,
    write_records,
)
from cva_confidence_ros.evaluation.reliability import (
    format_calibration_table,
    pooled,
    write_calibration,
)
from cva_confidence_ros.evaluation.scene import evaluate_scene, select_pixels
from cva_confidence_ros.evaluation.table1 import _load_reusable


def _rec(method: str, auc: float, auc_opt: float = 0.01, error_rate: float = 0.1,
         n_pixels: int = 1000, scene: str = 's1') -> EvalRecord:
    return EvalRecord('d', scene, 'm', method, auc, auc_opt, error_rate, n_pixels)


def _shifted_sample(width: int = 40, height: int = 16, shift: int = 3) -> StereoSample:
    """Random texture shifted by ``shift`` px: ground truth everywhere but the left edge."""
    rng = np.random.default_rng(31)
    texture = rng.integers(0, 256, (height, width + shift), dtype=np.uint8)
    left = np.ascontiguousarray(texture[:, :width])
    right = np.ascontiguousarray(texture[:, shift:])
    gt = np.full((height, width), float(shift), dtype=np.float32)
    gt[:, :shift] = np.nan
    return StereoSample('synthetic', 'shift3', left, right, gt)


# --- evaluation/records.py -------------------------------------------------------------------


def test_records_of_one_scene_scored_on_other_pixels_are_refused() -> None:
    # Run 1 scored all 1000 pixels of s1 (opt 0.01), run 2 a subset of 50 (opt 0.03). The
    # Opt. cell was that of whichever record came first: 1.00 in one order, 3.00 in the other.
    mixed = [_rec('a', 0.05), _rec('b', 0.06, auc_opt=0.03, error_rate=0.2, n_pixels=50)]
    for records in (mixed, mixed[::-1]):
        with pytest.raises(InputError, match='records of d/s1 m were scored on different '
                                             'pixels: .*auc_opt 0.0[13].*auc_opt 0.0[13]'):
            format_table(records)
    # One run: the methods of a scene agree, and the scenes may differ from each other.
    same = [_rec('a', 0.05), _rec('b', 0.08), _rec('a', 0.07, 0.03, 0.2, 50, scene='s2')]
    assert format_table(same).split('\n')[2] == '| d | m | 2.00 | **6.00** | 8.00 |'


def test_records_are_on_the_disk_before_they_replace_the_old_file(
    tmp_path: Path, monkeypatch
) -> None:
    # The temporary file was moved over the old one unsynced: a crash soon after could leave
    # an empty records file on ext4 / XFS.
    events: list[tuple[str, object]] = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd: int) -> None:
        events.append(('fsync', os.fstat(fd).st_ino))
        real_fsync(fd)

    def replace(src, dst) -> None:
        events.append(('replace', Path(dst).name))
        real_replace(src, dst)

    monkeypatch.setattr(records_module.os, 'fsync', fsync)
    monkeypatch.setattr(records_module.os, 'replace', replace)
    path = write_records([_rec('a', 0.05)], tmp_path / 'records.json')
    assert read_records(path) == [_rec('a', 0.05)]
    moved = events.index(('replace', 'records.json'))
    # The file now at ``path`` (same inode as the temporary one) was synced before the move,
    # the folder holding the rename after it.
    assert ('fsync', path.stat().st_ino) in events[:moved]
    assert ('fsync', tmp_path.stat().st_ino) in events[moved:]


# --- evaluation/scene.py ---------------------------------------------------------------------


class _ShortPatch:
    """A patch-mode method that returns one value too few."""

    def __call__(self, inputs):  # pragma: no cover - a subset run must not call it
        raise AssertionError('dense call in a pixel-subset run')

    def confidence_at(self, inputs, ys, xs):
        return np.full(len(ys) - 1, 0.5, dtype=np.float32)


def test_a_patch_method_returning_too_few_values_is_an_input_error() -> None:
    # Before: a bare numpy ValueError 'shape mismatch: value array of shape (29,) ...'.
    with pytest.raises(InputError, match="method 'net' must return one value per scored "
                                         'pixel, 30; got 29'):
        evaluate_scene(_shifted_sample(), 'census_bm', {'net': _ShortPatch()},
                       max_disparity=8, max_pixels=30)


def test_method_order_naming_a_method_not_given_is_an_input_error() -> None:
    from cva_confidence_ros.confidence import CONFIDENCE_METHODS

    methods = {'score': CONFIDENCE_METHODS.get('score')()}
    # Before: a bare KeyError 'scroe', after the matching had run.
    with pytest.raises(InputError, match=r"method_order names methods that are not given: "
                                         r"\['scroe'\]; given: \['score'\]"):
        evaluate_scene(_shifted_sample(), 'census_bm', methods, max_disparity=8,
                       method_order=['score', 'scroe'])


@pytest.mark.parametrize(
    ('max_pixels', 'seed', 'message'),
    [
        (float('nan'), 0, 'max_pixels must be an integer ≥ 1 or None; got nan'),
        (2.5, 0, 'max_pixels must be an integer ≥ 1 or None; got 2.5'),
        (True, 0, 'max_pixels must be an integer ≥ 1 or None; got True'),
        (2, 1.5, 'seed must be an integer ≥ 0; got 1.5'),
    ],
)
def test_select_pixels_refuses_a_size_or_seed_that_is_no_integer(
    max_pixels: object, seed: object, message: str
) -> None:
    # NaN passed every check and scored all 12 pixels; the others were numpy TypeErrors.
    known = np.ones((3, 4), dtype=bool)
    with pytest.raises(InputError, match=message):
        select_pixels(known, max_pixels, seed)  # type: ignore[arg-type]
    assert select_pixels(known, np.int64(2), np.int64(3))[0].size == 2


# --- evaluation/reliability.py ---------------------------------------------------------------


def test_pooling_tables_of_other_bins_names_the_matcher_and_method() -> None:
    confidence, correct = np.array([0.2, 0.9]), np.array([False, True])
    tables = {
        ('kitti2015', 'census_bm', 'cva_net'): reliability(confidence, correct),
        ('middlebury2014', 'census_bm', 'cva_net'): reliability(confidence, correct, bins=5),
    }
    # Before: 'cannot merge reliability tables of 10 and 5 bins', naming no row.
    with pytest.raises(InputError, match=r'census_bm cva_net .*bins differ \(kitti2015 10, '
                                         r'middlebury2014 5\)'):
        pooled(tables)


def test_a_calibration_row_without_pixels_is_named(tmp_path: Path) -> None:
    full = reliability(np.array([0.2, 0.9]), np.array([False, True]))
    empty = reliability(np.zeros(0), np.zeros(0, dtype=bool))
    tables = {('kitti2015', 'census_bm', 'cva_net'): full,
              ('kitti2015', 'census_sgm', 'lfn'): empty}
    # Before: 'the reliability table holds no pixels', of which of the rows not said.
    message = 'calibration of kitti2015 census_sgm lfn: the reliability table holds no pixels'
    with pytest.raises(InputError, match=message):
        format_calibration_table(tables)
    with pytest.raises(InputError, match=message):
        write_calibration(tables, tmp_path / 'out')
    assert not (tmp_path / 'out').exists()


def test_a_pipe_in_a_calibration_name_stays_in_its_cell() -> None:
    table = reliability(np.array([0.2, 0.9]), np.array([False, True]))
    text = format_calibration_table({('kitti2015', 'census_bm', 'my|net'): table})
    row = text.split('\n')[2]
    assert row.startswith('| kitti2015 | census_bm | my\\|net | 2 |')
    header = text.split('\n')[0]
    assert row.replace('\\|', '').count('|') == header.count('|')


# --- evaluation/table1.py (--reuse) ----------------------------------------------------------


def test_a_reuse_object_without_records_is_refused(tmp_path: Path) -> None:
    path = tmp_path / 'summary.json'
    path.write_text(json.dumps({'protocol': 'develop', 'cells': []}), encoding='utf-8')
    # Before: read as no records at all, so every scene was silently recomputed.
    with pytest.raises(DataError, match=r'--reuse .*summary.json: a JSON object without '
                                        r'"records"'):
        _load_reusable(path, ['pkrn'])
    path.write_text(json.dumps({'records': [_rec('pkrn', 0.1).as_dict()]}), encoding='utf-8')
    assert list(_load_reusable(path, ['pkrn'])) == [('d', 's1', 'm')]


def test_a_bad_reuse_record_names_the_file_and_its_index(tmp_path: Path) -> None:
    path = tmp_path / 'reuse.json'
    good = _rec('pkrn', 0.1).as_dict()
    path.write_text(json.dumps([good, {**good, 'auc': 2.0}]), encoding='utf-8')
    # Before: 'evaluation record d/s1 pkrn: auc must be ...', no file, no index.
    with pytest.raises(InputError, match=r'--reuse .*reuse.json: record 1: .*auc must be a '
                                         r'number in \[0, 1\]; got 2.0'):
        _load_reusable(path, ['pkrn'])


def test_two_different_reuse_records_of_one_scene_are_refused(tmp_path: Path) -> None:
    path = tmp_path / 'reuse.json'
    first, second = _rec('pkrn', 0.1).as_dict(), _rec('pkrn', 0.2).as_dict()
    path.write_text(json.dumps([first, second]), encoding='utf-8')
    # Before: the later one silently took the earlier one's place.
    with pytest.raises(InputError, match=r'record 1: a second, different record of d/s1 m '
                                         r'pkrn: auc 0.1 and 0.2'):
        _load_reusable(path, ['pkrn'])
    path.write_text(json.dumps([first, first]), encoding='utf-8')  # the same twice: one
    assert _load_reusable(path, ['pkrn']) == {('d', 's1', 'm'): {'pkrn': first}}

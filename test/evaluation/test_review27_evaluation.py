"""Regression tests of a review of the calibration, plot and evaluation-record modules."""

from __future__ import annotations

import json

from matplotlib.image import imread
import numpy as np
import pytest

from cva_confidence_ros.calibration import ReliabilityTable, expected_error, reliability
from cva_confidence_ros.errors import DataError, InputError
from cva_confidence_ros.evaluation.records import EvalRecord, read_records, write_records
from cva_confidence_ros.evaluation.reliability import pooled, write_calibration
from cva_confidence_ros.evaluation.table1 import _load_reusable
from cva_confidence_ros.plots import save_correctness_overlay, save_roc_curves


def _record(**values: object) -> dict[str, object]:
    item: dict[str, object] = {
        'dataset': 'kitti2015', 'scene': '000001', 'matcher': 'census_bm', 'method': 'pkrn',
        'auc': 0.1, 'auc_opt': 0.01, 'error_rate': 0.2, 'n_pixels': 100,
    }
    item.update(values)
    return item


def test_a_confidence_on_a_bin_edge_opens_that_bin() -> None:
    # int(15/22 · 22) = int(14.999999999999998) = 14 put the edge into the bin below.
    confidence = np.array([15 / 22, 0.1, 0.99])
    table = reliability(confidence, np.array([True, False, True]), bins=22)
    assert table.counts[15] == 1 and table.counts[14] == 0
    predicted = 1 - (15 / 22 + 0.99) / 2
    assert table.kept_at(15 / 22) == (pytest.approx(2 / 3), 0.0, pytest.approx(predicted))
    for bins in (10, 22, 49):
        edges = reliability(np.zeros(1), np.ones(1, dtype=bool), bins=bins).edges
        assert edges.tolist() == [k / bins for k in range(bins + 1)]


def test_kept_at_one_is_refused_as_the_last_bin_holds_the_ones() -> None:
    # Both pixels have confidence ≥ 1, yet the table answered "none kept".
    table = reliability(np.array([1.0, 1.0]), np.array([True, False]))
    with pytest.raises(InputError, match='threshold 1 cannot be answered.*≤ 0.9'):
        table.kept_at(1.0)
    assert table.kept_at(0.9) == (1.0, 0.5, 0.0)


def _table_dict(**changes: object) -> dict[str, object]:
    item = reliability(np.array([0.15, 0.95, 0.9]), np.array([False, True, True]), bins=2)
    data = item.as_dict()
    bins = dict(data['bins'])
    for key, value in changes.items():
        if key == 'brier':
            data['brier'] = value
        else:
            bins[key] = value
    data['bins'] = bins
    return data


@pytest.mark.parametrize(
    ('changes', 'message'),
    [
        ({'counts': [2.5, 2]}, r'counts\[0\] must be a whole number ≥ 0; got 2.5'),
        ({'counts': [-1, 2]}, r'counts\[0\] must be a whole number ≥ 0; got -1'),
        ({'counts': ['1', 2]}, r"counts\[0\] must be a whole number ≥ 0; got '1'"),
        ({'counts': [True, 2]}, r'counts\[0\] must be a whole number ≥ 0; got True'),
        ({'mean_confidence': [5.0, 0.925]}, r'mean_confidence\[0\] of 1 pixels .*got 5.0'),
        ({'accuracy': [None, 1.0]}, r'accuracy\[0\] of 1 pixels .*got None'),
        ({'accuracy': [float('nan'), 1.0]}, r'accuracy\[0\] of 1 pixels .*got nan'),
        ({'brier': float('nan')}, 'brier must be a number in'),
        ({'brier': -0.5}, 'brier must be a number in'),
        (
            {'counts': [[1, 2]], 'mean_confidence': [[0.1, 0.9]], 'accuracy': [[0.0, 1.0]]},
            r'counts\[0\] must be a whole number',
        ),
    ],
)
def test_from_dict_refuses_what_as_dict_cannot_have_written(changes, message) -> None:
    with pytest.raises(InputError, match=f'not a reliability table: .*{message}'):
        ReliabilityTable.from_dict(_table_dict(**changes))


def test_from_dict_still_reads_empty_bins() -> None:
    written = _table_dict(counts=[0, 3], mean_confidence=[None, 0.6667], accuracy=[None, 2 / 3])
    data = json.loads(json.dumps(written))
    table = ReliabilityTable.from_dict(data)
    assert table.counts.tolist() == [0, 3]
    assert table.ece == pytest.approx(abs(0.6667 - 2 / 3))


def test_reliability_refuses_labels_of_a_transposed_shape() -> None:
    confidence = np.linspace(0.0, 1.0, 6).reshape(2, 3)
    correct = confidence > 0.5
    with pytest.raises(InputError, match=r'same shape; got \(2, 3\) and \(3, 2\)'):
        reliability(confidence, correct.T.copy())
    flat = reliability(confidence, correct.ravel())
    fortran = reliability(np.asfortranarray(confidence), np.asfortranarray(correct))
    assert flat.correct_sums.tolist() == fortran.correct_sums.tolist()
    assert flat.correct_sums.sum() == 3


def test_a_confidence_that_is_no_number_is_an_input_error() -> None:
    with pytest.raises(InputError, match='confidence must be a numeric array; got dtype <U'):
        reliability(np.array(['0.5']), np.array([True]))
    with pytest.raises(InputError, match='confidence must be a numeric array; got dtype object'):
        expected_error([0.1, None])
    assert expected_error(np.array([0.25, 0.75], dtype=np.float16)) == 0.5


def test_a_record_that_cannot_be_read_back_is_neither_made_nor_written(tmp_path) -> None:
    path = tmp_path / 'records.json'
    write_records([_record()], path)
    before = path.read_text(encoding='utf-8')
    # Made directly, a NaN AUC used to be written as a bare NaN that read_records refuses.
    with pytest.raises(InputError, match='000001 pkrn: auc must be a number in .*got nan'):
        write_records([EvalRecord(**_record(auc=float('nan')))], path)
    with pytest.raises(InputError, match='n_pixels must be a whole number ≥ 1; got 0'):
        write_records([_record(), _record(n_pixels=0)], path)
    assert path.read_text(encoding='utf-8') == before
    assert read_records(path) == [EvalRecord.from_mapping(_record())]


def test_numpy_scalars_in_a_record_are_written_as_json_numbers(tmp_path) -> None:
    values = np.float32(0.25), np.float64(0.125), np.float32(0.5), np.int64(7)
    record = EvalRecord('d', 's', 'm', 'a', *values)
    path = write_records([record], tmp_path / 'r.json')
    item = json.loads(path.read_text(encoding='utf-8'))[0]
    assert item['auc'] == 0.25 and item['n_pixels'] == 7 and type(item['n_pixels']) is int
    assert read_records(path) == [record]


@pytest.mark.parametrize(
    ('key', 'value', 'message'),
    [
        ('dataset', None, 'dataset must be a string; got None'),
        ('method', ['cva_net'], r"method must be a string; got \['cva_net'\]"),
        ('auc', '0.5', r'auc must be a number in .*got 0.5 \(a str\)'),
        ('auc_opt', True, r'auc_opt must be a number in .*got True \(a bool\)'),
        ('n_pixels', '7', "n_pixels must be a whole number ≥ 1; got '7'"),
        ('auc', 10**400, 'auc must be a number in'),
        ('n_pixels', 10**400, 'n_pixels must be a whole number ≥ 1'),
    ],
)
def test_from_mapping_refuses_values_of_the_wrong_type(key, value, message) -> None:
    with pytest.raises(InputError, match=message):
        EvalRecord.from_mapping(_record(**{key: value}))


def test_read_records_names_the_file_and_the_record(tmp_path) -> None:
    path = tmp_path / 'records.json'
    path.write_text(json.dumps([_record(), _record(auc=1.5)]), encoding='utf-8')
    with pytest.raises(InputError, match=r'records.json: record 1: .*auc must be .*got 1.5'):
        read_records(path)


@pytest.mark.parametrize('text', ['[' * 100_000, '[' + '1' * 5000 + ']'])
def test_a_records_file_too_deep_or_with_a_huge_number_is_a_data_error(tmp_path, text) -> None:
    path = tmp_path / 'records.json'
    path.write_text(text, encoding='utf-8')
    with pytest.raises(DataError, match='cannot read evaluation records from .*records.json'):
        read_records(path)


@pytest.mark.filterwarnings('error')
def test_correctness_overlay_draws_a_nan_image_black_without_warnings(tmp_path) -> None:
    image = np.array([[np.nan, 0.5], [1.0, np.inf]])
    confidence = np.full((2, 2), 0.9)
    mask = np.zeros((2, 2), dtype=bool)
    path = save_correctness_overlay(confidence, np.zeros((2, 2), dtype=bool),
                                    tmp_path / 'o.png', image=image, mask=mask)
    gray = np.round(imread(path)[..., 0] * 255.0).astype(int)
    assert gray.tolist() == [[0, 63], [127, 0]]
    all_nan = save_correctness_overlay(confidence, np.zeros((2, 2), dtype=bool),
                                       tmp_path / 'n.png', image=np.full((2, 2), np.nan))
    assert imread(all_nan).shape[:2] == (2, 2)


@pytest.mark.filterwarnings('error')
def test_an_roc_figure_without_curves_does_not_warn(tmp_path) -> None:
    path = save_roc_curves({}, tmp_path / 'roc.png', title='nothing scored')
    assert imread(path).shape[0] > 100


def test_write_calibration_writes_nothing_when_the_table_fails(tmp_path) -> None:
    # 0.8 is no edge of 4 bins: the JSON used to be written before the Markdown table failed.
    table = reliability(np.array([0.2, 0.9, 0.6]), np.array([False, True, True]), bins=4)
    with pytest.raises(InputError, match='bin edge .*got 0.8'):
        write_calibration({('kitti2015', 'census_bm', 'cva_net'): table}, tmp_path / 'out')
    assert not (tmp_path / 'out').exists()


def test_pooled_refuses_a_data_set_named_all() -> None:
    # Its own row used to be replaced by the rows pooled over all data sets.
    one = reliability(np.array([0.2, 0.9]), np.array([False, True]))
    tables = {('all', 'census_bm', 'cva_net'): one, ('kitti2015', 'census_bm', 'cva_net'): one}
    with pytest.raises(InputError, match="data set named 'all' cannot be pooled"):
        pooled(tables)
    alone = ('all', 'census_bm', 'cva_net')
    assert list(pooled({alone: one})) == [alone]


def test_a_records_file_that_cannot_be_written_leaves_the_old_one(
    tmp_path, file_size_limit
) -> None:
    path = tmp_path / 'records.json'
    write_records([_record()], path)
    before = path.read_bytes()
    many = [_record(scene=f'{index:06d}') for index in range(200)]
    # Before: the old file was truncated to what fitted, and an OSError came out.
    with pytest.raises(DataError, match='cannot write records .*the file there was left as'):
        with file_size_limit(len(before) + 1000):
            write_records(many, path)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ['records.json']
    assert len(read_records(write_records(many, path))) == 200


@pytest.mark.parametrize('text', ['[' * 100_000, '[' + '1' * 5000 + ']'])
def test_a_reuse_file_too_deep_or_with_a_huge_number_is_a_data_error(tmp_path, text) -> None:
    path = tmp_path / 'reuse.json'
    path.write_text(text, encoding='utf-8')
    # Before: a RecursionError / ValueError traceback out of cva-table1 --reuse.
    with pytest.raises(DataError, match='cannot read --reuse records .*reuse.json'):
        _load_reusable(path, ['pkrn'])

"""Tests of the evaluation records: JSON keys and the Table-1 Markdown layout."""

from __future__ import annotations

import json

import pytest

from cva_confidence_ros.errors import DataError, InputError
from cva_confidence_ros.evaluation import RECORD_KEYS, EvalRecord, format_table
from cva_confidence_ros.evaluation.records import read_records, write_records


def _rec(dataset, scene, matcher, method, auc, auc_opt=0.01) -> EvalRecord:
    return EvalRecord(dataset, scene, matcher, method, auc, auc_opt, 0.1, 100)


def _rows(table: str) -> list[list[str]]:
    lines = table.strip().split('\n')
    return [[cell.strip() for cell in line.strip('|').split('|')] for line in lines]


def test_table_averages_scenes_bolds_best_and_keeps_order() -> None:
    records = [
        _rec('kitti2015', 's1', 'census_sgm', 'pkrn', 0.030, 0.010),
        _rec('kitti2015', 's1', 'census_sgm', 'cva_net', 0.020, 0.010),
        _rec('kitti2015', 's2', 'census_sgm', 'pkrn', 0.050, 0.020),
        _rec('kitti2015', 's2', 'census_sgm', 'cva_net', 0.070, 0.020),
        _rec('kitti2015', 's1', 'census_bm', 'pkrn', 0.100, 0.090),
        _rec('kitti2015', 's1', 'census_bm', 'cva_net', 0.110, 0.090),
    ]
    rows = _rows(format_table(records))
    assert rows[0] == ['data set', 'matcher', 'Opt.', 'pkrn', 'cva_net']
    assert rows[1] == [':---', ':---', '---:', '---:', '---:']
    # (0.03 + 0.05) / 2 = 4.00 vs (0.02 + 0.07) / 2 = 4.50; Opt (0.01 + 0.02) / 2 = 1.50.
    assert rows[2] == ['kitti2015', 'census_sgm', '1.50', '**4.00**', '4.50']
    assert rows[3] == ['kitti2015', 'census_bm', '9.00', '**10.00**', '11.00']
    assert len(rows) == 4


def test_table_opt_counts_each_scene_once() -> None:
    # Two methods on s1 (opt 0.01) and one on s2 (opt 0.04): mean over scenes = 2.5, not 2.0.
    records = [
        _rec('d', 's1', 'm', 'a', 0.05, 0.01),
        _rec('d', 's1', 'm', 'b', 0.05, 0.01),
        _rec('d', 's2', 'm', 'a', 0.05, 0.04),
    ]
    assert _rows(format_table(records))[2][2] == '2.50'


def test_table_ties_and_missing_methods_and_column_order() -> None:
    records = [
        _rec('middlebury2014', 'A', 'mccnn_fast', 'lrd', 0.04001),
        _rec('middlebury2014', 'A', 'mccnn_fast', 'mlm', 0.04002),
    ]
    rows = _rows(format_table(records, methods=['mlm', 'cva_net', 'lrd'], decimals=2))
    assert rows[0][3:] == ['mlm', 'cva_net', 'lrd']
    assert rows[2][3:] == ['**4.00**', '–', '**4.00**']


def test_table_of_dicts_and_empty_input() -> None:
    record = _rec('d', 's', 'm', 'a', 0.123456).as_dict()
    assert _rows(format_table([record], decimals=3))[2] == ['d', 'm', '1.000', '**12.346**']
    assert format_table([]).count('\n') == 2


def test_json_round_trip_has_exactly_the_keys(tmp_path) -> None:
    records = [_rec('d', 's', 'm', 'a', 0.1), _rec('d', 's', 'm', 'b', 0.2)]
    path = write_records(records, tmp_path / 'x' / 'r.json')
    items = json.loads(path.read_text())
    assert [list(item) for item in items] == [list(RECORD_KEYS)] * 2
    assert items[1]['method'] == 'b' and items[1]['n_pixels'] == 100
    assert read_records(path) == records


def test_bad_records_are_rejected(tmp_path) -> None:
    with pytest.raises(InputError, match='lacks keys'):
        format_table([{'dataset': 'd'}])
    bad = tmp_path / 'bad.json'
    bad.write_text('{"a": 1}')
    with pytest.raises(DataError, match='JSON list'):
        read_records(bad)


def test_a_binary_records_file_is_a_data_error(tmp_path) -> None:
    binary = tmp_path / 'records.json'
    binary.write_bytes(b'\xff\xfe\x00\x89PNG')
    with pytest.raises(DataError, match='cannot read evaluation records from .*records.json'):
        read_records(binary)


@pytest.mark.parametrize(
    ('key', 'value', 'message'),
    [
        ('auc', float('nan'), 'auc must be a number in \\[0, 1\\]; got nan'),
        ('auc_opt', 1.5, 'auc_opt must be a number in \\[0, 1\\]; got 1.5'),
        ('error_rate', -0.1, 'error_rate must be a number in \\[0, 1\\]'),
        ('n_pixels', 12.5, 'n_pixels must be a whole number ≥ 1; got 12.5'),
        ('n_pixels', 0, 'n_pixels must be a whole number ≥ 1; got 0'),
        ('n_pixels', True, 'n_pixels must be a whole number ≥ 1; got True'),
    ],
)
def test_a_record_with_an_impossible_value_is_named(key: str, value: object, message: str) -> None:
    # A NaN AUC used to pass and turn its table cells into nan; 12.5 pixels became 12.
    item = {**_rec('kitti2015', '000001', 'census_bm', 'pkrn', 0.1).as_dict(), key: value}
    with pytest.raises(InputError, match=f'kitti2015/000001 pkrn: {message}'):
        EvalRecord.from_mapping(item)
    whole = {**item, key: 100.0} if key == 'n_pixels' else {**item, key: 0.25}
    assert EvalRecord.from_mapping(whole).as_dict()[key] == whole[key]

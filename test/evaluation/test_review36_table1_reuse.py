"""``cva-table1 --reuse`` refuses records scored with other weights: their pixels and error
rate agree with a scene scored again, only the AUC tells them apart."""

from __future__ import annotations

import json

import pytest
from test_review35_at_scale import D, _middlebury, _restore_threads  # noqa: F401 (fixture)


def _base(tmp_path, methods: str) -> list[str]:
    root = _middlebury(tmp_path / 'data', 2)
    return ['--data-root', str(root), '--matchers', 'census_bm', '--methods', methods,
            '--max-disparity', str(D), '--max-pixels', '100', '--protocol', 'develop',
            '--threads', '1', '--out', str(tmp_path / 'out')]


def _tamper(path, method: str) -> None:
    """Shift one method's AUC everywhere, as records of other weights would be."""
    summary = json.loads(path.read_text())
    for record in summary['records']:
        if record['method'] == method:
            record['auc'] += 0.01
    path.write_text(json.dumps(summary))


@pytest.mark.usefixtures('_restore_threads')
def test_reuse_refuses_records_of_a_whole_scene_with_another_auc(tmp_path, capsys):
    from cva_confidence_ros.evaluation.table1 import main as table1

    base = _base(tmp_path, 'pkrn')
    assert table1(base) == 0
    held = tmp_path / 'held.json'
    held.write_text((tmp_path / 'out' / 'table1.json').read_text())
    _tamper(held, 'pkrn')
    assert table1([*base, '--reuse', str(held)]) == 2
    assert 'pkrn has AUC 0.1' in capsys.readouterr().err
    # The file as written is taken over.
    held.write_text((tmp_path / 'out' / 'table1.json').read_text())
    assert table1([*base, '--reuse', str(held)]) == 0
    records = json.loads((tmp_path / 'out' / 'table1.json').read_text())['records']
    assert [r.get('reused', False) for r in records] == [True, True]


@pytest.mark.usefixtures('_restore_threads')
def test_a_partly_held_scene_does_not_stand_for_the_check(tmp_path, capsys):
    from cva_confidence_ros.evaluation.table1 import main as table1

    base = _base(tmp_path, 'pkrn,mlm')
    assert table1(base) == 0
    summary = json.loads((tmp_path / 'out' / 'table1.json').read_text())
    # S0 without its MLM record (only PKRN's pixels can be checked there); S1 held in full,
    # with PKRN's AUC of other weights.
    records = [r for r in summary['records'] if (r['scene'], r['method']) != ('S0', 'mlm')]
    for record in records:
        if (record['scene'], record['method']) == ('S1', 'pkrn'):
            record['auc'] += 0.01
    held = tmp_path / 'held.json'
    held.write_text(json.dumps(records))
    # Before: S0's pixel check counted as the check and S1 was taken over as it was.
    assert table1([*base, '--reuse', str(held)]) == 2
    assert 'S1 census_bm pkrn has AUC' in capsys.readouterr().err

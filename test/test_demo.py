"""``cva-demo`` end to end on the embedded Motorcycle pair (fast methods only)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from cva_confidence_ros.demo import main


@pytest.mark.timeout(300)
def test_demo_matches_bags_and_replays(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / 'demo'
    code = main([
        '--out', str(out), '--matchers', 'census_bm', '--methods', 'pkrn,score',
        '--downsample', '4',
    ])
    assert code == 0
    printed = capsys.readouterr().out
    assert '| census_bm | pkrn |' in printed and '| census_bm | score |' in printed
    summary = json.loads((out / 'cost_volume_summary.json').read_text())
    assert {row['matcher'] for row in summary} == {'census_bm', 'census_sgm', 'mccnn_fast'}
    for row in summary:
        assert 0.0 <= row['cost_min'] <= row['cost_mean'] <= row['cost_max'] <= 1.0
        assert 0.0 < row['error_rate'] < 0.6
        assert Path(row['png']).stat().st_size > 0
    report = json.loads((out / 'replay' / 'census_bm__pkrn' / 'report.json').read_text())
    assert len(report['frames']) == 1
    assert report['summary']['auc'] >= report['summary']['auc_opt'] > 0
    assert (out / 'motorcycle_bag').is_dir()

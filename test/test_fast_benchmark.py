"""``cva-benchmark --suite fast``: records with the issue's keys, on a tiny frame."""

from __future__ import annotations

import json

import pytest
import torch

from cva_confidence_ros.benchmark import RECORD_KEYS, BenchSettings, main
from cva_confidence_ros.fast_benchmark import FAST_CONFIGS, format_fast_table, run_fast


@pytest.fixture(autouse=True)
def _one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def test_rows_have_the_record_keys():
    by_name = {c.name: c for c in FAST_CONFIGS}
    configs = [by_name[n] for n in ('exact', 'stride8+pkrn0.25', 'pipeline:stride8')]
    records = run_fast(
        BenchSettings(80, 8, 64, 1), configs, crop=4, log=lambda _text: None, gemm_size=256
    )
    assert [r['config'] for r in records] == [c.name for c in configs]
    for record in records:
        assert set(RECORD_KEYS) <= set(record)
        assert record['ms_per_frame'] > 0 and record['network_gflops'] > 0
        assert record['auc_rel'] is None  # no data root
        assert (record['width'], record['height'], record['max_disparity']) == (80, 8, 64)
    assert records[0]['extrapolated'] is True
    assert 0 < records[1]['network_share'] < 0.1
    assert 'matching' in records[2]['stages_ms']
    assert 'stride8+pkrn0.25' in format_fast_table(records)


def test_cli_rejects_unknown_rows(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(['--suite', 'fast', '--configs', 'stride3', '--json', str(tmp_path / 'a.json')])
    assert exit_info.value.code == 2
    assert 'stride3' in capsys.readouterr().err


def test_cli_writes_json(tmp_path):
    out = tmp_path / 'fast.json'
    code = main(['--suite', 'fast', '--width', '80', '--height', '8', '--configs', 'stride8',
                 '--json', str(out)])
    assert code == 0
    rows = json.loads(out.read_text())
    assert rows[0]['config'] == 'stride8' and set(RECORD_KEYS) <= set(rows[0])

"""``cva-benchmark --suite gpu``: the rows, their keys and the table, run on the CPU (the smoke
path; the GPU numbers in the README come from the same code with ``--device cuda``)."""

from __future__ import annotations

import json

import pytest

from cva_confidence_ros.benchmark import RECORD_KEYS, BenchSettings, main
from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.gpu_benchmark import format_gpu_table, run_gpu

pytestmark = pytest.mark.usefixtures('one_torch_thread')


def test_rows_per_network_and_precision():
    records = run_gpu(BenchSettings(40, 8, 16, 1), ['lite', 'fast'], ['fp32', 'bf16'],
                      device='cpu', warmup=1, log=lambda _text: None)
    assert [r['config'] for r in records] == ['lite:fp32', 'lite:bf16', 'fast:fp32', 'fast:bf16']
    for record in records:
        assert set(RECORD_KEYS) <= set(record)
        assert record['ms_per_frame'] > 0 and record['gpu_ms'] > 0
        assert record['network_gflops'] > 0 and record['gemm_gflops'] > 0
        assert record['auc_rel'] is None  # no data root
        assert record['peak_mem_mb'] is None  # CUDA memory only
        assert (record['width'], record['height'], record['max_disparity']) == (40, 8, 16)
        # No shipped weights at D = 16: the row says why its numbers are speed only.
        assert 'random init' in record['note']
    table = format_gpu_table(records)
    assert 'fast:bf16' in table and 'cpu, 40×8, D = 16' in table


def test_bad_rows_are_refused():
    settings = BenchSettings(40, 8, 16, 1)
    with pytest.raises(ConfigError, match='fp16 needs a CUDA device'):
        run_gpu(settings, ['fast'], ['fp16'], device='cpu')
    with pytest.raises(ConfigError, match="unknown networks \\['resnet'\\]"):
        run_gpu(settings, ['resnet'], ['fp32'], device='cpu')
    with pytest.raises(ConfigError, match='warmup must be ≥ 0 untimed frames; got -3'):
        run_gpu(settings, ['fast'], ['fp32'], device='cpu', warmup=-3)


def test_cli_writes_json(tmp_path):
    out = tmp_path / 'gpu.json'
    argv = ['--suite', 'gpu', '--device', 'cpu', '--width', '40', '--height', '8',
            '--max-disparity', '16', '--repeat', '1', '--warmup', '1', '--networks', 'fast',
            '--precisions', 'fp32', '--json', str(out)]
    assert main(argv) == 0
    (row,) = json.loads(out.read_text())
    assert row['config'] == 'fast:fp32' and set(RECORD_KEYS) <= set(row)
    assert row['precision'] == 'fp32' and row['arch'] == 'cvanet_fast'


def test_a_cpu_smoke_run_leaves_fp16_out_by_default(tmp_path):
    # The README's smoke test (--device cpu, no --precisions) stopped at once: 'fp16 needs a
    # CUDA device'. An explicit fp16 on a CPU is still refused (test_bad_rows_are_refused).
    out = tmp_path / 'gpu.json'
    argv = ['--suite', 'gpu', '--device', 'cpu', '--width', '40', '--height', '8',
            '--max-disparity', '16', '--repeat', '1', '--warmup', '0', '--networks', 'fast',
            '--no-channels-last', '--json', str(out)]
    assert main(argv) == 0
    assert [row['config'] for row in json.loads(out.read_text())] == ['fast:fp32', 'fast:bf16']

"""Regressions found in a review of the benchmark suites (cva-benchmark and its suites)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
import resource
import sys
from typing import Any

import pytest

from cva_confidence_ros import benchmark, gpu_benchmark

_COMMON = {'device': 'cpu', 'width': 64, 'height': 48, 'max_disparity': 16}


def test_matcher_table_shows_a_dash_for_an_unknown_peak() -> None:
    # run_network gives peak_mem_mb None where /proc/self/status or clear_refs cannot be used;
    # the table used to fail on it (TypeError) after every row had been measured.
    records = [
        {**_COMMON, 'config': 'opencv_sgbm', 'ms_per_frame': 10.0, 'peak_mem_mb': 2.0},
        {**_COMMON, 'config': 'cvanet_d16', 'ms_per_frame': 900.0, 'peak_mem_mb': None,
         'network_gflops': 5.0, 'gemm_gflops': 10.0, 'crop': [8, 8]},
    ]
    table = benchmark.format_table(records, threads=2)
    row = next(line for line in table.splitlines() if line.startswith('cvanet_d16'))
    assert row.split()[-1] == '—'
    sgbm = next(line for line in table.splitlines() if line.startswith('opencv_sgbm'))
    assert sgbm.split()[-1] == '2.0'


def _suite_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog='suite')
    for option, default in (('--width', 64), ('--height', 48), ('--max-disparity', 16),
                            ('--repeat', 1)):
        parser.add_argument(option, type=int, default=default)
    parser.add_argument('--json', type=Path, default=None)
    return parser


def test_suite_records_are_saved_before_the_table_is_printed(tmp_path: Path) -> None:
    out = tmp_path / 'suite.json'
    record = {**_COMMON, 'config': 'row', 'ms_per_frame': 3.0, 'peak_mem_mb': None}

    def measure(_args: argparse.Namespace, _settings: Any) -> list[dict[str, Any]]:
        return [dict(record)]

    def table(_records: list[dict[str, Any]]) -> str:
        raise BrokenPipeError('stdout closed')  # e.g. `cva-benchmark … | head -1`

    with pytest.raises(BrokenPipeError):
        benchmark.run_suite(_suite_parser(), ['--json', str(out)], measure, table)
    (row,) = json.loads(out.read_text())
    assert row['config'] == 'row' and row['ms_per_frame'] == 3.0


def test_max_rss_is_in_kilobytes_on_every_platform(monkeypatch: pytest.MonkeyPatch) -> None:
    # ru_maxrss is in kB on Linux but in bytes on macOS.
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    linux = benchmark._max_rss_kb()
    monkeypatch.setattr(sys, 'platform', 'darwin')
    darwin = benchmark._max_rss_kb()
    after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    monkeypatch.undo()
    if sys.platform.startswith('linux'):
        assert before <= linux <= after
    assert before // 1024 <= darwin <= after // 1024


def test_gpu_auc_rel_does_not_depend_on_the_row_order() -> None:
    # The reference row used to be picked up only when it came first: `--networks fast exact`
    # or `--precisions bf16 fp32` left auc_rel empty in the rows measured before it.
    records: list[dict[str, Any]] = [
        {'config': 'fast:fp32', 'auc': 0.02, 'auc_rel': None},
        {'config': 'exact:bf16', 'auc': 0.041, 'auc_rel': None},
        {'config': 'exact:fp32', 'auc': 0.04, 'auc_rel': None},
        {'config': 'lite:fp32', 'auc': None, 'auc_rel': None, 'note': 'random init'},
    ]
    assert gpu_benchmark._fill_auc_rel(records)
    assert [r['auc_rel'] for r in records] == pytest.approx([0.5, 1.025, 1.0, None])


def test_gpu_auc_rel_without_its_reference_row_says_so() -> None:
    records: list[dict[str, Any]] = [{'config': 'fast:fp32', 'auc': 0.02, 'auc_rel': None}]
    assert not gpu_benchmark._fill_auc_rel(records)
    assert records[0]['auc_rel'] is None

"""Review 36: every JSON file the package writes is strict JSON (NaN / inf as null).

``json.dumps`` writes a NaN or infinite float as ``NaN`` / ``Infinity``, which jq,
JavaScript's ``JSON.parse`` and Go refuse; the writers share ``cva_confidence_ros.strict_json``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest


def _strict(text: str) -> Any:
    """``json.loads`` that refuses ``NaN``, ``Infinity`` and ``-Infinity`` as a strict parser
    does."""

    def refuse(token: str) -> None:
        raise ValueError(f'not JSON: {token}')

    return json.loads(text, parse_constant=refuse)


def test_json_ready_nulls_non_finite_values_and_plain_numpy() -> None:
    from cva_confidence_ros.strict_json import dumps, json_ready

    value = {
        'nan': float('nan'), 'inf': np.float32('inf'), 'int': np.int64(7),
        'ok': np.float32(0.5), 'nested': ({'x': -math.inf}, [np.nan, 1.0]),
        'array': np.array([np.nan, 2.0]), 'flag': np.bool_(True), 'name': 'a',
    }  # fmt: skip
    expected = {
        'nan': None, 'inf': None, 'int': 7, 'ok': 0.5, 'nested': [{'x': None}, [None, 1.0]],
        'array': [None, 2.0], 'flag': True, 'name': 'a',
    }  # fmt: skip
    assert json_ready(value) == expected
    assert _strict(dumps(value)) == expected


def test_replay_report_is_strict_json_with_a_non_finite_config_value(tmp_path: Path) -> None:
    # The config block went to json.dumps as it came: an infinite value was written as
    # Infinity (the frames and the summary were cleaned, the config not).
    from msg_tools.scoring import FrameScore, ReplayReport, ReportWriter

    report = ReplayReport(
        frames=[FrameScore(frame=0, stamp_ns=1, kept_fraction=0.5, note='no ground truth')],
        config={'bag': 'in', 'sync_tolerance_s': math.inf, 'scale': np.float32('nan')},
    )
    paths = ReportWriter(tmp_path / 'report', max_plots=0).write(report)
    document = _strict(paths['json'].read_text(encoding='utf-8'))
    assert document['config'] == {'bag': 'in', 'sync_tolerance_s': None, 'scale': None}
    assert document['frames'][0]['auc'] is None


def test_node_benchmark_json_is_strict(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    # cva-benchmark --suite node wrote its rows with plain json.dumps, unlike the other
    # suites: an infinite rate was Infinity, a numpy value a TypeError after the whole run.
    from cva_confidence_ros import node_benchmark

    record = {
        'config': 'node:census_bm+pkrn', 'device': 'cpu', 'width': 64, 'height': 48,
        'max_disparity': 16, 'ms_per_frame': 12.5, 'peak_mem_mb': np.float64(80.0),
        'network_gflops': None, 'gemm_gflops': None, 'auc_rel': None,
        'burst_output_hz': math.inf, 'stages_ms': {'confidence': math.nan},
    }  # fmt: skip
    monkeypatch.setattr(node_benchmark, 'run_suite', lambda *args, **kwargs: [record])
    monkeypatch.setattr(node_benchmark, 'format_table', lambda records, threads: 'table')
    monkeypatch.setattr(node_benchmark, 'host_summary', lambda: 'host')
    out = tmp_path / 'node.json'
    assert node_benchmark.main(['--json', str(out)]) == 0
    capsys.readouterr()
    (row,) = _strict(out.read_text(encoding='utf-8'))
    assert row['burst_output_hz'] is None and row['stages_ms'] == {'confidence': None}
    assert row['peak_mem_mb'] == 80.0 and row['host'] == 'host'


def test_benchmark_records_take_numpy_integers(tmp_path: Path) -> None:
    # write_records' own cleaner turned numpy floats into floats but left np.int64, which
    # json.dumps refuses (TypeError) after every row was measured.
    from cva_confidence_ros.benchmark import RECORD_KEYS, write_records

    record: dict[str, Any] = dict.fromkeys(RECORD_KEYS)
    record.update(config='x', width=np.int64(64), ms_per_frame=np.float32(np.inf))
    path = tmp_path / 'bench.json'
    write_records(path, [record], host='host')
    (row,) = _strict(path.read_text(encoding='utf-8'))
    assert row['width'] == 64 and row['ms_per_frame'] is None


def test_training_history_is_strict_json(tmp_path: Path) -> None:
    # history.json went to json.dumps as it came: a NaN loss or AUC was written as NaN.
    from cva_confidence_ros.training.trainer import _write_history

    history = [{'epoch': 1, 'train_loss': math.nan, 'val_auc': np.float32(0.25),
                'samples_per_s': math.inf}]
    _write_history(tmp_path, history)
    (record,) = _strict((tmp_path / 'history.json').read_text(encoding='utf-8'))
    assert record == {'epoch': 1, 'train_loss': None, 'val_auc': 0.25, 'samples_per_s': None}


def test_demo_summary_is_strict_json(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # The demo's cost_volume_summary.json: a pair without known ground truth gave an error
    # rate of NaN (a mean over no pixels), written as NaN.
    from cva_confidence_ros import datasets, demo
    from cva_confidence_ros.datasets.synthetic import synthetic_pair

    sample = synthetic_pair(1, 24, 40, max_disparity=8)
    sample.disparity[...] = np.nan

    monkeypatch.setattr(datasets, 'load_scene', lambda *args, **kwargs: sample)
    with np.errstate(all='ignore'), pytest.warns(RuntimeWarning):
        rows = demo._match_all(tmp_path, ['census_bm'], 8, 1)
    assert math.isnan(float(rows[0]['error_rate']))  # type: ignore[arg-type]
    (row,) = _strict((tmp_path / 'cost_volume_summary.json').read_text(encoding='utf-8'))
    assert row['error_rate'] is None and row['matcher'] == 'census_bm'

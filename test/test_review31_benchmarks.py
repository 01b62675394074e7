"""Regressions found in the second review of the benchmark suites (cva-benchmark, its suites)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from cva_confidence_ros import benchmark, gpu_benchmark
from cva_confidence_ros.benchmark import BenchSettings


def _refuse_constant(name: str) -> Any:
    raise ValueError(f'not JSON: {name}')


def test_json_records_are_strict_json_without_nan(tmp_path: Path) -> None:
    # json.dumps wrote NaN / Infinity (no JSON tokens: strict readers refuse the file) for an
    # AUC ratio over a zero reference or a rate over no time, and numpy floats failed.
    out = tmp_path / 'bench.json'
    record = {
        'config': 'row', 'device': 'cpu', 'width': 40, 'height': 8, 'max_disparity': 16,
        'ms_per_frame': 2.5, 'peak_mem_mb': np.float32(1.5), 'network_gflops': float('inf'),
        'auc_rel': float('nan'), 'stages_ms': {'volume': float('nan'), 'wta': 0.5},
    }
    benchmark.write_records(out, [record], ('stages_ms',), host='test host')
    (row,) = json.loads(out.read_text(), parse_constant=_refuse_constant)
    assert row['ms_per_frame'] == 2.5 and row['peak_mem_mb'] == 1.5
    assert row['network_gflops'] is None and row['auc_rel'] is None
    assert row['stages_ms'] == {'volume': None, 'wta': 0.5}
    assert row['host'] == 'test host'


def test_matcher_peak_is_unknown_without_the_resident_memory_before(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # Without /proc/self/status (macOS) the resident memory before the frames was taken as 0:
    # peak_mem_mb was the whole process's peak (187 MB for a 40×8 frame), not a frame's.
    monkeypatch.setattr(benchmark, 'memory_kb', lambda _field: None)
    monkeypatch.setattr(benchmark, '_reset_peak', lambda: False)
    record = benchmark.run_case('census_bm', BenchSettings(40, 8, 16, 1))
    assert record['peak_mem_mb'] is None
    assert record['ms_per_frame'] > 0
    row = benchmark.format_table([record], threads=1).splitlines()[2]
    assert row.startswith('census_bm') and row.split()[-1] == '—'


def test_network_row_hands_freed_heap_back_before_its_resident_memory(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # run_network read the resident memory with the band's matching and the warm-up's freed
    # heap still in it; the crop reused that heap, and its peak came out lower (320×240, D =
    # 64, crop 32: 45 MB against 50 MB with the trim that run_case and the fast suite do).
    events: list[str] = []
    memory_kb = benchmark.memory_kb

    def traced_memory(field_name: str) -> int | None:
        events.append(field_name)
        return memory_kb(field_name)

    monkeypatch.setattr(benchmark, '_release_free_heap', lambda: events.append('trim'))
    monkeypatch.setattr(benchmark, 'memory_kb', traced_memory)
    monkeypatch.setattr(benchmark, '_gemm_gflops', lambda *_args, **_kwargs: 10.0)
    record = benchmark.run_network(BenchSettings(40, 8, 16, 1), 4)
    assert 'trim' in events and 'VmRSS' in events
    assert events.index('trim') < events.index('VmRSS')
    assert record['crop'] == [4, 4] and record['ms_per_frame'] > 0


def test_gpu_peak_is_taken_before_the_network_only_copy_of_the_volume(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # The network-only timing's padded device copy of the volume (164 MB at 640×480, D = 128)
    # was made before the peak mark was reset and stayed allocated through the timed frames:
    # peak_mem_mb counted a tensor that no frame has.
    from cva_confidence_ros import model

    events: list[str] = []
    pad, evaluator_class = model.pad_cost_volume, model.SparseEvaluator

    def traced_pad(volume: np.ndarray) -> np.ndarray:
        events.append('network-only copy')
        return pad(volume)

    class TracedEvaluator(evaluator_class):  # type: ignore[misc, valid-type]
        def __call__(self, *args: Any, **kwargs: Any) -> Any:
            events.append('frame')
            return super().__call__(*args, **kwargs)

    monkeypatch.setattr(model, 'pad_cost_volume', traced_pad)
    monkeypatch.setattr(model, 'SparseEvaluator', TracedEvaluator)
    (record,) = gpu_benchmark.run_gpu(BenchSettings(40, 8, 16, 2), ['fast'], ['fp32'],
                                      device='cpu', warmup=1, log=lambda _text: None)
    # one warm-up and two timed frames, then the copy for the network-only timing
    assert events == ['frame', 'frame', 'frame', 'network-only copy']
    assert record['ms_per_frame'] > 0 and record['gpu_ms'] > 0


@pytest.mark.parametrize(
    ('argv', 'message'),
    [
        (['--crop', '2'], '--crop must be ≥ 4 pixels; got 2'),
        (['--auc-crop', '8x300'], "--auc-crop must be at least 16x16; got '8x300'"),
    ],
)
def test_fast_suite_names_the_bad_crop(
    argv: list[str], message: str, capsys: pytest.CaptureFixture[str],
) -> None:
    # One message for both options, without the value given.
    with pytest.raises(SystemExit) as exit_info:
        benchmark.main(['--suite', 'fast', *argv])
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err


def test_fast_table_says_the_crop_rows_peak_is_the_crops() -> None:
    # The * of the exact and bf16 rows said only that their time was extrapolated; their peak
    # MB, printed in the same row as the frame's time, is that of the crop (a 4×4 crop: a few
    # MB next to a frame time of minutes).
    from cva_confidence_ros.fast_benchmark import format_fast_table

    row = {'config': 'exact', 'device': 'cpu', 'width': 320, 'height': 240,
           'max_disparity': 64, 'ms_per_frame': 6e4, 'peak_mem_mb': 3.0, 'network_gflops': 40.0,
           'gemm_gflops': 50.0, 'auc_rel': None, 'extrapolated': True, 'network_share': 1.0,
           'threads': 1, 'numba_threads': 1}
    footnote = format_fast_table([row]).splitlines()[-1]
    assert footnote.startswith('* timed on a crop') and "peak MiB is the crop's" in footnote

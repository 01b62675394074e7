"""Regressions found in a review of the benchmark suites (cva-benchmark and its suites)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
import resource
import sys
from typing import Any

import numpy as np
import pytest

from cva_confidence_ros import benchmark, fast_benchmark, gpu_benchmark
from cva_confidence_ros.benchmark import BenchSettings
from cva_confidence_ros.errors import ConfigError

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


def _fast_configs(*names: str) -> list[fast_benchmark.FastConfig]:
    by_name = {c.name: c for c in fast_benchmark.FAST_CONFIGS}
    return [by_name[name] for name in names]


def test_crop_rows_time_repeat_calls_after_an_untimed_one_of_the_same_shape(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # The exact and bf16 rows used to time a single call on the crop, whatever --repeat said,
    # after a warm-up on its 4×4 corner only (another shape, so not the untimed frame the
    # module docstring promised).
    shapes: list[list[tuple[int, ...]]] = []
    real = fast_benchmark._time_frames

    def spy(frame: Any, repeat: int) -> Any:
        seen: list[tuple[int, ...]] = []
        shapes.append(seen)
        evaluator, part = frame.__defaults__

        def counted() -> Any:
            seen.append(part.shape)
            return frame()

        assert evaluator is not None
        return real(counted, repeat)

    monkeypatch.setattr(fast_benchmark, '_time_frames', spy)
    records = fast_benchmark.run_fast(
        BenchSettings(40, 8, 16, 2), _fast_configs('exact', 'bf16'), crop=4,
        log=lambda _text: None, gemm_size=64,
    )
    assert [r['timed_calls'] for r in records] == [2, 2]
    assert [r['crop'] for r in records] == [[4, 4], [4, 4]]
    # one untimed call, then the two timed ones, all on the crop itself
    assert shapes == [[(16, 4, 4)] * 3, [(16, 4, 4)] * 3]
    assert all(r['ms_per_frame'] > 0 and r['network_gflops'] > 0 for r in records)


def test_peak_is_read_on_an_untimed_frame_and_the_timed_frames_follow_without_a_trim(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # malloc_trim used to run right before the timed frames: the first of them (with the
    # default --repeat 1 the only one) paid the page faults again, which the node, keeping its
    # freed memory, does not.
    events: list[str] = []
    trim, memory_kb = fast_benchmark._release_free_heap, fast_benchmark.memory_kb

    def traced_trim() -> None:
        events.append('trim')
        trim()

    def traced_memory(field_name: str) -> int | None:
        events.append(field_name)
        return memory_kb(field_name)

    monkeypatch.setattr(fast_benchmark, '_release_free_heap', traced_trim)
    monkeypatch.setattr(fast_benchmark, 'memory_kb', traced_memory)
    size = 32 * 2**20

    def frame() -> dict[str, float]:
        events.append('frame')
        block = np.ones(size // 8)  # 32 MB, every page touched
        return {'sum': float(block[::512].sum())}

    timing = fast_benchmark._time_frames(frame, 2)
    hwm = ['VmHWM'] if 'VmHWM' in events else []  # not read where the mark cannot be reset
    assert events == ['trim', 'VmRSS', 'frame', *hwm, 'frame', 'frame']
    assert len(timing.seconds) == 2 and [r['sum'] for r in timing.results] == [8192.0] * 2
    if timing.peak_kb is not None and timing.rss_kb is not None:
        assert timing.peak_kb - timing.rss_kb >= 0.75 * size / 1024  # the untimed frame's block


def test_fast_threads_apply_to_torch_and_numba_and_the_table_says_what_ran(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
) -> None:
    # `python -m cva_confidence_ros.fast_benchmark` only set OMP_NUM_THREADS after numba had
    # been imported: numba's matching kept every core while the threads column said 1.
    import numba
    import torch

    from cva_confidence_ros import memory

    kept: list[bool] = []

    def keep_freed_memory() -> bool:
        kept.append(True)
        return True

    monkeypatch.setattr(memory, 'keep_freed_memory', keep_freed_memory)
    several = min(2, int(numba.config.NUMBA_NUM_THREADS))  # type: ignore[attr-defined]
    torch_before, numba_before = torch.get_num_threads(), numba.get_num_threads()
    out = tmp_path / 'fast.json'
    try:
        torch.set_num_threads(2)
        numba.set_num_threads(several)
        argv = ['--suite', 'fast', '--width', '40', '--height', '8', '--max-disparity', '16',
                '--configs', 'stride8', '--threads', '1', '--json', str(out)]
        assert benchmark.main(argv) == 0
        assert (torch.get_num_threads(), numba.get_num_threads()) == (2, several)  # put back
    finally:
        torch.set_num_threads(torch_before)
        numba.set_num_threads(numba_before)
    (row,) = json.loads(out.read_text())
    assert (row['threads'], row['numba_threads'], row['timed_calls']) == (1, 1, 1)
    assert kept == [True]  # the node's allocator setting, before the frames
    mixed = {**row, 'threads': 1, 'numba_threads': 2}
    assert '1 torch / 2 numba threads' in fast_benchmark.format_fast_table([mixed])
    with pytest.raises(ConfigError, match='threads must be ≥ 1; got 0'):
        fast_benchmark.run_fast(BenchSettings(40, 8, 16, 1), [], threads=0)


def test_gpu_suite_puts_the_cudnn_autotuner_flag_back(monkeypatch: pytest.MonkeyPatch) -> None:
    # run_gpu switched torch.backends.cudnn.benchmark on for the rest of the process.
    import torch

    before = torch.backends.cudnn.benchmark
    try:
        torch.backends.cudnn.benchmark = False
        with pytest.raises(RuntimeError, match='row failed'):
            with gpu_benchmark._cudnn_autotuner(torch.device('cuda')):
                assert torch.backends.cudnn.benchmark is True
                raise RuntimeError('row failed')
        assert torch.backends.cudnn.benchmark is False
        with gpu_benchmark._cudnn_autotuner(torch.device('cpu')):
            assert torch.backends.cudnn.benchmark is False
    finally:
        torch.backends.cudnn.benchmark = before
    devices: list[str] = []
    real = gpu_benchmark._cudnn_autotuner

    def traced(device: Any) -> Any:
        devices.append(device.type)
        return real(device)

    monkeypatch.setattr(gpu_benchmark, '_cudnn_autotuner', traced)
    gpu_benchmark.run_gpu(BenchSettings(40, 8, 16, 1), ['fast'], ['fp32'], device='cpu',
                          warmup=0, log=lambda _text: None)
    assert devices == ['cpu']


def test_matcher_suite_json_keeps_the_network_rows_crop_and_threads(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
) -> None:
    # The README's network-row table quotes the crop and the threads, which --json left out.
    settings = BenchSettings(64, 48, 16, 1)
    monkeypatch.setattr(benchmark, '_gemm_gflops', lambda *_args, **_kwargs: 10.0)
    network = benchmark.run_network(settings, 4)

    def in_subprocess(name: str, _settings: Any, _extra: Any = ()) -> dict[str, Any]:
        if name.startswith('cvanet_d'):
            return network
        return {**_COMMON, 'config': name, 'ms_per_frame': 1.0, 'peak_mem_mb': 1.0}

    monkeypatch.setattr(benchmark, '_run_in_subprocess', in_subprocess)
    out = tmp_path / 'bench.json'
    argv = ['--matchers', 'census_bm', '--width', '64', '--height', '48', '--max-disparity',
            '16', '--repeat', '1', '--network-crop', '4', '--json', str(out)]
    assert benchmark.main(argv) == 0
    row = json.loads(out.read_text())[-1]
    assert row['config'] == 'cvanet_d16' and row['extrapolated'] is True
    assert row['crop'] == [4, 4] and row['crop_ms'] == pytest.approx(network['crop_ms'])
    assert row['threads'] == network['threads'] >= 1

"""Regressions found in the third review of cva-benchmark (matcher suite) and its fast suite."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from cva_confidence_ros import benchmark, fast_benchmark
from cva_confidence_ros.benchmark import BenchSettings
from cva_confidence_ros.errors import ConfigError

pytestmark = pytest.mark.usefixtures('one_torch_thread')

_COMMON = {'device': 'cpu', 'width': 48, 'height': 8, 'max_disparity': 8}


def _rows(*names: str) -> list[fast_benchmark.FastConfig]:
    by_name = {c.name: c for c in fast_benchmark.FAST_CONFIGS}
    return [by_name[name] for name in names]


def test_matcher_suite_refuses_a_depth_below_the_network_row_before_measuring(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
) -> None:
    # D = 8 < 13 (CVA-Net's fusion removes 12 disparities) failed only in the network row's
    # subprocess, the last one: after every matcher row had been measured, and without a JSON.
    measured: list[str] = []

    def in_subprocess(name: str, _settings: Any, _extra: Any = ()) -> dict[str, Any]:
        measured.append(name)
        return {**_COMMON, 'config': name, 'ms_per_frame': 1.0, 'peak_mem_mb': 1.0}

    monkeypatch.setattr(benchmark, '_run_in_subprocess', in_subprocess)
    argv = ['--width', '48', '--height', '8', '--max-disparity', '8', '--repeat', '1',
            '--matchers', 'census_bm']
    with pytest.raises(SystemExit) as exit_info:
        benchmark.main(argv)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert 'the CVA-Net row cvanet_d8 needs --max-disparity ≥ 13' in err
    assert 'got 8' in err and '--no-network' in err
    assert measured == []
    assert benchmark.main([*argv, '--no-network']) == 0
    assert measured == ['census_bm', 'opencv_sgbm']


def test_network_row_times_calls_after_an_untimed_one_on_the_crop(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # The network row warmed up on a 4×4 corner only: its first timed call was the first at
    # the crop's shape (16×16, D = 16: 82 ms against 58 for the next calls), and with
    # --repeat 1 or 2 that call made or moved the median. run_case warms up at full size.
    from cva_confidence_ros import model, node_benchmark

    events: list[Any] = []
    predict, reset = model.predict_confidence, benchmark._reset_peak

    def traced_predict(net: Any, volume: np.ndarray, **kwargs: Any) -> Any:
        events.append(volume.shape)
        return predict(net, volume, **kwargs)

    def traced_reset() -> bool:
        events.append('reset')
        return reset()

    monkeypatch.setattr(model, 'predict_confidence', traced_predict)
    monkeypatch.setattr(benchmark, '_reset_peak', traced_reset)
    monkeypatch.setattr(benchmark, '_gemm_gflops', lambda *_args, **_kwargs: 10.0)
    # FLOPs per pixel, padding left out: counting them on the meta device takes seconds
    monkeypatch.setattr(node_benchmark, 'network_flops', lambda rows, columns, _d: rows * columns)
    record = benchmark.run_network(BenchSettings(48, 16, 16, 2), 8)
    crop = (16, 8, 8)
    assert events == [(16, 4, 4), crop, 'reset', crop, crop]
    assert record['crop'] == [8, 8] and record['ms_per_frame'] > record['crop_ms'] > 0


def _crop(wrong: np.ndarray, known: np.ndarray, name: str = 'window') -> dict[str, Any]:
    rng = np.random.default_rng(7)
    volume = rng.random((16, 16, 16), dtype=np.float32)
    return {
        'name': name, 'volume': volume, 'volume_right': volume.copy(),
        'disparity': volume.argmin(axis=0).astype(np.float32),
        'image': rng.integers(0, 256, (16, 16, 3), dtype=np.uint8),
        'wrong': wrong, 'known': known,
    }


def _net() -> Any:
    from cva_confidence_ros.model import CVANet

    torch.manual_seed(0)
    return CVANet(16).eval()


def test_auc_rel_without_a_wrong_pixel_is_undefined_not_a_crash() -> None:
    # Every develop pixel right: the exact AUC is 0, and the ratio to it raised
    # ZeroDivisionError after the whole AUC pass (bf16's ratio over 0 gave nan, printed as
    # 'nan' while the JSON said null).
    shape = (16, 16)
    crop = _crop(np.zeros(shape, bool), np.ones(shape, bool))
    logged: list[str] = []
    rel = fast_benchmark._auc_rel(_rows('exact', 'stride2', 'bf16'), [crop], _net(),
                                  logged.append)
    assert rel == {}
    assert any('auc_rel undefined' in line for line in logged)


def test_auc_rel_skips_a_window_without_ground_truth() -> None:
    # A window with no known pixel failed in roc_auc ('confidence and error are empty'),
    # without naming the scene, after every scene before it had been scored.
    shape = (16, 16)
    wrong = np.random.default_rng(3).random(shape) < 0.3
    empty = _crop(wrong, np.zeros(shape, bool), 'kitti2015/000000')
    scored = _crop(wrong, np.ones(shape, bool), 'middlebury2003/cones')
    logged: list[str] = []
    rel = fast_benchmark._auc_rel(_rows('exact', 'stride2'), [empty, scored], _net(),
                                  logged.append)
    assert rel['exact'] == 1.0 and np.isfinite(rel['stride2']) and rel['stride2'] > 0
    assert any('kitti2015/000000' in line and 'skipped' in line for line in logged)


def test_pipeline_rows_without_shipped_weights_are_refused_before_any_row() -> None:
    # The pipeline rows load shipped weights (the others fall back to a random network); at a
    # D without them they failed when their row came, after every row before had been
    # measured (at 320×240 the exact row alone takes minutes).
    logged: list[str] = []
    with pytest.raises(ConfigError, match=r"D = 16.*\['pipeline:stride8'\]"):
        fast_benchmark.run_fast(BenchSettings(40, 8, 16, 1),
                                _rows('stride8', 'pipeline:stride8'), log=logged.append,
                                gemm_size=64)
    assert not any('measuring' in line for line in logged)
    fast_benchmark._check_pipeline_weights(_rows('pipeline:stride8', 'pipeline:fast'), 64)


def test_fast_rows_alone_run_at_a_depth_below_cva_nets_minimum() -> None:
    # CVA-Net (D ≥ 13) was built for every run, also one of CVA-Net-Fast rows only (D ≥ 9)
    # without a data root: D = 10 was refused with CVA-Net's message.
    (record,) = fast_benchmark.run_fast(BenchSettings(40, 8, 10, 1), _rows('fast'),
                                        log=lambda _text: None, gemm_size=64)
    assert record['config'] == 'fast' and record['arch'] == 'cvanet_fast'
    assert record['max_disparity'] == 10 and record['ms_per_frame'] > 0
    assert record['auc_rel'] is None
    with pytest.raises(ConfigError, match='>= 13'):
        fast_benchmark.run_fast(BenchSettings(40, 8, 10, 1), _rows('stride8'),
                                log=lambda _text: None, gemm_size=64)


def test_fast_table_has_the_crop_footnote_only_with_a_starred_row() -> None:
    # The footnote '* timed on a crop …' was printed under every table, also one without a
    # starred (extrapolated) row.
    row = {'config': 'stride8', 'device': 'cpu', 'width': 40, 'height': 8, 'max_disparity': 16,
           'ms_per_frame': 5.0, 'peak_mem_mb': 1.0, 'network_gflops': 4.0, 'gemm_gflops': 8.0,
           'auc_rel': None, 'extrapolated': False, 'network_share': 0.02, 'threads': 1,
           'numba_threads': 1}
    table = fast_benchmark.format_fast_table([row])
    assert '*' not in table and 'timed on a crop' not in table
    starred = fast_benchmark.format_fast_table([row, {**row, 'config': 'exact',
                                                      'extrapolated': True}])
    assert '| exact * |' in starred
    assert starred.splitlines()[-1].startswith('* timed on a crop')


def test_memory_kb_reads_a_status_with_a_non_ascii_process_name(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A process named 'kaméra' (prctl PR_SET_NAME): the ASCII read raised UnicodeDecodeError.
    import builtins

    from cva_confidence_ros.benchmark import memory_kb

    status = tmp_path / 'status'
    status.write_bytes('Name:\tkaméra\nVmRSS:\t  2048 kB\nVmHWM:\t  4096 kB\n'.encode())
    real_open = builtins.open

    def fake_open(path, *args, **kwargs):
        return real_open(status if path == '/proc/self/status' else path, *args, **kwargs)

    monkeypatch.setattr(builtins, 'open', fake_open)
    assert (memory_kb('VmRSS'), memory_kb('VmHWM'), memory_kb('VmSwap')) == (2048, 4096, None)

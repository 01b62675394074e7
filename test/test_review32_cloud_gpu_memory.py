"""Review 32: the cloud and GPU suites of ``cva-benchmark`` and the device names."""

from __future__ import annotations

from pathlib import Path
from typing import Any
import weakref

import numpy as np
import pytest
import torch

from cva_confidence_ros import gpu_benchmark
from cva_confidence_ros.benchmark import BenchSettings, main
from cva_confidence_ros.devices import resolve_device
from cva_confidence_ros.errors import ConfigError


@pytest.mark.parametrize('cuda', [False, True])
@pytest.mark.parametrize('name', ['cuda:01', 'cuda:00', 'cuda:\u0663', 'cuda:' + '9' * 20])
def test_a_gpu_index_torch_cannot_read_is_a_config_error(
    monkeypatch: pytest.MonkeyPatch, name: str, cuda: bool
) -> None:
    # str.isdecimal let these through to torch.device, which raised a bare RuntimeError
    # ('Invalid device string'): a traceback and exit 1 instead of a ConfigError.
    monkeypatch.setattr(torch.cuda, 'is_available', lambda: cuda)
    monkeypatch.setattr(torch.cuda, 'device_count', lambda: 2)
    with pytest.raises(ConfigError, match='cuda:N'):
        resolve_device(name)


def test_gpu_suite_without_cuda_exits_2_and_writes_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    # The --json folder was made before the device was looked at: a machine without CUDA
    # was left with an empty folder from a run that could never measure anything.
    monkeypatch.setattr(torch.cuda, 'is_available', lambda: False)
    out = tmp_path / 'runs' / 'gpu.json'
    with pytest.raises(SystemExit) as exit_info:
        main(['--suite', 'gpu', '--json', str(out)])
    assert exit_info.value.code == 2
    captured = capsys.readouterr()
    assert captured.out == ''
    assert captured.err == (
        "cva-benchmark: error: device 'cuda' asked for, but CUDA is not available here\n"
    )
    assert list(tmp_path.iterdir()) == []


def test_gpu_suite_refuses_a_bad_device_index_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(['--suite', 'gpu', '--device', 'cuda:01', '--json', str(tmp_path / 'x' / 'g.json')])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and "got 'cuda:01'" in err
    assert list(tmp_path.iterdir()) == []


def test_cloud_suite_bad_threshold_writes_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Same for the cloud suite: the threshold was checked after the --json folder was made.
    with pytest.raises(SystemExit) as exit_info:
        main(['--suite', 'cloud', '--threshold', 'nan', '--json', str(tmp_path / 'c' / 'c.json')])
    assert exit_info.value.code == 2
    assert capsys.readouterr().err == (
        'cva-benchmark: error: --threshold must be in [0, 1]; got nan\n'
    )
    assert list(tmp_path.iterdir()) == []


def test_run_gpu_refuses_no_rows() -> None:
    # No networks (or no precisions) measured the matmuls and returned [], on which
    # format_gpu_table failed with an IndexError.
    settings = BenchSettings(40, 8, 16, 1)
    with pytest.raises(ConfigError, match=r'no rows to measure: networks \[\]'):
        gpu_benchmark.run_gpu(settings, [], ['fp32'], device='cpu')
    with pytest.raises(ConfigError, match=r'no rows to measure: .*precisions \[\]'):
        gpu_benchmark.run_gpu(settings, ['fast'], [], device='cpu')


def test_cuda_timer_records_on_the_stream_of_its_device(monkeypatch: pytest.MonkeyPatch) -> None:
    # The events went to torch.cuda.current_stream() of the current device (cuda:0), while
    # the work on cuda:1 ran on that device's stream: gpu_ms timed nothing there.
    streams: list[Any] = []

    class FakeEvent:
        def __init__(self, enable_timing: bool = False) -> None:
            pass

        def record(self, stream: Any = None) -> None:
            streams.append(stream)

        def synchronize(self) -> None:
            pass

        def elapsed_time(self, other: FakeEvent) -> float:
            return 5.0

    monkeypatch.setattr(torch.cuda, 'Event', FakeEvent)
    monkeypatch.setattr(torch.cuda, 'current_stream', lambda device=None: f'stream of {device}')
    seconds = gpu_benchmark._Timer(torch.device('cuda', 1))(lambda: None)
    assert seconds == pytest.approx(0.005)
    assert streams == ['stream of cuda:1'] * 2


@pytest.mark.usefixtures('one_torch_thread')
def test_a_row_lets_go_of_its_padded_volume_before_the_next(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # network_only's default arguments kept the row's padded device volume (164 MB at
    # 640×480, D = 128) and evaluator alive through the next row's timed frames, so every
    # peak_mem_mb after the first counted them.
    import cva_confidence_ros.model as model

    real_pad, real_evaluator = model.pad_cost_volume, model.SparseEvaluator
    padded: list[weakref.ref[np.ndarray]] = []
    alive_at_row_start: list[int] = []

    def pad(volume: np.ndarray) -> np.ndarray:
        out = real_pad(volume)
        padded.append(weakref.ref(out))
        return out

    def evaluator(*args: Any, **kwargs: Any) -> Any:
        alive_at_row_start.append(sum(ref() is not None for ref in padded))
        return real_evaluator(*args, **kwargs)

    monkeypatch.setattr(model, 'pad_cost_volume', pad)
    monkeypatch.setattr(model, 'SparseEvaluator', evaluator)
    records = gpu_benchmark.run_gpu(BenchSettings(40, 8, 16, 1), ['fast'], ['fp32', 'bf16'],
                                    device='cpu', warmup=0, log=lambda _text: None)
    assert [r['config'] for r in records] == ['fast:fp32', 'fast:bf16']
    assert alive_at_row_start == [0, 0]

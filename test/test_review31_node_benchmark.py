"""Review of cva-benchmark --suite node: what it prints is what it measures, and no orphans."""

from __future__ import annotations

from collections.abc import Callable
import os
from pathlib import Path
import signal
import subprocess
import sys
import textwrap
import time
from typing import Any

import pytest

from cva_confidence_ros import node_benchmark
from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.node_benchmark import NodeBenchSettings

pytestmark = pytest.mark.timeout(60)


class _FakeNode:
    """Stands in for :class:`NodeProcess`: alive until ``dies_after`` publishes."""

    def __init__(self, client: _FakeClient, dies_after: int | None = None) -> None:
        self.client = client
        self.dies_after = dies_after
        self.stopped = False

    def alive(self) -> bool:
        return self.dies_after is None or self.client.published < self.dies_after

    def fail(self, what: str) -> ConfigError:
        return ConfigError(f'{what} (fake node)')

    def cpu_seconds(self) -> float:
        return 0.0

    def wait_ready(self, timeout: float) -> None:
        pass

    def memory_mb(self, field_name: str) -> float:
        return 100.0

    def stop(self) -> int:
        self.stopped = True
        return 0


class _FakeClient:
    """Stands in for the DDS client: the node receives, processes and answers the frames for
    which ``answers(index)`` holds; the others never reach it."""

    def __init__(self, answers: Callable[[int], bool] = lambda index: True) -> None:
        self.answers = answers
        self.published = 0
        self.counters: dict[str, int] = {}
        self.arrivals: dict[int, float] = {}

    def counter(self, key: str) -> int:
        return self.counters.get(key, 0)

    def publish(self, messages: dict[str, Any]) -> float:
        start = time.perf_counter()
        index, self.published = self.published, self.published + 1
        if self.answers(index):
            for key in ('frames_received', 'frames_processed'):
                self.counters[key] = self.counter(key) + 1
            self.arrivals[messages['stamp']] = time.perf_counter() + 0.001 * (index + 1)
        return start

    def answer_time(self, stamp: int) -> float | None:
        return self.arrivals.get(stamp)

    def idle_after(self, processed: int) -> bool:
        return self.counter('frames_processed') >= processed

    def diagnostics(self) -> dict[str, str]:
        return {'last_frame_ms': '1.0'}

    def matched(self) -> bool:
        return True

    def wait(self, predicate: Callable[[], bool], timeout: float,
             alive: Callable[[], bool]) -> bool:
        return alive() and predicate()

    def __enter__(self) -> _FakeClient:
        return self

    def __exit__(self, *_: object) -> None:
        pass


@pytest.fixture
def no_messages(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(node_benchmark, 'frame_messages', lambda left, right, stamp: {
        'stamp': stamp})


def _pair() -> tuple[Any, Any]:
    return None, None


def _row(**changes: Any) -> dict[str, Any]:
    row = {
        'config': 'node:census_bm+pkrn', 'device': 'cpu', 'width': 32, 'height': 16,
        'max_disparity': 8, 'matcher': 'census_bm', 'downsample': 1, 'ms_per_frame': 10.0,
        'latency_ms_median': 10.0, 'fps': 100.0, 'online': True, 'extrapolated': False,
        'peak_mem_mb': 300.0, 'stages_ms': {}, 'note': '',
    }  # fmt: skip
    row.update(changes)
    return row


def test_peak_memory_is_labelled_mib_as_proc_counts_kib() -> None:
    # VmHWM is in KiB; memory_mb divides by 1024: the number is MiB, so must be the label.
    table = node_benchmark.format_table([_row()], threads=2)
    header = next(line for line in table.splitlines() if line.startswith('| config |'))
    assert header.endswith('| peak RSS MiB |')
    assert 'MB |' not in table


def test_rate_must_be_finite() -> None:
    # An infinite rate rounded the stamp period to 0 ns: every burst frame had one stamp.
    for rate in (float('inf'), 1e12):
        with pytest.raises(ConfigError, match='rate'):
            NodeBenchSettings(rate_hz=rate)
    assert NodeBenchSettings(rate_hz=1e3).rate_hz == 1e3


def test_burst_counts_the_frames_it_lost(no_messages: None) -> None:
    # Frame 1 of 4 never reaches the node: it is neither answered nor dropped nor throttled.
    client = _FakeClient(answers=lambda index: index != 1)
    node = _FakeNode(client)
    settings = NodeBenchSettings(rate_hz=1000.0, burst_frames=4, timeout_s=0.1)
    burst = node_benchmark._burst(client, node, _pair(), node_benchmark._stamps(), settings)  # type: ignore[arg-type]
    assert (burst['burst_sent'], burst['burst_answered'], burst['burst_dropped']) == (4, 3, 0)
    assert burst['burst_lost'] == 1
    table = node_benchmark.format_table(
        [_row(**{**burst, 'burst_output_hz': 5.0, 'burst_cpu_cores': 1.0})], threads=2
    )
    assert '| lost |' in table and '| 4 | 3 | 0 | 0 | 1 |' in table


def test_burst_raises_when_the_node_dies(no_messages: None) -> None:
    # The node dies after the second frame: the burst must not be reported as a result.
    client = _FakeClient()
    node = _FakeNode(client, dies_after=2)
    settings = NodeBenchSettings(rate_hz=1000.0, burst_frames=4, timeout_s=0.1)
    with pytest.raises(ConfigError, match='died during the burst'):
        node_benchmark._burst(client, node, _pair(), node_benchmark._stamps(), settings)  # type: ignore[arg-type]


def test_dead_node_in_a_timed_frame_is_not_reported_as_a_timeout(
    no_messages: None, monkeypatch: pytest.MonkeyPatch
) -> None:
    client = _FakeClient(answers=lambda index: False)
    nodes: list[_FakeNode] = []

    def start(command: Any, env: Any) -> _FakeNode:
        nodes.append(_FakeNode(client, dies_after=1))
        return nodes[-1]

    monkeypatch.setattr(node_benchmark, '_Client', lambda domain, outputs: client)
    monkeypatch.setattr(node_benchmark, 'NodeProcess', start)
    monkeypatch.setattr(node_benchmark, '_warm_up', lambda *args: None)
    settings = NodeBenchSettings(repeat=2, timeout_s=3600.0)
    with pytest.raises(ConfigError, match='died during a timed frame') as error:
        node_benchmark.measure_node(settings, 'census_bm', 'pkrn', _pair())  # type: ignore[arg-type]
    assert '3600' not in str(error.value)
    assert nodes[0].stopped


def test_table_names_the_outputs_the_latency_waits_for() -> None:
    row = _row(outputs=['points2'])
    table = node_benchmark.format_table([row], threads=2)
    assert '→ points2 received' in table
    assert 'disparity and confidence received' not in table
    # the extrapolated row keeps what its base waited for
    crop = {
        'crop': [4, 4], 'crop_confidence_ms': 1.0, 'crop_pixels_per_s': 16.0,
        'crop_flops': 1.0, 'frame_flops': 2.0, 'crop_gflop_per_s': 1.0, 'gemm_gflops': 1.0,
    }  # fmt: skip
    assert node_benchmark.extrapolate_cva_net(row, crop, 'w')['outputs'] == ['points2']


def test_repeated_or_missing_names_are_rejected_before_any_node_starts(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    started: list[str] = []

    def measure(settings: Any, matcher: str, method: str, *args: Any) -> dict[str, Any]:
        started.append(f'{matcher}+{method}')
        return _row(config=f'node:{matcher}+{method}')

    monkeypatch.setattr(node_benchmark, 'measure_node', measure)
    monkeypatch.setattr(node_benchmark, 'benchmark_pair', lambda width, height: _pair())
    settings = NodeBenchSettings(width=32, height=16, max_disparity=8, repeat=1)
    for matchers, methods, name in (
        (['census_bm', 'census_bm'], ['pkrn'], 'census_bm'),
        (['census_bm'], ['pkrn', 'mlm', 'pkrn'], 'pkrn'),
        ([], ['pkrn'], 'matchers'),
    ):
        with pytest.raises(ConfigError, match=name):
            node_benchmark.run_suite(settings, matchers, methods, log=lambda line: None)
    assert started == []


_SIGTERM_SCRIPT = """
import sys, time
from cva_confidence_ros import node_benchmark

class Client:
    def __enter__(self): return self
    def __exit__(self, *args): pass
    def matched(self): return False
    def wait(self, predicate, timeout, alive):
        print('waiting', flush=True)
        time.sleep(timeout)
        return False

pid_file = sys.argv[1]
node = (
    "import os, sys, time; open(sys.argv[1], 'w').write(str(os.getpid())); "
    "print('ready: fake', flush=True); time.sleep(60)"
)
node_benchmark.node_command = lambda: [sys.executable, '-c', node, pid_file]
node_benchmark._Client = lambda domain, outputs: Client()
node_benchmark.measure_node(node_benchmark.NodeBenchSettings(), 'census_bm', 'pkrn', (None, None))
"""


def _gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    # a zombie (not yet reaped by init) counts as gone
    try:
        state = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()[0]
    except OSError:
        return True
    return state == 'Z'


def test_sigterm_to_the_benchmark_stops_the_node(tmp_path: Path) -> None:
    pid_file = tmp_path / 'node.pid'
    bench = subprocess.Popen(
        [sys.executable, '-c', textwrap.dedent(_SIGTERM_SCRIPT), str(pid_file)],
        stdout=subprocess.PIPE, text=True,
        env={**os.environ, 'PYTHONPATH': str(Path(node_benchmark.__file__).parents[1])},
    )  # fmt: skip
    node_pid = None
    try:
        assert bench.stdout is not None
        assert bench.stdout.readline().strip() == 'waiting'  # the node is up and ready
        node_pid = int(pid_file.read_text())
        bench.send_signal(signal.SIGTERM)
        bench.wait(20)
        deadline = time.monotonic() + 10
        while not _gone(node_pid) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert _gone(node_pid), 'cva-node outlived the benchmark that SIGTERM ended'
    finally:
        bench.kill()
        bench.wait(10)
        if node_pid is not None and not _gone(node_pid):
            os.kill(node_pid, signal.SIGKILL)

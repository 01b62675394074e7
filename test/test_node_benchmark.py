"""cva-benchmark --suite node: settings, operation count, extrapolation, table, one real run."""

from __future__ import annotations

import json
import os
from pathlib import Path
from xml.etree import ElementTree

import pytest

from cva_confidence_ros import benchmark, node_benchmark
from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.node_benchmark import NodeBenchSettings

pytestmark = pytest.mark.timeout(180)


@pytest.mark.parametrize(
    ('changes', 'message'),
    [
        ({'width': 8}, 'at least'),
        ({'repeat': 0}, 'repeat'),
        ({'downsample': 3}, 'downsample'),
        ({'device': 'tpu'}, 'device'),
        ({'crop': (0, 4)}, 'crop'),
        ({'rate_hz': 0.0}, 'rate'),
        ({'outputs': ('points3',)}, 'outputs'),
        ({'domain_id': 300}, 'domain_id'),
        ({'dds_profile': 'no/such/profiles.xml'}, 'dds_profile'),
    ],
)
def test_invalid_settings_are_rejected(changes: dict[str, object], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        NodeBenchSettings(**changes)  # type: ignore[arg-type]


def test_node_parameters_ask_for_reliable_qos_both_ways() -> None:
    settings = NodeBenchSettings(max_disparity=32, downsample=2)
    args = node_benchmark.node_parameters(settings, 'census_sgm', 'lrc', '/w.pt')
    values = dict(arg.split(':=') for arg in args if arg != '-p')
    assert args.count('-p') == len(values)
    assert values['input_qos'] == values['output_qos'] == 'reliable'
    assert values['matcher'] == 'census_sgm' and values['confidence_method'] == 'lrc'
    assert values['max_disparity'] == '32' and values['downsample'] == '2'
    assert values['model_path'] == '/w.pt'
    assert settings.processed_size == (240, 320)


def test_param_option_reaches_the_node_as_ros_parameters() -> None:
    """``--param NAME=VALUE`` (repeatable) is parsed, checked and passed as ``-p NAME:=VALUE``."""
    args = node_benchmark._parser().parse_args(
        ['--param', 'cva_stride=4', '--param', 'cva_cascade=pkrn', '--param', 'matcher=x']
    )
    params = node_benchmark.parse_params(args.param)
    assert params == (('cva_stride', '4'), ('cva_cascade', 'pkrn'), ('matcher', 'x'))
    settings = NodeBenchSettings(params=params)
    ros_args = node_benchmark.node_parameters(settings, 'census_bm', 'cva_net_lite')
    assert ros_args[-4:] == ['-p', 'cva_stride:=4', '-p', 'cva_cascade:=pkrn']
    # a --param overrides the benchmark's own value of the same name (no duplicate -p)
    values = dict(arg.split(':=') for arg in ros_args if arg != '-p')
    assert ros_args.count('-p') == len(values) and values['matcher'] == 'x'
    assert node_benchmark.parse_params([' cva_precision = bf16 ']) == (('cva_precision', 'bf16'),)
    for bad in ('cva_stride', 'cva_stride=', '=4', '4x=1', 'a b=1'):
        with pytest.raises(ConfigError, match='--param must be NAME=VALUE'):
            node_benchmark.parse_params([bad])
    with pytest.raises(ConfigError, match='params'):
        NodeBenchSettings(params=(('cva_stride', ''),))
    # the CPU extrapolation of cva_net times the exact network: parameters would be ignored
    with pytest.raises(ConfigError, match='--full-cva-net'):
        node_benchmark.run_suite(settings, ['census_bm'], ['cva_net'])
    code = None
    try:
        node_benchmark.main(['--methods', 'cva_net', '--param', 'nonsense'])
    except SystemExit as exit_:
        code = exit_.code
    assert code == 2


def test_large_message_profile_gives_shared_memory_room_for_image_messages() -> None:
    root = ElementTree.fromstring(node_benchmark.FASTDDS_LARGE_MESSAGES_XML)
    sizes = [int(e.text or 0) for e in root.iter() if e.tag.endswith('segment_size')]
    # two 640×480 rgb8 inputs plus four float32 / point outputs of one frame, with room to spare
    assert sizes == [16 * 1024 * 1024]
    assert sizes[0] > 2 * 640 * 480 * 3 + 4 * 640 * 480 * 4


def test_network_flops_of_one_extract_match_the_architecture() -> None:
    depth = 16
    # Six unpadded 3×3×3 convolutions, 32 filters: layer k outputs (D − 2k) × (13 − 2k)².
    fusion = sum(
        2 * 32 * (1 if k == 1 else 32) * 27 * (depth - 2 * k) * (13 - 2 * k) ** 2
        for k in range(1, 7)
    )
    # Ten depth convolutions (kernels 8, 16, 32, 64 × 7) over D − 12, then 16 and 1 nodes.
    curves = 2 * 32 * 32 * (8 + 16 + 32 + 7 * 64) * (depth - 12)
    dense = 2 * 16 * 32 * (depth - 12) + 2 * 16
    assert fusion + curves + dense == 102_169_248
    assert node_benchmark.network_flops(1, 1, depth) == 102_169_248
    # Small tiles repeat the 6-px borders: the same frame costs more when cut finer.
    whole = node_benchmark.network_flops(64, 96, depth)
    assert node_benchmark.network_flops(64, 96, depth, tile_budget_mb=1.0) > 2 * whole


def _base_record() -> dict[str, object]:
    return {
        'config': 'node:census_bm+pkrn', 'device': 'cpu', 'width': 640, 'height': 480,
        'max_disparity': 128, 'matcher': 'census_bm', 'downsample': 1,
        'latency_ms_median': 200.0,
        'stages_ms': {'matching': 120.0, 'confidence': 30.0, 'frame': 170.0},
    }  # fmt: skip


def test_extrapolation_swaps_the_confidence_stage_for_the_scaled_network_time() -> None:
    crop = {
        'crop': [10, 20], 'crop_confidence_ms': 1000.0, 'crop_pixels_per_s': 200.0,
        'crop_flops': 2e9, 'frame_flops': 50e9, 'crop_gflop_per_s': 2.0,
        'crop_peak_delta_mb': 100.0, 'gemm_gflops': 40.0,
    }  # fmt: skip
    row = node_benchmark.extrapolate_cva_net(_base_record(), crop, 'random init')
    # 1000 ms × 50 / 2 = 25 s of network; 200 − 30 ms of the rest
    assert row['network_ms'] == pytest.approx(25_000.0)
    assert row['latency_ms_median'] == pytest.approx(25_170.0)
    assert row['fps'] == pytest.approx(1000.0 / 25_170.0)
    assert row['online'] is False and row['extrapolated'] is True
    assert row['config'] == 'node:census_bm+cva_net'
    assert row['stages_ms']['frame'] == pytest.approx(25_140.0)
    assert row['network_gflops'] == pytest.approx(50.0)
    assert row['peak_mem_mb'] is None
    assert set(node_benchmark.RECORD_KEYS) <= set(row)


def test_table_marks_extrapolated_rows_and_the_online_ones() -> None:
    fast = {
        **_base_record(), 'ms_per_frame': 100.0, 'latency_ms_median': 100.0, 'fps': 10.0,
        'online': True, 'extrapolated': False, 'peak_mem_mb': 500.0, 'note': '',
    }  # fmt: skip
    slow = {
        **fast, 'config': 'node:census_bm+cva_net', 'latency_ms_median': 9000.0, 'fps': 0.11,
        'online': False, 'extrapolated': True, 'peak_mem_mb': None, 'note': 'extrapolated: x',
    }  # fmt: skip
    table = node_benchmark.format_table([fast, slow], threads=2)
    lines = table.splitlines()
    assert any(line.startswith('| node:census_bm+pkrn | 100.0 | 10.00 | yes |') for line in lines)
    assert any(line.startswith('| node:census_bm+cva_net * | 9000.0 | 0.11 | no |')
               for line in lines)
    assert 'EXTRAPOLATED' in table and 'extrapolated: x' in table


def test_tiny_run_through_the_real_node(tmp_path: Path) -> None:
    out = tmp_path / 'node.json'
    code = benchmark.main(
        ['--suite', 'node', '--width', '96', '--height', '64', '--max-disparity', '16',
         '--repeat', '2', '--matchers', 'census_bm', '--methods', 'pkrn', 'cva_net',
         '--crop', '8', '16', '--threads', '1', '--rate', '50', '--burst-frames', '3',
         '--json', str(out)]
    )  # fmt: skip
    assert code == 0
    rows = json.loads(out.read_text())
    assert [row['config'] for row in rows] == ['node:census_bm+pkrn', 'node:census_bm+cva_net']
    measured, extrapolated = rows
    for row in rows:
        assert set(node_benchmark.RECORD_KEYS) <= set(row)
        assert row['host'] == benchmark.host_summary()
        assert (row['width'], row['height'], row['max_disparity']) == (96, 64, 16)
        assert row['latency_ms_median'] > 0
        assert row['fps'] == pytest.approx(1000.0 / row['latency_ms_median'])
        assert row['online'] == (row['fps'] >= 5.0)
    assert measured['extrapolated'] is False
    assert len(measured['latencies_ms']) == 2 and min(measured['latencies_ms']) > 0
    # The node's own times come over /diagnostics and hardly exceed the round trip (its frame
    # clock stops once its publish calls return, which can be a moment after the client has
    # the message: a few milliseconds of slack).
    assert 0 < measured['stages_ms']['frame'] <= max(measured['latencies_ms']) + 5.0
    assert measured['peak_mem_mb'] >= measured['rss_ready_mb'] > 0
    assert measured['burst_sent'] == 3 and measured['burst_answered'] >= 1
    assert measured['burst_answered'] + measured['burst_dropped'] <= 3
    assert measured['burst_throttled'] == 0  # no max_rate_hz here
    # The node's CPU time over the burst, on at most the cores here plus slack for the 10 ms
    # ticks of /proc/<pid>/stat (three tiny frames can take less than one tick: ≥ 0).
    assert 0 <= measured['burst_cpu_cores'] <= (os.cpu_count() or 1) + 0.5
    assert extrapolated['extrapolated'] is True
    assert extrapolated['crop'] == [8, 16] and extrapolated['network_gflops'] > 0
    assert extrapolated['base_config'] == 'node:census_bm+pkrn'

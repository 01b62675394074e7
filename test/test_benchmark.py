"""cva-benchmark: pairs, records, table, and one tiny real run through subprocesses."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from cva_confidence_ros import benchmark
from cva_confidence_ros.errors import ConfigError


def test_settings_are_validated() -> None:
    with pytest.raises(ConfigError, match='max_disparity'):
        benchmark.BenchSettings(width=64, height=48, max_disparity=64)
    with pytest.raises(ConfigError, match='repeat'):
        benchmark.BenchSettings(repeat=0)
    with pytest.raises(ConfigError, match='at least'):
        benchmark.BenchSettings(width=8, height=8, max_disparity=2)


def test_pairs_have_the_requested_size_and_the_synthetic_one_its_disparities() -> None:
    settings = benchmark.BenchSettings(width=96, height=60, max_disparity=24, repeat=1)
    pairs = benchmark.make_pairs(settings)
    assert set(pairs) == {'real', 'synthetic'}
    for left, right in pairs.values():
        assert left.shape == right.shape == (60, 96, 3) and left.dtype == np.uint8
    left, right = pairs['synthetic']
    # band b (10 rows each) has disparity (b + 1)·23 // 7: left(y, x) = right(y, x − d)
    for band in range(6):
        disparity = (band + 1) * 23 // 7
        rows = slice(band * 10, band * 10 + 10)
        np.testing.assert_array_equal(left[rows, disparity:], right[rows, :96 - disparity])
    # the real pair is not a shifted copy: the Motorcycle scene has depth
    assert not np.array_equal(pairs['real'][0], pairs['real'][1])


def test_table_shows_the_ratio_to_sgbm() -> None:
    common = {'device': 'cpu', 'width': 64, 'height': 48, 'max_disparity': 16}
    records = [
        {**common, 'config': 'census_bm', 'ms_per_frame': 5.0, 'peak_mem_mb': 1.0,
         'per_pair_ms': {'real': 4.0, 'synthetic': 6.0}, 'stages_ms': {'volume': 3.0}},
        {**common, 'config': 'opencv_sgbm', 'ms_per_frame': 10.0, 'peak_mem_mb': 2.0},
    ]
    table = benchmark.format_table(records, threads=2)
    bm_line = next(line for line in table.splitlines() if line.startswith('census_bm'))
    assert bm_line.split()[-2] == '0.50'
    assert '64×48, D = 16' in table


def test_tiny_run_writes_the_records(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / 'bench' / 'out.json'
    code = benchmark.main(
        ['--width', '64', '--height', '48', '--max-disparity', '16', '--repeat', '1',
         '--matchers', 'census_bm', '--no-network', '--json', str(out)]
    )
    assert code == 0
    records = json.loads(out.read_text())
    assert [r['config'] for r in records] == ['census_bm', 'opencv_sgbm']
    for record in records:
        # The table's per-pair, volume and paired-SGBM columns come from these.
        assert tuple(record) == (*benchmark.RECORD_KEYS, 'per_pair_ms', 'stages_ms',
                                 'paired_sgbm_ms', 'host')
        assert set(record['per_pair_ms']) == {'real', 'synthetic'}
        assert record['host'] == benchmark.host_summary()
        assert (record['width'], record['height'], record['max_disparity']) == (64, 48, 16)
        assert record['device'] == 'cpu'
        assert record['ms_per_frame'] > 0 and record['peak_mem_mb'] >= 0
        assert record['network_gflops'] is None and record['auc_rel'] is None
    printed = capsys.readouterr().out
    assert 'opencv_sgbm' in printed and f'host: {benchmark.host_summary()}' in printed
    assert 'nan' not in printed  # a dash where a row has no such number (SGBM's own volume)


def test_unknown_configuration_exits_with_a_usage_error(
    capsys: pytest.CaptureFixture[str],
) -> None:
    with pytest.raises(SystemExit) as exit_info:
        benchmark.main(['--matchers', 'sad'])
    assert exit_info.value.code == 2
    assert "unknown benchmark configuration 'sad'" in capsys.readouterr().err


def test_every_matcher_is_a_configuration() -> None:
    from cva_confidence_ros.matching import MATCHERS

    assert set(MATCHERS.names()) | {'opencv_sgbm'} == set(benchmark.CASES.names())


def test_network_row_is_extrapolated_from_a_crop() -> None:
    settings = benchmark.BenchSettings(width=64, height=48, max_disparity=16, repeat=1)
    record = benchmark.run_network(settings, crop=8)
    assert set(benchmark.RECORD_KEYS) <= set(record)
    assert record['config'] == 'cvanet_d16' and record['device'] == 'cpu'
    assert record['extrapolated'] is True and record['crop'] == [8, 8]
    assert record['auc_rel'] == 1.0
    # no weights are shipped for D = 16: a random network, and the record says so
    assert 'random init' in record['note']
    assert record['network_gflops'] > 0 and record['gemm_gflops'] > 0
    # the 64×48 frame has 48 times the crop's pixels, and more FLOPs than the crop
    assert record['ms_per_frame'] > record['crop_ms'] > 0
    assert record['peak_mem_mb'] is None or record['peak_mem_mb'] >= 0


def test_network_row_goes_into_the_json(tmp_path: Path) -> None:
    out = tmp_path / 'out.json'
    code = benchmark.main(
        ['--width', '64', '--height', '48', '--max-disparity', '16', '--repeat', '1',
         '--matchers', 'census_bm', '--network-crop', '8', '--json', str(out)]
    )
    assert code == 0
    records = json.loads(out.read_text())
    assert [r['config'] for r in records] == ['census_bm', 'opencv_sgbm', 'cvanet_d16']
    network = records[-1]
    assert tuple(network)[: len(benchmark.RECORD_KEYS)] == benchmark.RECORD_KEYS
    assert network['extrapolated'] is True and network['ms_per_frame'] > 0
    assert network['network_gflops'] > 0 and network['gemm_gflops'] > 0


def test_network_crop_must_be_positive(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        benchmark.main(['--network-crop', '0'])
    assert exit_info.value.code == 2
    assert 'network-crop' in capsys.readouterr().err


def test_depths_that_are_not_a_multiple_of_16(capsys: pytest.CaptureFixture[str]) -> None:
    # OpenCV rounds SGBM's disparity count up to a multiple of 16: D = 17 searches 32.
    code = benchmark.main(['--width', '48', '--height', '8', '--max-disparity', '17',
                           '--repeat', '1', '--matchers', 'census_bm', '--no-network'])
    assert code == 0 and 'opencv_sgbm' in capsys.readouterr().out
    with pytest.raises(SystemExit) as exit_info:
        benchmark.main(['--width', '34', '--height', '8', '--max-disparity', '17',
                        '--repeat', '1', '--matchers', 'census_bm', '--no-network'])
    assert exit_info.value.code == 2
    assert 'at least 35 px wide at D = 17' in capsys.readouterr().err


@pytest.mark.parametrize('suite', [[], ['--suite', 'fast']])
def test_json_path_is_checked_before_measuring(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], suite: list[str]
) -> None:
    with pytest.raises(SystemExit) as exit_info:
        benchmark.main([*suite, '--width', '64', '--height', '8', '--max-disparity', '8',
                        '--repeat', '1', '--json', str(tmp_path)])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith('cva-benchmark: error: --json') and 'measuring' not in err


def test_data_errors_of_a_suite_are_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        benchmark.main(['--suite', 'fast', '--width', '32', '--height', '16', '--max-disparity',
                        '16', '--configs', 'exact', '--data-root', '/nonexistent/data'])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    last = err.splitlines()[-1]
    assert last.startswith('cva-benchmark: error:') and 'is not a folder' in last
    assert 'Traceback' not in err


def test_wide_numbers_stay_apart_in_the_table() -> None:
    # A network 1924× slower than SGBM at 160×120 printed '2.1111924.38': its SGBM* and
    # × SGBM cells ran together.
    common = {'device': 'cpu', 'width': 160, 'height': 120, 'max_disparity': 32}
    records = [
        {**common, 'config': 'cvanet_d32', 'ms_per_frame': 4062.5, 'peak_mem_mb': 1.0,
         'paired_sgbm_ms': 2.111},
        {**common, 'config': 'opencv_sgbm', 'ms_per_frame': 2.1, 'peak_mem_mb': 2.0},
    ]
    table = benchmark.format_table(records, threads=2)
    line = next(line for line in table.splitlines() if line.startswith('cvanet_d32'))
    assert line.split()[-3:-1] == ['2.1', '1924.44']

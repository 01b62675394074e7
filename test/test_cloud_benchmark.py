"""``cva-benchmark --suite cloud``: the point-cloud stages on a small real frame."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from cva_confidence_ros.benchmark import main


def test_cloud_suite_prints_and_writes_every_stage(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / 'cloud.json'
    code = main([
        '--suite', 'cloud', '--width', '96', '--height', '64', '--max-disparity', '16',
        '--repeat', '2', '--json', str(out),
    ])  # fmt: skip
    assert code == 0
    table = capsys.readouterr().out
    assert '| cloud_filter dense | 96×64 |' in table
    records = {r['config']: r for r in json.loads(out.read_text())}
    assert list(records) == [
        'points2', 'points2+confidence', 'cloud_filter organised', 'cloud_filter dense',
        'depth 32FC1', 'depth 16UC1', 'scan',
    ]
    assert all(r['ms_per_frame'] > 0 for r in records.values())
    annotated = records['points2+confidence']
    # The filter at the node's threshold keeps exactly the points the node keeps itself.
    assert records['cloud_filter dense']['points_in'] == annotated['points_out']
    assert records['cloud_filter dense']['points_out'] == records['points2']['points_out']
    assert records['cloud_filter organised']['points_out'] == records['points2']['points_out']
    assert records['points2']['points_out'] < annotated['points_out']
    # 20-byte annotated points against 16-byte plain ones, both organised 96×64.
    assert (annotated['bytes'], records['points2']['bytes']) == (96 * 64 * 20, 96 * 64 * 16)
    # The depth image has a value exactly where points2 has a point: 4 or 2 bytes a pixel.
    for name, size in (('depth 32FC1', 4), ('depth 16UC1', 2)):
        assert records[name]['points_out'] == records['points2']['points_out']
        assert records[name]['bytes'] == 96 * 64 * size
    # The scan: at most one beam a column, each with a float32 range and intensity.
    scan = records['scan']
    assert 0 < scan['points_out'] <= 96 and scan['bytes'] <= 96 * 8


def test_cloud_suite_refuses_a_bad_threshold(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(['--suite', 'cloud', '--threshold', '2'])
    assert exit_info.value.code == 2
    assert '--threshold must be in [0, 1]' in capsys.readouterr().err

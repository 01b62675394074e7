"""``cva-benchmark --suite fast``: records with the issue's keys, on a tiny frame."""

from __future__ import annotations

import json

import pytest
import torch

from cva_confidence_ros.benchmark import RECORD_KEYS, BenchSettings, main
from cva_confidence_ros.fast_benchmark import FAST_CONFIGS, format_fast_table, run_fast

pytestmark = pytest.mark.usefixtures('one_torch_thread')


def test_rows_have_the_record_keys():
    by_name = {c.name: c for c in FAST_CONFIGS}
    configs = [by_name[n] for n in ('exact', 'stride8+pkrn0.25', 'pipeline:stride8')]
    records = run_fast(
        BenchSettings(80, 8, 64, 1), configs, crop=4, log=lambda _text: None, gemm_size=256
    )
    assert [r['config'] for r in records] == [c.name for c in configs]
    for record in records:
        assert set(RECORD_KEYS) <= set(record)
        assert record['ms_per_frame'] > 0 and record['network_gflops'] > 0
        assert record['auc_rel'] is None  # no data root
        assert (record['width'], record['height'], record['max_disparity']) == (80, 8, 64)
    assert records[0]['extrapolated'] is True
    assert 0 < records[1]['network_share'] < 0.1
    assert 'matching' in records[2]['stages_ms']
    assert 'stride8+pkrn0.25' in format_fast_table(records)


def test_cli_rejects_unknown_rows(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(['--suite', 'fast', '--configs', 'stride3', '--json', str(tmp_path / 'a.json')])
    assert exit_info.value.code == 2
    assert 'stride3' in capsys.readouterr().err


def test_cli_writes_json(tmp_path):
    out = tmp_path / 'fast.json'
    code = main(
        [
            '--suite',
            'fast',
            '--width',
            '80',
            '--height',
            '8',
            '--configs',
            'stride8',
            '--json',
            str(out),
        ]
    )
    assert code == 0
    rows = json.loads(out.read_text())
    assert rows[0]['config'] == 'stride8' and set(RECORD_KEYS) <= set(rows[0])


def test_lite_rows_time_lite_and_score_it_against_the_full_network():
    import numpy as np

    from cva_confidence_ros.datasets.synthetic import synthetic_pair
    from cva_confidence_ros.fast_benchmark import FastConfig, _auc_rel
    from cva_confidence_ros.matching import compute_cost_volume, wta_disparity
    from cva_confidence_ros.metrics import kitti_error, roc_auc
    from cva_confidence_ros.model import CVANet, CVANetFast, CVANetLite, SparseEvaluator

    by_name = {c.name: c for c in FAST_CONFIGS}
    names = ('lite', 'lite+stride4', 'lite+stride8+pkrn0.1', 'pipeline:lite+stride4')
    assert all(
        by_name[n].arch == 'cvanet_lite' and by_name[n].method == 'cva_net_lite' for n in names
    )
    assert by_name['stride4'].arch == 'cvanet'
    with pytest.raises(Exception, match='arch'):
        FastConfig('x', arch='resnet')
    records = run_fast(
        BenchSettings(80, 8, 64, 1), [by_name[n] for n in names], crop=4,
        log=lambda _text: None, gemm_size=256,
    )  # fmt: skip
    assert [r['arch'] for r in records] == ['cvanet_lite'] * 4
    assert records[0]['network_share'] == 1.0 and records[0]['extrapolated'] is False
    assert records[1]['network_share'] == pytest.approx(1 / 16, abs=0.05)
    assert 'matching' in records[3]['stages_ms']
    # auc_rel of a Lite row = AUC of Lite (looked up at the evaluated pixels) / AUC of CVA-Net
    sample = synthetic_pair(3, 32, 64, 16)
    volume = compute_cost_volume(sample.left, sample.right, 'census_bm', 16)
    disparity = wta_disparity(volume)
    crop = {
        'name': 'synthetic', 'volume': volume, 'disparity': disparity, 'image': sample.left,
        'volume_right': compute_cost_volume(sample.left, sample.right, 'census_bm', 16,
                                            view='right'),
        'wrong': kitti_error(disparity, sample.disparity),
        'known': np.ones(volume.shape[1:], bool),
    }  # fmt: skip
    torch.manual_seed(0)
    net, lite, fast = CVANet(16).eval(), CVANetLite(16).eval(), CVANetFast(16).eval()
    configs = [FastConfig('lite', arch='cvanet_lite'), FastConfig('stride2', stride=2),
               FastConfig('lite+stride2', stride=2, arch='cvanet_lite'),
               FastConfig('fast', arch='cvanet_fast')]  # fmt: skip
    rel = _auc_rel(configs, [crop], net, lambda _text: None,
                   {'cvanet_lite': lite, 'cvanet_fast': fast})  # fmt: skip
    wrong = crop['wrong'].ravel()
    full = roc_auc(SparseEvaluator(net)(volume).ravel(), wrong)
    for name, other in (('lite', lite), ('fast', fast)):
        assert rel[name] == pytest.approx(
            roc_auc(SparseEvaluator(other)(volume).ravel(), wrong) / full
        )
    with pytest.raises(Exception, match='CVA-Net-Fast'):
        _auc_rel(configs, [crop], net, lambda _text: None, {'cvanet_lite': lite})
    assert rel['exact'] == 1.0 and 'bf16' not in rel  # bf16 only when its row is asked for
    assert rel['lite+stride2'] != rel['lite'] and rel['stride2'] != rel['lite+stride2']

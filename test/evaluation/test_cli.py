"""End-to-end tests of ``cva-evaluate`` on the scikit-image Motorcycle pair, shrunk small."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cva_confidence_ros.evaluation import RECORD_KEYS
from cva_confidence_ros.evaluation.cli import main, parse_weights

pytest.importorskip('skimage')

# 1/8 of 741×500: 92×62 px; the largest disparity (~60 px at full size) shrinks to ~7.5 px.
_SMALL = ['--dataset', 'motorcycle', '--downsample', '8', '--max-disparity', '16']


def _rows(table: str) -> list[list[str]]:
    return [[c.strip() for c in line.strip('|').split('|')] for line in table.strip().split('\n')]


def test_handcrafted_methods_end_to_end(tmp_path, capsys) -> None:
    out = tmp_path / 'out'
    json_path = tmp_path / 'r.json'
    code = main([*_SMALL, '--matchers', 'census_bm', '--methods', 'pkrn,mlm,lrd',
                 '--json', str(json_path), '--out', str(out)])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    records = json.loads(json_path.read_text())
    assert [r['method'] for r in records] == ['pkrn', 'mlm', 'lrd']
    for record in records:
        assert list(record) == list(RECORD_KEYS)
        assert record['dataset'] == 'motorcycle' and record['matcher'] == 'census_bm'
        assert 0.0 < record['auc_opt'] <= record['auc'] <= record['error_rate'] + 1e-9
        assert record['n_pixels'] > 0.5 * 92 * 62  # dense ground truth
    # All methods share the disparity map, hence the error rate, AUC_opt and pixel count.
    assert len({(r['error_rate'], r['auc_opt'], r['n_pixels']) for r in records}) == 1

    rows = _rows(captured.out)
    assert rows[0] == ['data set', 'matcher', 'Opt.', 'pkrn', 'mlm', 'lrd']
    assert rows[2][:3] == ['motorcycle', 'census_bm', f"{100 * records[0]['auc_opt']:.2f}"]
    best = min(records, key=lambda r: r['auc'])
    assert f"**{100 * best['auc']:.2f}**" in rows[2]
    assert (out / 'table.md').read_text() == captured.out
    assert '[1/1] motorcycle/' in captured.err and 'pkrn' in captured.err

    scene_dir = next((out / 'motorcycle').iterdir()) / 'census_bm'
    names = sorted(p.name for p in scene_dir.iterdir())
    assert names == sorted(['disparity.png', 'roc.png'] + [
        f'{kind}_{m}.png' for kind in ('confidence', 'correct') for m in ('pkrn', 'mlm', 'lrd')
    ])
    # Hand-crafted measures are no probabilities: no calibration report.
    assert not (out / 'calibration.json').exists() and not list(out.glob('reliability_*'))


def test_cva_net_patch_mode_with_random_weights(tmp_path, capsys) -> None:
    torch = pytest.importorskip('torch')
    from cva_confidence_ros.model import CVANet, save_weights

    torch.manual_seed(0)
    weights = tmp_path / 'random.pt'
    save_weights(CVANet(16), weights, {'matcher': 'census_bm'})
    json_path = tmp_path / 'r.json'
    code = main([*_SMALL, '--matchers', 'census_bm', '--methods', 'cva_net,score',
                 '--weights', f'census_bm={weights}', '--max-pixels', '200', '--seed', '3',
                 '--json', str(json_path), '--out', str(tmp_path / 'out')])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    records = json.loads(json_path.read_text())
    assert [r['method'] for r in records] == ['cva_net', 'score']
    assert all(r['n_pixels'] == 200 for r in records)
    assert records[0]['error_rate'] == records[1]['error_rate']
    assert 0.0 <= records[0]['auc'] <= 1.0
    assert np.isfinite(records[0]['auc'])

    # CVA-Net's output is meant as a probability: its calibration on the same 200 pixels.
    out = tmp_path / 'out'
    calibration = json.loads((out / 'calibration.json').read_text())
    assert [(c['dataset'], c['matcher'], c['method']) for c in calibration] == [
        ('motorcycle', 'census_bm', 'cva_net')
    ]
    row = calibration[0]
    assert row['n_pixels'] == 200 and sum(row['bins']['counts']) == 200
    assert row['accuracy'] == pytest.approx(1.0 - records[0]['error_rate'])
    assert 0.0 <= row['ece'] <= 1.0 and 0.0 <= row['brier'] <= 1.0
    table = _rows((out / 'calibration.md').read_text())
    assert table[0][:5] == ['data set', 'matcher', 'method', 'pixels', 'ECE %']
    assert table[2][:5] == ['motorcycle', 'census_bm', 'cva_net', '200', f"{100 * row['ece']:.2f}"]
    assert (out / 'reliability_motorcycle_census_bm.png').stat().st_size > 0
    assert (next((out / 'motorcycle').iterdir()) / 'census_bm' / 'reliability.png').exists()
    assert 'calibration motorcycle census_bm cva_net' in captured.err

    # Same seed, same subset, same numbers; another seed draws other pixels.
    again = tmp_path / 'again.json'
    assert main([*_SMALL, '--matchers', 'census_bm', '--methods', 'score', '--max-pixels',
                 '200', '--seed', '3', '--json', str(again)]) == 0
    assert json.loads(again.read_text())[0] == records[1]


@pytest.mark.parametrize(
    ('args', 'message'),
    [
        (['--dataset', 'nope', '--matchers', 'census_bm', '--methods', 'pkrn'],
         'unknown data set'),
        (['--dataset', 'motorcycle', '--matchers', 'sad', '--methods', 'pkrn'], 'unknown matcher'),
        (['--dataset', 'motorcycle', '--matchers', 'census_bm', '--methods', 'magic'],
         'unknown confidence method'),
        (['--dataset', 'kitti2015', '--matchers', 'census_bm', '--methods', 'pkrn'], 'kitti2015'),
        (['--dataset', 'motorcycle', '--matchers', 'census_bm', '--methods', 'pkrn',
          '--weights', 'census_sgm=x.pt'], 'census_sgm'),
        (['--dataset', 'motorcycle', '--matchers', 'census_bm', '--methods', 'pkrn',
          '--max-pixels', '0'], '--max-pixels'),
    ],
)
def test_bad_input_exits_2_with_one_line(tmp_path, capsys, args, message) -> None:
    empty_root = tmp_path / 'empty'
    empty_root.mkdir()
    code = main([*args, '--data-root', str(empty_root), '--json', str(tmp_path / 'r.json')])
    err = capsys.readouterr().err
    assert code == 2
    assert err.count('\n') == 1 and err.startswith('cva-evaluate: error:')
    assert message in err
    assert not (tmp_path / 'r.json').exists()


def test_weights_for_another_depth_exit_2(tmp_path, capsys) -> None:
    pytest.importorskip('torch')
    from cva_confidence_ros.model import CVANet, save_weights

    weights = tmp_path / 'd32.pt'
    save_weights(CVANet(32), weights, {'matcher': 'census_bm'})
    code = main([*_SMALL, '--matchers', 'census_bm', '--methods', 'cva_net',
                 '--weights', str(weights), '--json', str(tmp_path / 'r.json')])
    err = capsys.readouterr().err
    assert code == 2 and err.count('\n') == 1 and 'cva-evaluate: error:' in err


def test_parse_weights() -> None:
    matchers = ['census_bm', 'mccnn_fast']
    assert parse_weights(None, matchers) == {'census_bm': None, 'mccnn_fast': None}
    assert parse_weights('w.pt', matchers) == {'census_bm': 'w.pt', 'mccnn_fast': 'w.pt'}
    assert parse_weights('mccnn_fast=a.pt', matchers) == {'census_bm': None, 'mccnn_fast': 'a.pt'}
    assert parse_weights('census_bm=a.pt, mccnn_fast=b.pt', matchers) == {
        'census_bm': 'a.pt', 'mccnn_fast': 'b.pt'}


def test_output_paths_and_options_are_checked_before_any_work(tmp_path, capsys) -> None:
    afile = tmp_path / 'afile'
    afile.write_text('not a folder')
    base = ['--dataset', 'motorcycle', '--matchers', 'census_bm', '--methods', 'pkrn',
            '--max-pixels', '10']
    records = ['--json', str(tmp_path / 'r.json')]
    cases = [
        (['--json', str(tmp_path)], '--json', 'is a folder; expected a file'),
        (['--json', str(afile / 'r.json')], '--json', 'is a file, not a folder'),
        ([*records, '--out', str(afile)], '--out', 'is a file; expected a folder'),
        ([*records, '--seed', '-1'], '--seed', 'must be ≥ 0'),
        ([*records, '--tile-budget-mb', 'nan'], '--tile-budget-mb', 'finite'),
    ]
    for extra, option, message in cases:
        assert main([*base, *extra]) == 2
        err = capsys.readouterr().err
        # One line, and before the scene was loaded (that would log a 'loaded' line first).
        assert err.count('\n') == 1 and err.startswith(f'cva-evaluate: error: {option}')
        assert message in err
    assert not (tmp_path / 'r.json').exists()


def test_parse_weights_keeps_a_path_with_an_equals_sign_whole(tmp_path, monkeypatch) -> None:
    matchers = ['census_bm', 'mccnn_fast']
    # Experiment folders are often named key=value (hydra, sweeps): one PATH, not a pair.
    path = 'runs/lr=1e-3/cvanet_census_bm_d64.pt'
    assert parse_weights(path, matchers) == {'census_bm': path, 'mccnn_fast': path}
    assert parse_weights(f'census_bm={path}', matchers) == {'census_bm': path,
                                                           'mccnn_fast': None}
    monkeypatch.chdir(tmp_path)
    (tmp_path / 'lr=0.1.pt').write_bytes(b'')  # an existing file in the working folder
    assert parse_weights('lr=0.1.pt', matchers) == {'census_bm': 'lr=0.1.pt',
                                                    'mccnn_fast': 'lr=0.1.pt'}

"""``cva-table1`` on a tiny synthetic data root in the KITTI / Middlebury layouts."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from cva_confidence_ros.datasets import list_scenes
from cva_confidence_ros.datasets.io import write_pfm
from cva_confidence_ros.datasets.synthetic import synthetic_pair
from cva_confidence_ros.evaluation.table1 import (
    COLUMNS,
    PAPER_TABLE1,
    format_paper_table1,
    format_table1,
    main,
    resolve_protocol,
    table_rows,
)

D = 16


@pytest.fixture(autouse=True)
def _restore_threads():
    import numba

    threads, numba_threads = torch.get_num_threads(), numba.get_num_threads()
    yield
    numba.set_num_threads(numba_threads)
    torch.set_num_threads(threads)


def _write_kitti(root: Path, name: str, seeds: list[int], dirs: tuple[str, str, str]) -> None:
    base = root / name / 'training'
    for folder in dirs:
        (base / folder).mkdir(parents=True, exist_ok=True)
    for number, seed in enumerate(seeds):
        pair = synthetic_pair(seed, 40, 64, D)
        stem = f'{number:06d}_10.png'
        cv2.imwrite(str(base / dirs[0] / stem), cv2.cvtColor(pair.left, cv2.COLOR_RGB2BGR)
                    if pair.left.ndim == 3 else pair.left)
        cv2.imwrite(str(base / dirs[1] / stem), cv2.cvtColor(pair.right, cv2.COLOR_RGB2BGR)
                    if pair.right.ndim == 3 else pair.right)
        gt = np.where(np.isfinite(pair.disparity), pair.disparity * 256.0, 0.0)
        gt[::3] = 0  # sparse, like LiDAR
        cv2.imwrite(str(base / dirs[2] / stem), gt.astype(np.uint16))


def _write_middlebury(root: Path, scene: str, seed: int) -> None:
    folder = root / 'middlebury2014' / 'trainingQ' / scene
    folder.mkdir(parents=True)
    pair = synthetic_pair(seed, 40, 64, D)
    for name, image in (('im0.png', pair.left), ('im1.png', pair.right)):
        cv2.imwrite(str(folder / name),
                    cv2.cvtColor(image, cv2.COLOR_RGB2BGR) if image.ndim == 3 else image)
    write_pfm(folder / 'disp0GT.pfm', np.where(np.isfinite(pair.disparity), pair.disparity,
                                               np.inf).astype(np.float32))


@pytest.fixture(scope='module')
def data_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp('data')
    # Five pairs: with --kitti2012-train 1 the paper protocol leaves out 1 + 3 and scores one.
    _write_kitti(root, 'kitti2012', [101, 102, 103, 104, 105],
                 ('colored_0', 'colored_1', 'disp_occ'))
    _write_kitti(root, 'kitti2015', [201, 202], ('image_2', 'image_3', 'disp_occ_0'))
    _write_middlebury(root, 'Synth', 301)
    return root


def test_rows_per_protocol(data_root):
    develop = table_rows('develop', data_root)
    assert [r.label for r in develop] == ['KITTI 2012', 'KITTI 2015', 'Middlebury v3',
                                          'Middlebury 2003 (extra)']
    assert 'training split' in develop[0].missing
    assert develop[1].missing == '' and develop[2].missing == ''
    assert 'no middlebury2003 pairs' in develop[3].missing
    paper = table_rows('paper', data_root, kitti2012_train=1)
    assert [(r.label, r.first, r.missing) for r in paper] == [
        ('KITTI 2012', 4, ''), ('KITTI 2015', 0, ''), ('Middlebury v3', 0, '')]
    assert 'no kitti2012' in table_rows('paper', data_root, kitti2012_train=2)[0].missing


def test_format_bold_and_missing():
    rows = table_rows('develop', Path('/nonexistent'))
    records = [
        {'row': 'KITTI 2015', 'scene': s, 'matcher': 'census_bm', 'method': m, 'auc': a,
         'auc_opt': 0.01}
        for s, m, a in [('a', 'ccnn', 0.05), ('b', 'ccnn', 0.07), ('a', 'pkrn', 0.04),
                        ('b', 'pkrn', 0.08)]
    ]
    table = format_table1(records, rows, ['census_bm'], [('ccnn', 'CCNN'), ('pkrn', 'PKRN')])
    lines = table.splitlines()
    assert lines[0] == '| data set | matcher | Opt. | CCNN | PKRN |'
    assert '| KITTI 2015 | Census-BM | 1.00 | **6.00** | **6.00** |' in lines  # tie: both
    assert '| KITTI 2012 | Census-BM | – | – | – |' in lines
    paper = format_paper_table1()
    assert '| Middlebury v3 | Census-SGM | 2.26 | 5.58 | 6.14 | **5.33** | 5.40 |' in paper
    assert PAPER_TABLE1['KITTI 2012']['census_bm'][4] == 11.52


def test_table1_trains_missing_weights_and_writes_outputs(data_root, tmp_path, capsys):
    out = tmp_path / 'out'
    # CVA-Net is left out here (its CPU inference alone would take minutes); the last run
    # below adds it with weights from the weights folder.
    methods = [m for m, _ in COLUMNS if m != 'cva_net']
    args = ['--data-root', str(data_root), '--out', str(out), '--matchers', 'census_bm',
            '--max-disparity', str(D), '--max-pixels', '300', '--weights-dir',
            str(tmp_path / 'w'), '--threads', '1', '--protocol', 'develop',
            '--methods', ','.join(methods)]
    # Without weights (D = 16 is shipped for nothing) and without --train-missing: exit 2.
    assert main(args) == 2
    assert 'no weights for' in capsys.readouterr().err
    quick = ['--train-missing', '--train-scale', '0.002', '--train-datasets', 'none',
             '--train-synthetic', '2', '--train-synthetic-size', '48x64']
    assert main([*args, *quick]) == 0
    for arch in ('ccnn', 'lfn', 'lgcnet'):
        assert (tmp_path / 'w' / f'{arch}_census_bm_d16.pt').is_file()
    markdown = (out / 'table1.md').read_text()
    header = '| data set | matcher | Opt. | ' + ' | '.join(
        t for m, t in COLUMNS if m in methods) + ' |'
    assert header in markdown
    kitti15 = next(line for line in markdown.splitlines()
                   if line.startswith('| KITTI 2015 | Census-BM |'))
    assert kitti15.count('**') >= 2 and '–' not in kitti15
    assert 'KITTI 2012: not scored' in markdown and "paper's Table 1" in markdown
    summary = json.loads((out / 'table1.json').read_text())
    assert summary['protocol'] == 'develop'
    assert 'mean of the per-scene values' in summary['cells_are']  # as table1.md says
    assert {r['row'] for r in summary['records']} == {'KITTI 2015', 'Middlebury v3'}
    assert {r['method'] for r in summary['records']} == set(methods)
    assert all(0 <= r['auc'] <= 1 and r['n_pixels'] <= 300 for r in summary['records'])
    assert (out / 'table1.png').stat().st_size > 1000
    # A second run finds the trained weights and gives the same numbers.
    again = tmp_path / 'again'
    assert main([*args[:3], str(again), *args[4:]]) == 0
    assert json.loads((again / 'table1.json').read_text())['cells'] == summary['cells']
    # --reuse takes records over (checked by pixel count and error rate) instead of scoring.
    taken = [dict(r, auc=0.5) for r in summary['records'] if r['method'] == 'ccnn']
    (tmp_path / 'old.json').write_text(json.dumps(taken))
    reuse = tmp_path / 'reuse'
    assert main([*args[:3], str(reuse), *args[4:], '--reuse', str(tmp_path / 'old.json')]) == 0
    cells = json.loads((reuse / 'table1.json').read_text())['cells']
    assert {c['ccnn'] for c in cells} == {50.0}
    assert [c['pkrn'] for c in cells] == [c['pkrn'] for c in summary['cells']]
    (tmp_path / 'bad.json').write_text(json.dumps([dict(r, error_rate=0.9) for r in taken]))
    assert main([*args[:3], str(reuse), *args[4:], '--reuse', str(tmp_path / 'bad.json')]) == 2
    assert 'scored on other pixels' in capsys.readouterr().err
    # All columns, CVA-Net from (random) weights in the weights folder, on a few pixels.
    from cva_confidence_ros.model import CVANet, save_weights

    torch.manual_seed(0)
    save_weights(CVANet(D), tmp_path / 'w' / 'cvanet_census_bm_d16.pt', {'matcher': 'census_bm'})
    full = tmp_path / 'full'
    assert main([*args[:3], str(full), *args[4:-2], '--max-pixels', '20']) == 0
    records = json.loads((full / 'table1.json').read_text())['records']
    assert {r['method'] for r in records} == {m for m, _ in COLUMNS}


def test_paper_protocol_on_a_tiny_root(data_root, tmp_path):
    out = tmp_path / 'paper'
    code = main(['--data-root', str(data_root), '--out', str(out), '--matchers', 'census_bm',
                 '--methods', 'pkrn,score', '--max-disparity', str(D), '--kitti2012-train',
                 '1', '--threads', '1'])
    assert code == 0
    summary = json.loads((out / 'table1.json').read_text())
    assert summary['protocol'] == 'paper'
    scored = {(r['row'], r['scene']) for r in summary['records']}
    assert scored == {('KITTI 2012', '000004'), ('KITTI 2015', '000000'),
                      ('KITTI 2015', '000001'), ('Middlebury v3', 'Synth')}


def test_paper_protocol_scores_the_papers_171_kitti2012_pairs(tmp_path):
    """Paper Sec. 4.2: the 23 pairs used for training and validating are not scored."""
    base = tmp_path / 'kitti2012' / 'training'
    for folder in ('colored_0', 'colored_1', 'disp_occ'):
        (base / folder).mkdir(parents=True)
    for number in range(194):  # the full download; the loader only lists the files
        for folder in ('colored_0', 'colored_1', 'disp_occ'):
            (base / folder / f'{number:06d}_10.png').touch()
    row = table_rows('paper', tmp_path)[0]
    assert (row.label, row.first, row.missing) == ('KITTI 2012', 23, '')
    assert len(list_scenes('kitti2012', tmp_path)[row.first:]) == 171
    assert resolve_protocol('auto', tmp_path, 20) == 'paper'
    assert resolve_protocol('auto', tmp_path, 191) == 'develop'  # 191 + 3 pairs: none left
    assert 'no kitti2012' in table_rows('paper', tmp_path, kitti2012_train=191)[0].missing


def test_bad_options_and_reuse_files_exit_2_before_any_work(data_root, tmp_path, capsys):
    afile = tmp_path / 'afile'
    afile.write_text('not a folder')
    base = ['--data-root', str(data_root), '--matchers', 'census_bm', '--methods', 'pkrn',
            '--max-disparity', str(D), '--max-pixels', '50']
    out = ['--out', str(tmp_path / 'out')]
    cases = [
        (['--out', str(afile)], '--out', 'is a file'),
        ([*out, '--weights-dir', str(afile)], '--weights-dir', 'is a file'),
        ([*out, '--threads', '0'], '--threads', 'must be ≥ 1'),
        ([*out, '--max-scenes', '0'], '--max-scenes', 'must be ≥ 1'),
        ([*out, '--kitti2012-train', '-1'], '--kitti2012-train', 'must be ≥ 0'),
        ([*out, '--seed', '-1'], '--seed', 'must be ≥ 0'),
        ([*out, '--max-disparity', '0'], '--max-disparity', 'must be in [1, 1024]'),
        ([*out, '--train-datasets', 'kitti2012,nosuch'], "'nosuch'", 'unknown data set'),
        ([*out, '--train-datasets', 'kitti2012:train,kitti2015'], 'kitti2015',
         'is a develop data set'),
    ]
    for extra, option, message in cases:
        assert main([*base, *extra]) == 2
        err = capsys.readouterr().err
        assert err == f'cva-table1: error: {err.split("error: ", 1)[1]}'
        assert err.count('\n') == 1 and option in err and message in err
    reuse = tmp_path / 'reuse.json'
    for text, message in [('[1, 2]', 'must be a JSON object; got int'),
                          ('{"records": 5}', 'expected a list of records')]:
        reuse.write_text(text)
        assert main([*base, *out, '--reuse', str(reuse)]) == 2
        assert message in capsys.readouterr().err.splitlines()[-1]
    assert not (tmp_path / 'out' / 'table1.md').exists()


def _root_with_a_bad_scene(tmp_path: Path) -> Path:
    """Middlebury v3 with three scenes, the middle one's right image an empty file."""
    root = tmp_path / 'data'
    for scene, seed in (('A', 401), ('B', 402), ('C', 403)):
        _write_middlebury(root, scene, seed)
    (root / 'middlebury2014' / 'trainingQ' / 'B' / 'im1.png').write_bytes(b'')
    return root


def test_evaluate_skips_a_bad_scene_writes_the_rest_and_exits_2(tmp_path, capsys):
    from cva_confidence_ros.evaluation.cli import main as evaluate

    root = _root_with_a_bad_scene(tmp_path)
    records, out = tmp_path / 'r.json', tmp_path / 'out'
    code = evaluate(['--data-root', str(root), '--dataset', 'middlebury2014', '--matchers',
                     'census_bm', '--methods', 'pkrn,score', '--max-disparity', str(D),
                     '--max-pixels', '200', '--json', str(records), '--out', str(out)])
    err = capsys.readouterr().err
    assert code == 2
    assert '[2/3] middlebury2014/B skipped: ' in err and 'im1.png' in err
    assert 'cva-evaluate: error: 1 of 3 scenes could not be used' in err
    written = json.loads(records.read_text())
    assert sorted({r['scene'] for r in written}) == ['A', 'C'] and len(written) == 4
    assert '**Partial: 2 of 3 scenes**' in (out / 'table.md').read_text()
    # Every scene bad: nothing to write, and the first reason is the error.
    for scene in ('A', 'C'):
        (root / 'middlebury2014' / 'trainingQ' / scene / 'im1.png').write_bytes(b'')
    records.unlink()
    assert evaluate(['--data-root', str(root), '--dataset', 'middlebury2014', '--matchers',
                     'census_bm', '--methods', 'pkrn', '--max-disparity', str(D),
                     '--json', str(records)]) == 2
    assert 'no scene could be evaluated; middlebury2014/A: ' in capsys.readouterr().err
    assert not records.exists()


def test_table1_keeps_the_scenes_done_when_interrupted(tmp_path, capsys, monkeypatch):
    from cva_confidence_ros.evaluation import scene as scene_module

    root = tmp_path / 'data'
    for scene, seed in (('A', 401), ('B', 402), ('C', 403)):
        _write_middlebury(root, scene, seed)
    real = scene_module.evaluate_scene
    calls = []

    def interrupted_on_the_second_scene(sample, *args, **kwargs):
        calls.append(sample)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(sample, *args, **kwargs)

    monkeypatch.setattr(scene_module, 'evaluate_scene', interrupted_on_the_second_scene)
    out = tmp_path / 'out'
    code = main(['--data-root', str(root), '--out', str(out), '--matchers', 'census_bm',
                 '--methods', 'pkrn', '--max-disparity', str(D), '--max-pixels', '100',
                 '--protocol', 'develop', '--threads', '1'])
    err = capsys.readouterr().err
    assert code == 130 and 'cva-table1: interrupted after 1 of 3 scenes' in err
    summary = json.loads((out / 'table1.json').read_text())
    assert [r['scene'] for r in summary['records']] == ['A']
    assert summary['partial'].startswith('**Partial: 1 of 3 scenes** — interrupted')
    assert '**Partial: 1 of 3 scenes**' in (out / 'table1.md').read_text()


def test_a_binary_reuse_file_exits_2_with_one_line(data_root, tmp_path, capsys):
    reuse = tmp_path / 'reuse.json'
    reuse.write_bytes(b'\x89PNG\r\n\x1a\n\xff\xfe')
    code = main(['--data-root', str(data_root), '--matchers', 'census_bm', '--methods', 'pkrn',
                 '--max-disparity', str(D), '--max-pixels', '50', '--out',
                 str(tmp_path / 'out'), '--reuse', str(reuse)])
    err = capsys.readouterr().err
    assert code == 2
    last = err.splitlines()[-1]
    assert last.startswith(f'cva-table1: error: cannot read --reuse records {reuse}')
    assert not (tmp_path / 'out' / 'table1.md').exists()


def test_a_bad_reuse_file_is_refused_before_missing_weights_are_trained(
    data_root, tmp_path, capsys, monkeypatch
):
    # With --train-missing the reuse file used to be read only after the training (hours).
    from cva_confidence_ros.evaluation import table1

    trained = []
    monkeypatch.setattr(table1, '_train', lambda *args: trained.append(args))
    reuse = tmp_path / 'reuse.json'
    reuse.write_text(json.dumps([{'dataset': 'kitti2015', 'scene': '000000',
                                  'matcher': 'census_bm', 'method': 'cva_net', 'auc': 'nan',
                                  'auc_opt': 0.01, 'error_rate': 0.1, 'n_pixels': 50}]))
    code = main(['--data-root', str(data_root), '--matchers', 'census_bm', '--methods',
                 'cva_net', '--max-disparity', str(D), '--weights-dir', str(tmp_path / 'none'),
                 '--train-missing', '--max-pixels', '50', '--out', str(tmp_path / 'out'),
                 '--reuse', str(reuse)])
    assert code == 2
    assert 'auc must be a number in [0, 1]; got nan' in capsys.readouterr().err
    assert trained == []

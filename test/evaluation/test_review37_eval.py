"""Review 37: left-out frames of sceneflow_extra / tartanair, partial runs of cva-evaluate and
cva-table1, the recorded range of the confidence PNGs, and the AUC protocol against an
independent implementation."""

from __future__ import annotations

from fractions import Fraction
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from cva_confidence_ros.datasets import StereoSample, list_scenes, skipped_scenes
from cva_confidence_ros.datasets.io import write_pfm
from cva_confidence_ros.datasets.synthetic import synthetic_pair
from cva_confidence_ros.metrics import auc_scores, kitti_error, optimal_auc, roc_auc

D = 16


def _png(path: Path, image: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), image)


GREY = np.zeros((8, 10), np.uint8)


def test_sceneflow_extra_names_frames_left_out_for_a_missing_file(tmp_path: Path) -> None:
    # Layout 1: a/{Left,Right,Disparity}/<id>; layout 2: b/RGB_cleanpass/{left,right}, …
    for stem in ('0001', '0002'):
        _png(tmp_path / 'a' / 'Left' / f'{stem}.png', GREY)
        (tmp_path / 'a' / 'Disparity').mkdir(parents=True, exist_ok=True)
        write_pfm(tmp_path / 'a' / 'Disparity' / f'{stem}.pfm', np.ones((8, 10), np.float32))
        (tmp_path / 'b' / 'disparity' / 'left').mkdir(parents=True, exist_ok=True)
        write_pfm(tmp_path / 'b' / 'disparity' / 'left' / f'{stem}.pfm',
                  np.ones((8, 10), np.float32))
        _png(tmp_path / 'b' / 'RGB_cleanpass' / 'right' / f'{stem}.png', GREY)
    _png(tmp_path / 'a' / 'Right' / '0001.png', GREY)
    _png(tmp_path / 'b' / 'RGB_cleanpass' / 'left' / '0001.png', GREY)
    assert list_scenes('sceneflow_extra', tmp_path) == ['a/0001', 'b/0001']
    # Before: [] (the frames were dropped unsaid).
    assert skipped_scenes('sceneflow_extra', tmp_path) == [
        ('a/0002', 'no Right/0002.png'),
        ('b/0002', 'no RGB_cleanpass/left/0002.png'),
    ]


def test_tartanair_names_frames_left_out_for_a_missing_file(tmp_path: Path) -> None:
    flat = tmp_path / 'P000'
    for frame in ('000000', '000001'):
        _png(flat / f'{frame}_left.png', GREY)
        np.save(flat / f'{frame}_left_disp.npy', np.ones((8, 10), np.float32))
    _png(flat / '000000_right.png', GREY)
    nested = tmp_path / 'abandonedfactory' / 'Easy' / 'P001'
    (nested / 'depth_left').mkdir(parents=True)
    for frame in ('000000', '000001'):
        np.save(nested / 'depth_left' / f'{frame}_left_depth.npy', np.ones((8, 10), np.float32))
        _png(nested / 'image_right' / f'{frame}_right.png', GREY)
    _png(nested / 'image_left' / '000000_left.png', GREY)
    assert list_scenes('tartanair', tmp_path) == [
        'P000/000000', 'abandonedfactory/Easy/P001/000000'
    ]
    assert skipped_scenes('tartanair', tmp_path) == [
        ('P000/000001', 'no 000001_right.png'),
        ('abandonedfactory/Easy/P001/000001', 'no image_left/000001_left.png'),
    ]


def _stereo_folder(root: Path, scenes: tuple[str, ...], lacking: str) -> Path:
    for number, scene in enumerate(scenes):
        pair = synthetic_pair(500 + number, 40, 64, D)
        folder = root / scene
        _png(folder / 'left.png', cv2.cvtColor(pair.left, cv2.COLOR_RGB2BGR))
        if scene != lacking:
            _png(folder / 'right.png', cv2.cvtColor(pair.right, cv2.COLOR_RGB2BGR))
        write_pfm(folder / 'disparity.pfm', pair.disparity.astype(np.float32))
    return root


def test_evaluate_marks_a_run_with_a_left_out_scene_partial(tmp_path, capsys) -> None:
    from cva_confidence_ros.evaluation.cli import main

    root = _stereo_folder(tmp_path / 'data', ('s1', 's2', 's3'), lacking='s2')
    base = ['--data-root', str(root), '--dataset', 'stereo_folder', '--matchers', 'census_bm',
            '--methods', 'pkrn', '--max-disparity', str(D), '--max-pixels', '200']
    out = tmp_path / 'out'
    # Before: exit status 0 and a table with no mark, the scene named only in a log line.
    assert main([*base, '--json', str(tmp_path / 'a.json'), '--out', str(out)]) == 2
    err = capsys.readouterr().err
    assert 'cva-evaluate: error: 1 of 3 scenes left out for a missing file' in err
    assert 'stereo_folder/s2: no right image' in err and '--allow-missing-files' in err
    table = (out / 'table.md').read_text()
    assert '**Partial: 2 of 3 scenes**' in table and 'stereo_folder/s2 (no right image' in table
    assert {r['scene'] for r in json.loads((tmp_path / 'a.json').read_text())} == {'s1', 's3'}
    # Accepted explicitly: exit status 0, still marked.
    assert main([*base, '--json', str(tmp_path / 'b.json'), '--out', str(out),
                 '--allow-missing-files']) == 0
    assert 'cva-evaluate: warning: 1 of 3 scenes left out' in capsys.readouterr().err
    assert '**Partial: 2 of 3 scenes**' in (out / 'table.md').read_text()
    # --max-scenes 1 takes s1 only: s2 was not among the scenes asked for.
    assert main([*base, '--json', str(tmp_path / 'c.json'), '--max-scenes', '1']) == 0


def test_table1_marks_a_row_with_a_left_out_scene_partial(tmp_path, capsys) -> None:
    from cva_confidence_ros.evaluation.table1 import main

    base = tmp_path / 'data' / 'kitti2015' / 'training'
    for number in range(3):
        pair = synthetic_pair(600 + number, 40, 64, D)
        stem = f'{number:06d}_10.png'
        _png(base / 'image_2' / stem, cv2.cvtColor(pair.left, cv2.COLOR_RGB2BGR))
        if number != 1:
            _png(base / 'image_3' / stem, cv2.cvtColor(pair.right, cv2.COLOR_RGB2BGR))
        gt = np.where(np.isfinite(pair.disparity), pair.disparity * 256.0, 0.0)
        _png(base / 'disp_occ_0' / stem, gt.astype(np.uint16))
    out = tmp_path / 'out'
    args = ['--data-root', str(tmp_path / 'data'), '--out', str(out), '--protocol', 'develop',
            '--matchers', 'census_bm', '--methods', 'pkrn', '--max-disparity', str(D),
            '--max-pixels', '200']
    assert main(args) == 2
    assert 'kitti2015/000001: no image_3/000001_10.png' in capsys.readouterr().err
    summary = json.loads((out / 'table1.json').read_text())
    assert summary['partial'].startswith('**Partial: 2 of 3 scenes**')
    assert '**Partial: 2 of 3 scenes**' in (out / 'table1.md').read_text()
    assert main([*args, '--allow-missing-files']) == 0


def test_confidence_png_records_the_values_drawn_black_and_white(tmp_path) -> None:
    from PIL import Image

    from cva_confidence_ros.confidence import CONFIDENCE_METHODS
    from cva_confidence_ros.evaluation.scene import evaluate_scene

    pair = synthetic_pair(7, 40, 64, D)
    sample = StereoSample('synthetic', 'p7', pair.left, pair.right,
                          pair.disparity.astype(np.float32))
    methods = {'pkrn': CONFIDENCE_METHODS.get('pkrn')(matcher='census_bm', max_disparity=D)}
    evaluate_scene(sample, 'census_bm', methods, max_disparity=D, plot_dir=tmp_path)
    image = Image.open(tmp_path / 'confidence_pkrn.png')
    # PKRN is a ratio ≥ 1: stretched over its 1st–99th percentile, now said in the PNG.
    assert 1.0 <= float(image.text['vmin']) < float(image.text['vmax'])
    assert 'percentile' in image.text['Description'] and 'τ = ' in image.text['Description']
    assert 'synthetic/p7 census_bm pkrn: black = ' in image.text['Description']
    # Still a plain RGB PNG pixel for pixel (OpenCV reads it).
    assert cv2.imread(str(tmp_path / 'confidence_pkrn.png')).shape == (40, 64, 3)


# Scenario checks of the protocol (they held before too).


def _independent_auc(confidence: np.ndarray, error: np.ndarray) -> float:
    """The paper's ROC with interval points, written from its definition with plain loops."""
    conf = [float(c) for c in confidence]
    wrong = [bool(e) for e in error]
    n = len(conf)
    groups, position = [], 0
    for value in sorted(set(conf), reverse=True):
        members = [e for c, e in zip(conf, wrong, strict=True) if c == value]
        groups.append((position, position + len(members), sum(members)))
        position += len(members)
    points: dict[int, float] = {}
    for k in range(1, 21):
        m = math.ceil(Fraction(k * n, 20))
        before = 0
        for start, end, bad in groups:
            if start < m <= end:
                points[end] = (before + bad) / end
                if m < end:
                    taken, good = m - start, end - start - bad
                    best, worst = before + max(0, taken - good), before + min(taken, bad)
                    points[m] = (best + worst) / 2 / m
                break
            before += bad
    xs = sorted(points)
    return sum((b - a) / n * (points[a] + points[b]) / 2 for a, b in zip(xs, xs[1:], strict=False))


def test_auc_matches_an_independent_implementation() -> None:
    rng = np.random.default_rng(37)
    for _ in range(60):
        n = int(rng.integers(1, 200))
        confidence = rng.integers(0, int(rng.integers(1, 6)), n).astype(np.float32)  # ties
        error = rng.random(n) < rng.random()
        assert roc_auc(confidence, error) == pytest.approx(_independent_auc(confidence, error),
                                                           abs=1e-12)
    error = np.arange(1000) < 300
    for confidence in (np.zeros(1000), (~error).astype(float), error.astype(float)):
        assert roc_auc(confidence, error) == pytest.approx(
            _independent_auc(confidence, error), abs=1e-12)
    perfect = auc_scores((~error).astype(float), error)
    assert perfect['auc'] <= perfect['auc_opt'] < perfect['auc'] + 0.004
    assert optimal_auc(0.3) == pytest.approx(0.3 + 0.7 * math.log(0.7))
    assert optimal_auc(0.0) == 0.0 and optimal_auc(1.0) == 1.0
    assert optimal_auc(1.0, 100) == pytest.approx(0.95)


def test_kitti_criterion_at_its_boundaries() -> None:
    gt = np.array([10.0, 100.0, 100.0, 0.0, np.nan])
    est = np.array([13.0, 105.0, 104.999, 2.999, 50.0])
    # 3 px exactly and 5 % exactly are wrong (strict '<', as the package documents); 0 is a
    # known disparity; no ground truth is never wrong.
    assert kitti_error(est, gt).tolist() == [True, True, False, False, False]


def test_a_run_without_calibration_removes_the_earlier_runs_calibration_files(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # A network's run writes calibration.md/.json and a reliability PNG; a later run of a
    # hand-crafted measure into the same folder left them beside its fresh table.md.
    from cva_confidence_ros.evaluation.cli import main as evaluate

    out = tmp_path / 'out'
    common = ['--dataset', 'motorcycle', '--matchers', 'census_bm', '--max-pixels', '200',
              '--downsample', '4', '--max-disparity', '64', '--out', str(out)]
    first = [*common, '--methods', 'cva_net_fast', '--json', str(tmp_path / 'a.json')]
    assert evaluate(first) == 0
    names = {'calibration.json', 'calibration.md', 'reliability_motorcycle_census_bm.png'}
    assert names <= {path.name for path in out.iterdir()}
    capsys.readouterr()
    assert evaluate([*common, '--methods', 'pkrn', '--json', str(tmp_path / 'b.json')]) == 0
    assert not names & {path.name for path in out.iterdir()}
    assert 'removed 3 calibration file(s) of an earlier run' in capsys.readouterr().err
    assert (out / 'table.md').is_file()
    # Nor do the scene's PNGs of the earlier run's method stay beside this run's.
    (scene,) = {path.parent for path in out.rglob('confidence_*.png')}
    assert sorted(path.name for path in scene.glob('*.png')) == [
        'confidence_pkrn.png', 'correct_pkrn.png', 'disparity.png', 'roc.png'
    ]

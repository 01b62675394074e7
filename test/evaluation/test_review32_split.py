"""``cva-evaluate --split`` for several data sets: one split where it exists, or per data set."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.evaluation.cli import main, parse_splits

H, W, D = 16, 40, 3


def _pair(folder: Path, left: str, right: str) -> None:
    """A textured pair with ``left[y, x] = right[y, x - D]``."""
    wide = np.random.default_rng(0).integers(0, 256, (H, W + D), np.uint8)
    for path, image in ((folder / left, wide[:, D:]), (folder / right, wide[:, :W])):
        path.parent.mkdir(parents=True, exist_ok=True)
        assert cv2.imwrite(str(path), image)


def _data_root(root: Path) -> Path:
    kitti = root / 'kitti2015' / 'training'
    _pair(kitti, 'image_2/000000_10.png', 'image_3/000000_10.png')
    (kitti / 'disp_occ_0').mkdir(parents=True)
    assert cv2.imwrite(str(kitti / 'disp_occ_0' / '000000_10.png'),
                       np.full((H, W), D * 256, np.uint16))
    from cva_confidence_ros.datasets import write_pfm

    folder = root / 'middlebury2014' / 'trainingH' / 'Tiny'
    _pair(folder, 'im0.png', 'im1.png')
    write_pfm(folder / 'disp0GT.pfm', np.full((H, W), D, np.float32))
    return root


def test_a_bare_split_goes_to_the_data_sets_that_have_it() -> None:
    splits = parse_splits('trainingH', ['kitti2015', 'middlebury2003', 'middlebury2014'])
    assert splits == {'kitti2015': None, 'middlebury2003': None, 'middlebury2014': 'trainingH'}
    assert parse_splits(None, ['kitti2015']) == {'kitti2015': None}


def test_pairs_name_one_split_per_data_set() -> None:
    splits = parse_splits(' middlebury2014 = trainingF , kitti2015=training',
                          ['kitti2015', 'middlebury2014'])
    assert splits == {'kitti2015': 'training', 'middlebury2014': 'trainingF'}


@pytest.mark.parametrize(('text', 'datasets', 'message'), [
    ('trainingX', ['kitti2015', 'middlebury2014'],
     r"'trainingX': no data set evaluated has it \(kitti2015: \['training'\], middlebury2014"),
    ('trainingQ', ['kitti2015'], r"kitti2015 has splits \['training'\]; got split='trainingQ'"),
    ('eth3d=training', ['kitti2015'], r"names data set 'eth3d', which is not among --dataset"),
    ('kitti2015=trainingQ', ['kitti2015', 'middlebury2014'], r'kitti2015 has splits'),
    ('kitti2015=', ['kitti2015'], r'lacks a split after "="'),
    ('trainingQ,trainingH', ['middlebury2014'], r'expected NAME=SPLIT pairs'),
    (' , ', ['middlebury2014'], r'names no split'),
])
def test_bad_splits_are_named(text: str, datasets: list[str], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        parse_splits(text, datasets)


def test_develop_like_run_with_one_split(tmp_path: Path, capsys) -> None:
    root = _data_root(tmp_path / 'data')
    json_path = tmp_path / 'r.json'
    code = main(['--data-root', str(root), '--dataset', 'kitti2015,middlebury2014',
                 '--split', 'trainingH', '--matchers', 'census_bm', '--methods', 'pkrn',
                 '--max-disparity', '8', '--json', str(json_path)])
    assert code == 0, capsys.readouterr().err
    records = json.loads(json_path.read_text())
    assert [(r['dataset'], r['scene']) for r in records] == [
        ('kitti2015', '000000'), ('middlebury2014', 'Tiny')]
    assert all(r['n_pixels'] > 0 for r in records)


def test_bad_split_exits_2_before_any_work(tmp_path: Path, capsys) -> None:
    code = main(['--data-root', str(tmp_path), '--dataset', 'kitti2015,middlebury2014',
                 '--split', 'middlebury2014=trainingX', '--matchers', 'census_bm',
                 '--methods', 'pkrn', '--json', str(tmp_path / 'r.json')])
    assert code == 2
    assert "middlebury2014 has splits ['trainingQ', 'trainingH', 'trainingF']" in (
        capsys.readouterr().err)

"""Review of the data set loaders and ``cva-evaluate``: regressions on tiny files."""

from __future__ import annotations

import builtins
import errno
import io
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from cva_confidence_ros.datasets import (
    StereoSample,
    list_scenes,
    load_dataset,
    load_scene,
    write_pfm,
)
from cva_confidence_ros.errors import ConfigError, DataError
from cva_confidence_ros.evaluation.cli import main

H, W, D = 16, 32, 3


def write_image(path: Path, image: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), image)


def write_gt_pfm(path: Path, value: float = D) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    write_pfm(path, np.full((H, W), value, np.float32))


def shifted_pair(folder: Path, left: str, right: str) -> None:
    """A textured pair with ``left[y, x] = right[y, x - D]``."""
    wide = np.random.default_rng(0).integers(0, 256, (H, W + D), np.uint8)
    write_image(folder / left, wide[:, D:])
    write_image(folder / right, wide[:, :W])


def middlebury2014_scene(root: Path, split: str = 'trainingQ', scene: str = 'Tiny') -> None:
    folder = root / split / scene
    shifted_pair(folder, 'im0.png', 'im1.png')
    write_gt_pfm(folder / 'disp0GT.pfm')


# --- loaders -------------------------------------------------------------------------------


def test_sample_refuses_negative_ground_truth() -> None:
    image = np.zeros((H, W), np.uint8)
    disparity = np.full((H, W), 2.0, np.float32)
    disparity[3, 5] = -2.0  # right-to-left convention: scored as wrong pixels before
    with pytest.raises(DataError, match=r't/s: disparity must be ≥ 0.*-2 at \(y, x\) = \(3, 5\)'):
        StereoSample('t', 's', image, image, disparity)
    disparity[3, 5] = np.nan  # unknown stays allowed
    assert StereoSample('t', 's', image, image, disparity).max_disparity == 2.0


def test_no_pairs_names_the_split_and_the_splits_that_hold_pairs(tmp_path: Path) -> None:
    middlebury2014_scene(tmp_path, 'trainingF')
    # The default split is trainingQ, which this root lacks.
    with pytest.raises(DataError, match=r"for split 'trainingQ'; split\(s\) \['trainingF'\]"):
        list_scenes('middlebury2014', tmp_path)
    assert list_scenes('middlebury2014', tmp_path, 'trainingF') == ['Tiny']


def test_eth3d_root_may_be_the_training_folder_with_ground_truth_beside_it(
    tmp_path: Path,
) -> None:
    shifted_pair(tmp_path / 'two_view_training' / 'delivery_1l', 'im0.png', 'im1.png')
    gt_folder = tmp_path / 'two_view_training_gt' / 'delivery_1l'
    write_gt_pfm(gt_folder / 'disp0GT.pfm')
    mask = np.full((H, W), 255, np.uint8)
    mask[0, 0] = 128
    write_image(gt_folder / 'mask0nocc.png', mask)
    for root in (tmp_path, tmp_path / 'two_view_training'):
        assert list_scenes('eth3d', root) == ['delivery_1l']
        sample = load_scene('eth3d', root, 'delivery_1l')
        assert np.all(sample.disparity == D)
        assert sample.nonocc is not None and not sample.nonocc[0, 0] and sample.nonocc.sum() == (
            H * W - 1
        )


@pytest.mark.parametrize('max_scenes', [2.5, '3', True])
def test_load_dataset_refuses_a_max_scenes_that_is_no_integer(
    tmp_path: Path, max_scenes: object
) -> None:
    middlebury2014_scene(tmp_path)
    with pytest.raises(ConfigError, match='max_scenes must be an integer'):
        load_dataset('middlebury2014', tmp_path, max_scenes=max_scenes)  # type: ignore[arg-type]


def test_flyingthings3d_scene_of_another_split_is_refused(tmp_path: Path) -> None:
    sequence = 'TEST/A/0000'
    shifted_pair(tmp_path / 'frames_cleanpass' / sequence, 'left/0006.png', 'right/0006.png')
    write_gt_pfm(tmp_path / 'disparity' / sequence / 'left' / '0006.pfm')
    scene = f'{sequence}/0006'
    assert list_scenes('flyingthings3d', tmp_path, 'TEST') == [scene]
    assert load_scene('flyingthings3d', tmp_path, scene, 'TEST').scene == scene
    assert load_scene('flyingthings3d', tmp_path, scene).scene == scene
    with pytest.raises(DataError, match="is in split 'TEST', not in split 'TRAIN'"):
        load_scene('flyingthings3d', tmp_path, scene, 'TRAIN')


# --- cva-evaluate ---------------------------------------------------------------------------


def evaluate(root: Path, *extra: str) -> int:
    return main([
        '--data-root', str(root), '--dataset', 'middlebury2014', '--matchers', 'census_bm',
        '--max-disparity', '8', *extra,
    ])


def test_unknown_method_is_named_before_any_weights_are_looked_for(tmp_path, capsys) -> None:
    middlebury2014_scene(tmp_path)
    code = evaluate(tmp_path, '--methods', 'cva_net,magic', '--weights',
                    str(tmp_path / 'missing.pt'), '--json', str(tmp_path / 'r.json'))
    err = capsys.readouterr().err
    assert code == 2 and err.count('\n') == 1
    assert "unknown confidence method 'magic'" in err and 'pkrn' in err
    assert 'missing.pt' not in err


@pytest.mark.parametrize('name', ['table.md', 'calibration.json', 'calibration.md'])
def test_json_that_out_would_overwrite_is_refused(tmp_path, capsys, name) -> None:
    middlebury2014_scene(tmp_path)
    out = tmp_path / 'out'
    code = evaluate(tmp_path, '--methods', 'pkrn', '--json', str(out / '..' / 'out' / name),
                    '--out', str(out))
    err = capsys.readouterr().err
    assert code == 2 and err.count('\n') == 1
    assert err.startswith('cva-evaluate: error: --json') and f'is the {name} that --out' in err
    assert not (out / name).exists()


def test_table_md_is_replaced_whole_or_not_at_all(tmp_path, capsys, monkeypatch) -> None:
    middlebury2014_scene(tmp_path)
    out = tmp_path / 'out'
    out.mkdir()
    (out / 'table.md').write_text('the table of an earlier run\n', encoding='utf-8')
    real_open = builtins.open

    def full_disk(file, mode='r', *args, **kwargs):  # type: ignore[no-untyped-def]
        handle = real_open(file, mode, *args, **kwargs)
        if 'w' in mode and Path(file).name.startswith('table.md'):
            handle.close()  # opened (and so emptied), then the disk is full
            raise OSError(errno.ENOSPC, 'No space left on device')
        return handle

    monkeypatch.setattr(builtins, 'open', full_disk)
    monkeypatch.setattr(io, 'open', full_disk)
    code = evaluate(tmp_path, '--methods', 'pkrn', '--json', str(tmp_path / 'r.json'),
                    '--out', str(out))
    monkeypatch.undo()
    err = capsys.readouterr().err
    assert code == 2
    assert f'cva-evaluate: error: cannot write {out / "table.md"}' in err
    assert 'the file there was left as it was' in err
    assert (out / 'table.md').read_text(encoding='utf-8') == 'the table of an earlier run\n'
    assert sorted(p.name for p in out.iterdir()) == ['middlebury2014', 'table.md']
    assert json.loads((tmp_path / 'r.json').read_text())[0]['method'] == 'pkrn'

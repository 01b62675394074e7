"""cva-train and cva-bag-from-dataset name the scenes a partial download leaves out (a scene
with its ground truth but without a file), as cva-evaluate and cva-table1 do: before, the run
was silently smaller."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from test_review36_val_root import OWN, _scenes

from cva_confidence_ros.datasets.synthetic import synthetic_pair
from cva_confidence_ros.training.cli import main as train

NOTICE = 'stereo_folder: 1 scene(s) left out, a file missing: scene2'


def _partial(root: Path) -> Path:
    _scenes(root, [3, 4])
    folder = root / 'scene2'  # left image and ground truth, the right image not downloaded
    folder.mkdir()
    sample = synthetic_pair(5, 48, 64, 16)
    cv2.imwrite(str(folder / 'left.png'), sample.left)
    np.save(folder / 'disparity.npy', sample.disparity.astype(np.float32))
    return root


def test_cva_train_names_a_left_out_scene(tmp_path: Path, capsys: pytest.CaptureFixture[str]):
    train_root = _partial(tmp_path / 'train')
    val_root = _scenes(tmp_path / 'val', [8])
    assert train([*OWN, '--arch', 'cvanet_lite', '--data-root', str(train_root),
                  '--val-data-root', str(val_root), '--out', str(tmp_path / 'run'),
                  '--weights-out', str(tmp_path / 'w.pt')]) == 0
    err = capsys.readouterr().err
    assert err.count(NOTICE) == 1, err
    assert NOTICE in (tmp_path / 'run' / 'train.log').read_text()


def test_cva_bag_from_dataset_names_a_left_out_scene(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
):
    from msg_tools.bag_from_dataset import main as bag_from_dataset

    root = _partial(tmp_path / 'data')
    assert bag_from_dataset(['--data-root', str(root), '--dataset', 'stereo_folder',
                             '--out', str(tmp_path / 'bag')]) == 0
    assert NOTICE in capsys.readouterr().err

"""Review 36: validation on held-out scenes of another root (``--val-data-root``), and the
baselines' refusal of a network collapsed to one confidence."""

from __future__ import annotations

import json
from pathlib import Path
import shutil

import pytest
from test_review36_training_users import _scenes as stereo_folder_scenes

from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.training.cli import main
from cva_confidence_ros.training.config import TrainConfig

#: A tiny run on stereo_folder scenes, validated on stereo_folder scenes (D = 16, one thread).
OWN = [
    '--matcher', 'census_bm',
    '--max-disparity', '16',
    '--datasets', 'stereo_folder',
    '--val-datasets', 'stereo_folder',
    '--val-pixels', '200',
    '--batch-size', '16',
    '--samples-per-epoch', '32',
    '--epochs', '1',
    '--epochs-low-lr', '0',
    '--threads', '1',
    '--no-progress',
]  # fmt: skip


def _scenes(root: Path, seeds: list[int]) -> Path:
    """stereo_folder scenes ``scene<i>`` of 48×64 synthetic pairs under ``root``."""
    return stereo_folder_scenes(root, seeds, size=(48, 64))


@pytest.mark.parametrize('arch', ['cvanet_lite', 'ccnn'])
def test_own_scenes_validate_on_held_out_scenes_of_another_root(tmp_path: Path, arch) -> None:
    # Training and validation read the one --data-root: validating on your own held-out
    # stereo_folder scenes was refused ('both use stereo_folder').
    train, val = _scenes(tmp_path / 'train', [1, 2]), _scenes(tmp_path / 'val', [3])
    weights = tmp_path / 'run' / 'w.pt'
    args = [*OWN, '--arch', arch, '--data-root', str(train), '--val-data-root', str(val),
            '--out', str(tmp_path / 'run'), '--weights-out', str(weights)]
    assert main(args) == 0
    card = json.loads(weights.with_suffix('.json').read_text())
    assert card['val_data_root'] == str(val)
    assert [s['name'] for s in card['val_scenes']] == ['stereo_folder/scene0']
    assert card['final_val_auc'] is not None
    text = weights.with_suffix('.md').read_text()
    assert f'validation scenes: stereo_folder/scene0 (200 pixels); data sets read from ' \
        f'--val-data-root `{val}`' in text


def test_validation_scenes_that_are_the_training_pairs_are_refused(tmp_path: Path,
                                                                   capsys) -> None:
    train = _scenes(tmp_path / 'train', [1, 2])
    copy = tmp_path / 'copy'
    shutil.copytree(train, copy)
    args = [*OWN, '--arch', 'cvanet_lite', '--data-root', str(train), '--out',
            str(tmp_path / 'run')]
    assert main([*args, '--val-data-root', str(copy)]) == 2
    err = capsys.readouterr().err
    assert 'validation data must be held apart from the training data; every scene of ' \
        f'--val-datasets stereo_folder in --val-data-root {copy} is a training pair' in err, err
    assert '(2 such scenes)' in err
    # The training root itself, spelled otherwise: refused by name, before any matching.
    assert main([*args, '--val-data-root', f'{train}/', '--overwrite']) == 2
    assert 'held apart from the training data; both use stereo_folder' in \
        capsys.readouterr().err
    with pytest.raises(ConfigError, match='--val-data-root .* needs --val-datasets'):
        TrainConfig(synthetic=1, val_data_root=str(copy))
    # One held-out scene beside a copy: the copy is left out, the other validates.
    _scenes(tmp_path / 'mixed', [3])
    shutil.copytree(train / 'scene0', tmp_path / 'mixed' / 'scene1')
    assert main([*args, '--val-data-root', str(tmp_path / 'mixed'), '--overwrite']) == 0
    err = capsys.readouterr().err
    assert 'val scene stereo_folder/scene1: the same pair as stereo_folder/scene0' in err
    assert '1 validation scenes' in err


def test_resume_refuses_other_validation_scenes(tmp_path: Path, capsys) -> None:
    train, val = _scenes(tmp_path / 'train', [1, 2]), _scenes(tmp_path / 'val', [3])
    out = str(tmp_path / 'run')
    args = [*OWN, '--arch', 'cvanet_lite', '--data-root', str(train), '--out', out]
    assert main([*args, '--val-data-root', str(val)]) == 0
    capsys.readouterr()
    resume = [*args, '--epochs', '2', '--resume']
    other = _scenes(tmp_path / 'other', [4])
    assert main([*resume, '--val-data-root', str(other)]) == 2
    err = capsys.readouterr().err
    assert "the validation data differ from the run's (stereo_folder/scene0 holds other " \
        'images or ground truth' in err, err
    assert f'(the run read --val-data-root {val})' in err
    # The same files in another place: resumed.
    moved = tmp_path / 'moved'
    shutil.copytree(val, moved)
    assert main([*resume, '--val-data-root', str(moved)]) == 0


@pytest.mark.parametrize('arch', ['ccnn', 'lfn'])
def test_a_baseline_collapsed_to_one_confidence_writes_no_weights(tmp_path: Path, arch,
                                                                  capsys) -> None:
    # At --lr 1 CCNN and LFN end giving one confidence everywhere (validation AUC that of a
    # constant) and their weights were written as the run's result.
    train = _scenes(tmp_path / 'train', [1, 2])
    weights = tmp_path / 'run' / 'w.pt'
    args = ['--arch', arch, '--matcher', 'census_bm', '--max-disparity', '16',
            '--data-root', str(train), '--datasets', 'stereo_folder', '--batch-size', '64',
            '--samples-per-epoch', '2000', '--epochs', '1', '--epochs-low-lr', '0',
            '--lr', '1.0', '--threads', '1', '--no-progress', '--out', str(tmp_path / 'run'),
            '--weights-out', str(weights)]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert 'training diverged: after epoch 1, the network gives one confidence' in err, err
    assert not weights.exists()

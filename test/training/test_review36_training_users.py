"""Review 36 of ``cva-train`` as a robotics team uses it: fine-tuning on its own recorded pairs
(``stereo_folder``), resuming, and a learning rate set too high."""

from __future__ import annotations

from pathlib import Path
import shutil

import cv2
import numpy as np
import torch
from train_test_utils import TINY

from cva_confidence_ros.datasets import load_scene
from cva_confidence_ros.datasets.synthetic import synthetic_pair
from cva_confidence_ros.matching import compute_cost_volume, wta_disparity
from cva_confidence_ros.training import trainer
from cva_confidence_ros.training.cli import main

#: A tiny run on the stereo_folder scenes of a --data-root (D = 16, one thread).
OWN = [
    '--arch', 'cvanet_lite',
    '--matcher', 'census_bm',
    '--max-disparity', '16',
    '--datasets', 'stereo_folder',
    '--batch-size', '16',
    '--samples-per-epoch', '32',
    '--epochs-low-lr', '0',
    '--threads', '1',
    '--no-progress',
]  # fmt: skip


def _scenes(
    root: Path, seeds: list[int], matcher_truth: bool = False, size: tuple[int, int] = (24, 40)
) -> Path:
    """stereo_folder scenes ``scene<i>`` of synthetic pairs of ``size`` (ground truth: the
    pair's, or the matcher's own winner-takes-all disparity)."""
    for number, seed in enumerate(seeds):
        sample = synthetic_pair(seed, *size, 16)
        folder = root / f'scene{number}'
        folder.mkdir(parents=True)
        cv2.imwrite(str(folder / 'left.png'), sample.left)
        cv2.imwrite(str(folder / 'right.png'), sample.right)
        truth = sample.disparity
        np.save(folder / 'disparity.npy', truth.astype(np.float32))
        if matcher_truth:  # matched as the trainer matches the pair it reads back
            read = load_scene('stereo_folder', root, folder.name)
            truth = wta_disparity(compute_cost_volume(read.left, read.right, 'census_bm', 16))
            np.save(folder / 'disparity.npy', truth.astype(np.float32))
    return root


def test_resume_refuses_other_training_scenes(tmp_path: Path, capsys) -> None:
    # The run's --data-root may change on a resume (the data moved), and another root of
    # stereo_folder was taken with a note that 'the same data sets are read from the new
    # place': the run went on with other pairs than its finished epochs had.
    first = _scenes(tmp_path / 'first', [1, 2])
    other = _scenes(tmp_path / 'other', [3, 4])
    out = str(tmp_path / 'run')
    assert main([*OWN, '--data-root', str(first), '--out', out, '--epochs', '1']) == 0
    capsys.readouterr()
    resume = [*OWN, '--out', out, '--epochs', '2', '--resume']
    assert main([*resume, '--data-root', str(other)]) == 2
    err = capsys.readouterr().err
    assert 'the training data differ' in err, err
    assert 'stereo_folder/scene0 holds other images or ground truth' in err, err
    fewer = tmp_path / 'fewer'
    shutil.copytree(first, fewer)
    shutil.rmtree(fewer / 'scene1')
    assert main([*resume, '--data-root', str(fewer)]) == 2
    assert 'stereo_folder/scene1 missing' in capsys.readouterr().err
    # The same pairs in another place: resumed.
    moved = tmp_path / 'moved'
    shutil.copytree(first, moved)
    assert main([*resume, '--data-root', str(moved)]) == 0


def test_resume_replaces_only_the_weights_of_its_own_run(tmp_path: Path, capsys) -> None:
    # --resume let --weights-out replace any existing weights and card (the shipped ones
    # too), also with no checkpoint at all, where the 'resume' starts afresh.
    shipped = tmp_path / 'models' / 'w.pt'
    shipped.parent.mkdir()
    shipped.write_text('shipped')
    args = [*TINY, '--epochs-low-lr', '0', '--out', str(tmp_path / 'run')]
    assert main([*args, '--epochs', '1', '--resume', '--weights-out', str(shipped)]) == 2
    err = capsys.readouterr().err
    assert 'exists' in err and '--resume replaces only the weights of its own run' in err, err
    assert shipped.read_text() == 'shipped'
    # The run's own weights: a resume that trains longer replaces them.
    own = tmp_path / 'run' / 'own.pt'
    assert main([*args, '--epochs', '1', '--weights-out', str(own)]) == 0
    assert main([*args, '--epochs', '2', '--resume', '--weights-out', str(own)]) == 0
    assert torch.load(own, weights_only=True)['meta']['epochs'] == 2
    assert main([*args, '--epochs', '3', '--resume', '--weights-out', str(shipped)]) == 2
    assert shipped.read_text() == 'shipped'


def test_a_collapsed_network_is_not_written_as_final(tmp_path: Path, monkeypatch, capsys):
    # A too-high --lr (1.0) mostly leaves finite weights that give one confidence for every
    # input (val AUC that of a constant): no NaN, so the run wrote them as its final weights.
    run_epoch = trainer._run_epoch

    def collapse(config, model, *args, **kwargs):  # type: ignore[no-untyped-def]
        result = run_epoch(config, model, *args, **kwargs)
        with torch.no_grad():
            for parameter in model.parameters():
                parameter.zero_()  # every logit 0: confidence 0.5 everywhere
        return result

    monkeypatch.setattr(trainer, '_run_epoch', collapse)
    out, weights = tmp_path / 'run', tmp_path / 'w.pt'
    args = [*TINY, '--out', str(out), '--weights-out', str(weights)]
    assert main([*args, '--epochs', '2', '--epochs-low-lr', '0']) == 2
    err = capsys.readouterr().err
    assert 'warning: after epoch 1, the network gives one confidence (0.5)' in err, err
    assert 'training diverged: after epoch 2, the network gives one confidence' in err, err
    assert not weights.exists()


def test_labels_of_one_class_are_warned_about(tmp_path: Path) -> None:
    # Ground truth made by the matcher itself labels every pixel correct: nothing to learn,
    # and the run said nothing.
    root = _scenes(tmp_path / 'data', [5], matcher_truth=True)
    out = tmp_path / 'run'
    assert main([*OWN, '--data-root', str(root), '--out', str(out), '--epochs', '1']) == 0
    log = (out / 'train.log').read_text()
    assert 'every labelled training pixel is correct for census_bm' in log

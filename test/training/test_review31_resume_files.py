"""Review 31 of cva-train's resume: the weight files named at the start of a run.

``--init-weights`` is not needed on a resume (the checkpoint holds the weights), so a file
moved away since must not stop it; a ``--teacher`` file replaced by another at the same path
would have the remaining epochs distil from other weights without a word."""

from __future__ import annotations

import json
from pathlib import Path
import re

import pytest
import torch
from train_test_utils import TINY

from cva_confidence_ros.model import CVANet, load_weights, save_weights
from cva_confidence_ros.training.cli import main


def _weights(path: Path, seed: int, samples: int) -> Path:
    torch.manual_seed(seed)
    save_weights(CVANet(16), path, {'matcher': 'census_bm', 'samples_seen': samples})
    return path


def test_a_resume_needs_no_init_weights_file(tmp_path: Path) -> None:
    start = _weights(tmp_path / 'start.pt', 3, 123)
    out, weights = tmp_path / 'run', tmp_path / 'cvanet_census_bm_d16.pt'
    args = [*TINY, '--init-weights', str(start), '--out', str(out),
            '--weights-out', str(weights), '--epochs-low-lr', '0']
    assert main([*args, '--epochs', '1']) == 0
    start.unlink()  # moved away after the run started
    # Before: ModelError "cannot read … start.pt" although the checkpoint holds the weights.
    assert main([*args, '--epochs', '2', '--resume']) == 0
    history = json.loads((out / 'history.json').read_text())
    assert [h['epoch'] for h in history] == [1, 2]
    meta = load_weights(weights)[1]
    assert meta['init_weights'] == str(start) and meta['init_meta']['samples_seen'] == 123
    assert 'not read again: the checkpoint holds the weights' in (out / 'train.log').read_text()


def test_a_resume_refuses_a_teacher_replaced_by_another(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    teacher = _weights(tmp_path / 'teacher.pt', 3, 123)
    out = tmp_path / 'run'
    args = [*TINY, '--teacher', str(teacher), '--distill-weight', '0.5', '--out', str(out),
            '--epochs-low-lr', '0']
    assert main([*args, '--epochs', '1']) == 0
    _weights(teacher, 4, 123)  # retrained: same path, other weights
    capsys.readouterr()
    assert main([*args, '--epochs', '2', '--resume']) == 2
    err = capsys.readouterr().err
    assert re.search(r'the teacher \S*teacher\.pt is not the file the run started with '
                     r'\(SHA-256 [0-9a-f]{12}…, was [0-9a-f]{12}…\)', err), err
    assert len(json.loads((out / 'history.json').read_text())) == 1
    # The same file again: the resume goes on.
    _weights(teacher, 3, 123)
    assert main([*args, '--epochs', '2', '--resume']) == 0

"""``cva-train`` under ``torchrun``: two real processes, DistributedDataParallel over gloo (CPU).

The same code path the issue asks for on several GPUs (``--device cuda`` picks NCCL instead).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
import subprocess
import sys

import torch
from train_test_utils import TINY

from cva_confidence_ros.model import load_weights

# 64 samples an epoch: 32 for each of the two processes.
RUN = [*TINY, '--samples-per-epoch', '64']


def _torchrun(*args: str) -> subprocess.CompletedProcess[str]:
    command = [
        sys.executable, '-m', 'torch.distributed.run', '--standalone', '--nproc-per-node', '2',
        '-m', 'cva_confidence_ros.training.cli', *RUN, *args,
    ]  # fmt: skip
    env = {**os.environ, 'OMP_NUM_THREADS': '1'}
    done = subprocess.run(command, capture_output=True, text=True, timeout=300, env=env)
    assert done.returncode == 0, done.stdout + done.stderr
    return done


def _state(path: Path) -> dict[str, torch.Tensor]:
    net, _ = load_weights(path, matcher='census_bm', max_disparity=16)
    return net.state_dict()


def test_two_processes_train_resume_and_repeat_exactly(tmp_path):
    straight = tmp_path / 'straight' / 'w.pt'
    done = _torchrun('--epochs', '1', '--epochs-low-lr', '1',
                     '--out', str(tmp_path / 'straight'), '--weights-out', str(straight))

    # Rank 0 alone logs, validates and writes: one line per epoch, not one per process.
    assert done.stderr.count('epoch 1/2') == 1 and done.stderr.count('epoch 2/2') == 1
    meta = json.loads(straight.with_suffix('.json').read_text())
    assert meta['hardware']['processes'] == 2
    assert 'processes: 2' in straight.with_suffix('.md').read_text()
    history = json.loads((tmp_path / 'straight' / 'history.json').read_text())
    assert [record['epoch'] for record in history] == [1, 2]
    assert all(0.0 < record['val_auc'] < 1.0 for record in history)
    assert all(record['samples'] == 64 for record in history)  # both shares counted

    # Stopped after the first epoch and resumed under torchrun: the same weights, bit for bit.
    broken = tmp_path / 'broken'
    _torchrun('--epochs', '1', '--epochs-low-lr', '0', '--out', str(broken))
    _torchrun('--epochs', '1', '--epochs-low-lr', '1', '--resume',
              '--out', str(broken), '--weights-out', str(broken / 'w.pt'))
    expected, resumed = _state(straight), _state(broken / 'w.pt')
    assert expected.keys() == resumed.keys()
    for name, value in expected.items():
        assert torch.equal(value, resumed[name]), name

"""Review 29 leftovers: the distillation loss of no outputs, steps of one extract under
torchrun, and inference on a network that does not say its depth."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from train_test_utils import TINY

from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.model.inference import predict_confidence, predict_confidence_at
from cva_confidence_ros.training.cli import main
from cva_confidence_ros.training.distill import distillation_loss


@pytest.mark.parametrize('teacher', [None, torch.zeros(0)])
def test_the_loss_of_no_outputs_is_zero_and_backpropagates(teacher) -> None:
    # A mean over no outputs was NaN (the trainer stepped around it; any other caller got NaN
    # weights from the optimiser).
    logits = torch.zeros(0, requires_grad=True)
    loss = distillation_loss(logits, torch.zeros(0), teacher, 0.0 if teacher is None else 0.5)
    assert loss.item() == 0.0
    loss.backward()
    assert logits.grad is not None and logits.grad.numel() == 0
    with pytest.raises(ConfigError, match='needs teacher logits'):
        distillation_loss(logits, torch.zeros(0), None, 0.5)


def test_samples_per_epoch_that_leave_each_process_one_extract_are_refused(
    tmp_path, capsys, monkeypatch
) -> None:
    # Two samples over two torchrun processes: a step of one extract on each, which
    # CVA-Net-Fast's batch norm refuses (a ValueError after the data were prepared).
    monkeypatch.setenv('WORLD_SIZE', '2')
    args = [*TINY, '--arch', 'cvanet_fast', '--out', str(tmp_path / 'run')]
    assert main([*args, '--samples-per-epoch', '2']) == 2
    err = capsys.readouterr().err
    assert '--samples-per-epoch 2 over 2 processes makes steps of a single 13×13' in err
    assert 'samples per process' in err and 'scene synthetic/seed0' not in err


def test_a_network_without_its_depth_is_named() -> None:
    # The error said 'built for cost volumes of depth D = None'.
    volume = np.zeros((4, 5, 5), np.float32)
    for predict in (
        lambda net: predict_confidence(net, volume),
        lambda net: predict_confidence_at(net, volume, np.array([0]), np.array([0])),
    ):
        with pytest.raises(ConfigError, match='says its depth .*got Conv3d$'):
            predict(torch.nn.Conv3d(1, 1, 1))


def test_a_pair_two_data_sets_ship_is_trained_on_once_and_not_validated_on(tmp_path) -> None:
    # The shared data's flyingthings3d TEST/A/0000/0006 is sceneflow_extra's 0006, byte for
    # byte: both in the training split, it weighed twice.
    from cva_confidence_ros.datasets.synthetic import synthetic_pair
    from cva_confidence_ros.training.config import TrainConfig
    from cva_confidence_ros.training.trainer import _Log, _prepare

    pair, other = synthetic_pair(0, 24, 40, 16), synthetic_pair(1, 24, 40, 16)
    renamed = dataclasses.replace(pair, dataset='sceneflow_extra', scene='0006')
    config = TrainConfig(matcher='census_bm', max_disparity=16, synthetic=1)
    log = _Log(tmp_path / 'train.log', True)

    def prepare(sample, matcher, depth):
        return SimpleNamespace(name=sample.scene, shape=(24, 40), factor=1, n_labelled=1,
                               n_wrong=0)

    seen: dict[str, str] = {}
    loaders = [('a/0006', lambda: pair), ('b/1', lambda: other), ('b/0006', lambda: renamed)]
    scenes = _prepare(loaders, config, False, log, prepare, seen)
    assert [s.name for s in scenes] == [pair.scene, other.scene]
    val = _prepare([('v/0', lambda: pair)], config, True, log, prepare, seen)
    assert val == []
    text = (tmp_path / 'train.log').read_text()
    assert 'scene b/0006: the same pair as a/0006 (taken once)' in text
    assert 'val scene v/0: the same pair as a/0006 (taken once)' in text

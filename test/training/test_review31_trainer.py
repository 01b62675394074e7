"""Review 31 of cva-train's loop: a run whose last step diverged.

The loss of an epoch is that of the weights before each step: when the last step of the last
epoch breaks the weights, the loss stays finite and the broken weights went into the checkpoint
and the weights file (exit 0); with validation, the run stopped on a metrics error about NaN
confidences that did not say the training diverged."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from train_test_utils import TINY

from cva_confidence_ros.datasets.synthetic import synthetic_pair
from cva_confidence_ros.errors import ModelError
from cva_confidence_ros.model import CVANet
from cva_confidence_ros.training.cli import main
from cva_confidence_ros.training.data import prepare_scene, validation_subset

# One step an epoch at a rate that leaves weights whose logits overflow to NaN (the loss of the
# step, taken before it, is 0.84).
_DIVERGING = ['--samples-per-epoch', '16', '--lr', '10', '--epochs-low-lr', '0']


def test_weights_broken_by_the_last_step_are_not_written(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out, weights = tmp_path / 'run', tmp_path / 'cvanet_census_bm_d16.pt'
    args = [*TINY, '--val-synthetic', '0', *_DIVERGING, '--epochs', '1', '--out', str(out),
            '--weights-out', str(weights)]  # fmt: skip
    # Before: exit 0, a weights file and checkpoint whose confidence is NaN everywhere.
    assert main(args) == 2
    err = capsys.readouterr().err
    assert 'training diverged: after epoch 1, 256 of 256 logits of the network at training ' \
        'pixels are NaN or infinite (lr 10); lower --lr. No weights were written' in err, err
    assert not weights.exists()
    assert not (out / 'checkpoint.pt').exists()


def test_nan_validation_confidence_is_named_a_divergence() -> None:
    # Before: InputError 'confidence holds 40 NaN values; expected a real number for every
    # evaluated pixel', which says nothing of the training.
    from cva_confidence_ros.training.trainer import _validate

    scene = prepare_scene(synthetic_pair(3, 24, 40, 16), 'census_bm', 16)
    subsets = validation_subset([scene], 40, 7)
    net = CVANet(16)
    with torch.no_grad():
        net.classification.fc2.bias.fill_(float('nan'))
    with pytest.raises(ModelError) as info:
        _validate(net, [scene], subsets, torch.device('cpu'), 2, 1e-3, Path('out/run'))
    assert str(info.value) == (
        'training diverged: after epoch 3, 40 of 40 validation confidences are NaN or '
        'infinite (lr 0.001); lower --lr. No weights were written; the checkpoint in '
        'out/run still holds epoch 2'
    )
    # Finite confidences are scored as before.
    with torch.no_grad():
        net.classification.fc2.bias.zero_()
    scores = _validate(net, [scene], subsets, torch.device('cpu'))
    assert scores['val_auc'] is not None and np.isfinite(scores['val_auc'])


def test_a_resume_writes_the_history_a_stopped_run_left_short(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Ctrl-C after the checkpoint of the last epoch, before history.json: the run says
    # 'continue with --resume', and the resume, with no epoch left to train, never wrote it.
    from cva_confidence_ros.training import trainer

    def interrupt(*args: object, **kwargs: object) -> str:
        raise KeyboardInterrupt

    out = tmp_path / 'run'
    args = [*TINY, '--epochs', '1', '--epochs-low-lr', '0', '--out', str(out)]
    with monkeypatch.context() as patch:
        patch.setattr(trainer.json, 'dumps', interrupt)
        assert main(args) == 130
    assert (out / 'checkpoint.pt').is_file() and not (out / 'history.json').exists()
    assert main([*args, '--resume']) == 0
    history = json.loads((out / 'history.json').read_text())
    assert [h['epoch'] for h in history] == [1]
    assert not (out / 'history.json.tmp').exists()


def test_a_learning_rate_beyond_float32_steps_is_refused_by_name() -> None:
    # --lr 1e39 is finite as a double: Adam's first step raised "value cannot be converted
    # to type float without overflow".
    from cva_confidence_ros.errors import ConfigError
    from cva_confidence_ros.training import TrainConfig

    with pytest.raises(ConfigError, match=r'^lr must be at most 1e\+38; got 1e\+39$'):
        TrainConfig(synthetic=1, lr=1e39)
    assert TrainConfig(synthetic=1, lr=1e30).lr == 1e30  # diverges, and says so

"""Review 32 of distillation (teacher targets) and of the baselines' training (divergence,
resume)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from cva_confidence_ros.datasets.synthetic import synthetic_pair
from cva_confidence_ros.errors import ModelError
from cva_confidence_ros.model import CVANet
from cva_confidence_ros.model.baselines import CCNN, LGCNet
from cva_confidence_ros.training import TrainConfig
from cva_confidence_ros.training.baselines import _auc, prepare_disparity_scene, train_baseline
from cva_confidence_ros.training.cli import main
from cva_confidence_ros.training.data import validation_subset
from cva_confidence_ros.training.distill import distillation_loss, teacher_logits

# Two 32×48 synthetic scenes at D = 16, one step of 256 outputs an epoch, no validation.
TINY = TrainConfig(
    arch='ccnn', matcher='census_bm', max_disparity=16, synthetic=2, synthetic_size=(32, 48),
    val_synthetic=0, mode='dense', crop_size=16, batch_size=256, samples_per_epoch=200,
    lr=1e-3, seed=3, threads=1, progress=False, epochs=1, epochs_low_lr=0,
)


def test_teacher_logits_run_a_teacher_in_training_mode_as_in_eval_mode() -> None:
    # An unfolded teacher left in training mode normalised by the batch's statistics, moved its
    # running statistics and dropped out: two calls on one batch gave -1.51 and -0.59.
    torch.manual_seed(0)
    teacher = CVANet(16)
    volumes = torch.rand(2, 1, 16, 13, 13)
    running = teacher.fusion.input_bn.running_mean.clone()
    first, second = teacher_logits(teacher, volumes), teacher_logits(teacher, volumes)
    assert torch.equal(first, second)
    assert torch.equal(teacher.fusion.input_bn.running_mean, running)
    assert teacher.training  # its mode given back
    teacher.eval()
    with torch.no_grad():
        assert torch.allclose(first, teacher.forward_logits(volumes))


def test_distillation_loss_sends_no_gradient_to_the_teacher() -> None:
    # The teacher's probability is a target; teacher logits with a graph got a gradient
    # (here [-0.021, 0.033, -0.066]), i.e. the student's loss trained the teacher too.
    logits = torch.tensor([0.5, -1.0, 2.0], requires_grad=True)
    labels = torch.tensor([1.0, 0.0, 0.0])
    teacher = torch.tensor([0.0, 1.0, -1.0], requires_grad=True)
    distillation_loss(logits, labels, teacher, 0.5).backward()
    assert teacher.grad is None
    expected = torch.tensor([0.5, -1.0, 2.0], requires_grad=True)
    distillation_loss(expected, labels, teacher.detach(), 0.5).backward()
    assert logits.grad is not None and torch.allclose(logits.grad, expected.grad)


@pytest.mark.parametrize(
    ('arch', 'what'),
    [
        ('ccnn', '256 of 256 logits of the network'),
        # Was stopped only by the NaN loss of epoch 2, with epoch 1's broken CCNN and ConfNet
        # in the checkpoint it named as the one to keep.
        ('lgcnet', '512 of 512 logits of CCNN and ConfNet'),
    ],
)
def test_weights_a_diverged_last_step_broke_are_not_written(
    tmp_path: Path, arch: str, what: str
) -> None:
    # At lr 1e8 the one step of epoch 1 leaves finite weights whose every output is NaN; the
    # loss of the epoch (taken before the step) is finite, and CCNN's weights were written.
    weights = tmp_path / f'{arch}_census_bm_d16.pt'
    config = TINY.replace(arch=arch, lr=1e8, out=str(tmp_path / 'run'), weights_out=str(weights))
    with pytest.raises(ModelError) as info:
        train_baseline(config)
    assert str(info.value) == (
        f'training diverged: after epoch 1, {what} at training pixels are NaN or infinite '
        '(lr 1e+08); lower --lr. No weights were written'
    )
    assert not weights.exists()
    assert not (tmp_path / 'run' / 'checkpoint.pt').exists()


def test_nan_validation_confidence_of_a_baseline_is_named_a_divergence() -> None:
    # Was auc_scores' InputError 'confidence holds 40 NaN values; expected a real number for
    # every evaluated pixel', which says nothing of the training.
    scene = prepare_disparity_scene(synthetic_pair(3, 32, 48, 16), 'census_bm', 16)
    subsets = validation_subset([scene], 40, 7)
    torch.manual_seed(0)
    net = CCNN(16)
    with torch.no_grad():
        net.head[-1].bias.fill_(float('nan'))
    with pytest.raises(ModelError, match='training diverged: after epoch 1, 40 of 40 valid'):
        _auc(net, [scene], subsets, 'cpu')
    with pytest.raises(ModelError) as info:  # epoch, lr and --out of the run named
        _auc(net, [scene], subsets, 'cpu', None, 2, 1e-3, Path('out/run'))
    assert str(info.value) == (
        'training diverged: after epoch 3, 40 of 40 validation confidences are NaN or '
        'infinite (lr 0.001); lower --lr. No weights were written; the checkpoint in '
        'out/run still holds epoch 2'
    )
    lgc = LGCNet(16)
    with torch.no_grad():
        lgc.confnet.out.bias.fill_(float('nan'))
    with pytest.raises(ModelError, match='40 of 40 ConfNet validation confidences'):
        _auc(lgc, [scene], subsets, 'cpu', 'global')
    # Finite confidences are scored as before.
    with torch.no_grad():
        net.head[-1].bias.zero_()
    scores = _auc(net, [scene], subsets, 'cpu')
    assert scores['val_auc'] is not None and np.isfinite(scores['val_auc'])


def test_a_resume_writes_the_history_a_stopped_baseline_run_left_short(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Ctrl-C after the checkpoint of the last epoch, before history.json: the resume, with no
    # epoch left to train, never wrote it (CVA-Net's trainer does).
    from cva_confidence_ros.training import trainer

    def interrupt(*args: object, **kwargs: object) -> str:
        raise KeyboardInterrupt

    out = tmp_path / 'run'
    args = [
        '--arch', 'ccnn', '--matcher', 'census_bm', '--max-disparity', '16',
        '--synthetic', '2', '--synthetic-size', '32x48', '--val-synthetic', '0',
        '--samples-per-epoch', '64', '--batch-size', '64', '--threads', '1',
        '--no-progress', '--epochs', '1', '--epochs-low-lr', '0', '--out', str(out),
    ]  # fmt: skip
    with monkeypatch.context() as patch:
        patch.setattr(trainer.json, 'dumps', interrupt)
        assert main(args) == 130
    assert (out / 'checkpoint.pt').is_file() and not (out / 'history.json').exists()
    assert main([*args, '--resume']) == 0
    history = json.loads((out / 'history.json').read_text())
    assert [h['epoch'] for h in history] == [1]

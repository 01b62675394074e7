"""Distillation (``--teacher``, ``--distill-weight``) and warm starts (``--init-weights``)."""

from __future__ import annotations

import json
import math

import pytest
import torch
from train_test_utils import TINY as TINY_RUN

from cva_confidence_ros.errors import ConfigError, ModelError
from cva_confidence_ros.model import CVANet, CVANetLite, load_weights, save_weights
from cva_confidence_ros.training import TrainConfig
from cva_confidence_ros.training.cli import main
from cva_confidence_ros.training.distill import (
    distillation_loss,
    load_init_weights,
    load_teacher,
    transfer_state,
)

TINY = [*TINY_RUN, '--epochs', '1', '--epochs-low-lr', '0']


@pytest.fixture(scope='module')
def teacher_path(tmp_path_factory):
    torch.manual_seed(3)
    path = tmp_path_factory.mktemp('teacher') / 'cvanet_census_bm_d16.pt'
    save_weights(CVANet(16), path, {'matcher': 'census_bm', 'samples_seen': 123})
    return path


def _bce(logit: float, target: float) -> float:
    p = 1 / (1 + math.exp(-logit))
    return -(target * math.log(p) + (1 - target) * math.log(1 - p))


def test_loss_mixes_labels_and_teacher_probabilities():
    logits = torch.tensor([0.5, -1.0])
    labels = torch.tensor([1.0, 0.0])
    teacher = torch.tensor([2.0, 0.0])  # probabilities 0.881, 0.5
    p_teacher = [1 / (1 + math.exp(-2.0)), 0.5]
    hard = (_bce(0.5, 1.0) + _bce(-1.0, 0.0)) / 2
    soft = (_bce(0.5, p_teacher[0]) + _bce(-1.0, p_teacher[1])) / 2
    assert float(distillation_loss(logits, labels, None, 0.0)) == pytest.approx(hard, rel=1e-6)
    assert float(distillation_loss(logits, labels, teacher, 0.0)) == pytest.approx(hard, rel=1e-6)
    assert float(distillation_loss(logits, labels, teacher, 1.0)) == pytest.approx(soft, rel=1e-6)
    mixed = float(distillation_loss(logits, labels, teacher, 0.25))
    assert mixed == pytest.approx(0.75 * hard + 0.25 * soft, rel=1e-6)
    with pytest.raises(ConfigError, match='needs teacher'):
        distillation_loss(logits, labels, None, 0.5)
    with pytest.raises(ConfigError, match=r'\[0, 1\]'):
        distillation_loss(logits, labels, teacher, 1.5)


def test_loss_gradient_pulls_towards_the_teacher():
    """With A = 1 the gradient vanishes exactly where the student equals the teacher."""
    logits = torch.tensor([1.3, -0.4], requires_grad=True)
    distillation_loss(logits, torch.tensor([0.0, 1.0]), logits.detach().clone(), 1.0).backward()
    assert torch.allclose(logits.grad, torch.zeros(2), atol=1e-7)


def test_config_validation():
    with pytest.raises(ConfigError, match='both --teacher PATH and --distill-weight'):
        TrainConfig(synthetic=1, teacher='t.pt')
    with pytest.raises(ConfigError, match='both --teacher PATH and --distill-weight'):
        TrainConfig(synthetic=1, distill_weight=0.3)
    with pytest.raises(ConfigError, match=r'distill_weight must be in \[0, 1\]'):
        TrainConfig(synthetic=1, teacher='t.pt', distill_weight=1.2)
    assert TrainConfig(synthetic=1, teacher='t.pt', distill_weight=0.3).distill_weight == 0.3


def test_teacher_is_folded_frozen_and_checked(teacher_path):
    teacher, meta = load_teacher(str(teacher_path), 'census_bm', 16, torch.device('cpu'))
    assert meta['samples_seen'] == 123 and getattr(teacher, 'is_folded', False)
    assert not any(p.requires_grad for p in teacher.parameters())
    volume = torch.rand(2, 1, 16, 15, 14)
    net = load_weights(teacher_path)[0]
    with torch.no_grad():
        expected = net.forward_logits(volume)
    assert torch.allclose(teacher.forward_logits(volume), expected, atol=1e-4)
    with pytest.raises(ModelError, match="asked for matcher 'census_sgm'"):
        load_teacher(str(teacher_path), 'census_sgm', 16, torch.device('cpu'))
    with pytest.raises(ModelError, match='asked for D = 24'):
        load_teacher(str(teacher_path), 'census_bm', 24, torch.device('cpu'))


@pytest.mark.parametrize('mode', ['sparse', 'dense'])
def test_distilled_lite_run_records_the_teacher(tmp_path, teacher_path, mode):
    weights = tmp_path / 'cvanet_lite_census_bm_d16.pt'
    args = [
        *TINY, '--arch', 'cvanet_lite', '--mode', mode, '--crop-size', '8',
        '--teacher', str(teacher_path), '--distill-weight', '0.3',
        '--out', str(tmp_path / 'run'), '--weights-out', str(weights),
    ]  # fmt: skip
    assert main(args) == 0
    net, meta = load_weights(weights, arch='cvanet_lite')
    assert isinstance(net, CVANetLite)
    assert meta['teacher'] == str(teacher_path) and meta['distill_weight'] == 0.3
    assert meta['teacher_meta']['arch'] == 'cvanet'
    assert meta['teacher_meta']['samples_seen'] == 123
    assert 0.0 <= meta['final_val_high'] <= 1.0
    card = weights.with_suffix('.md').read_text()
    assert card.startswith('# CVA-Net-Lite weights')
    assert 'A = 0.3; teacher `cvanet_census_bm_d16.pt`' in card
    assert json.loads(weights.with_suffix('.json').read_text())['distill_weight'] == 0.3
    assert 'distilling from' in (tmp_path / 'run' / 'train.log').read_text()


def test_teacher_of_another_matcher_exits_2(tmp_path, teacher_path, capsys):
    args = [
        *TINY, '--matcher', 'census_sgm', '--arch', 'cvanet_lite',
        '--teacher', str(teacher_path), '--distill-weight', '0.5', '--out', str(tmp_path),
    ]  # fmt: skip
    assert main(args) == 2
    assert "asked for matcher 'census_sgm'" in capsys.readouterr().err
    # Checked before the training data are prepared.
    assert 'labelled pixels' not in (tmp_path / 'train.log').read_text()


def test_init_weights_warm_start(tmp_path, teacher_path, capsys):
    net = CVANet(16)
    meta = load_init_weights(net, str(teacher_path), 'cvanet')
    reference = load_weights(teacher_path)[0].state_dict()
    for key, value in net.state_dict().items():
        assert torch.equal(value, reference[key])
    assert meta['samples_seen'] == 123

    weights = tmp_path / 'continued.pt'
    args = [*TINY, '--init-weights', str(teacher_path), '--out', str(tmp_path / 'run')]
    assert main([*args, '--weights-out', str(weights)]) == 0
    meta = load_weights(weights)[1]
    assert meta['init_weights'] == str(teacher_path)
    assert meta['init_meta']['samples_seen'] == 123
    assert 'initialised from `cvanet_census_bm_d16.pt`' in weights.with_suffix('.md').read_text()

    assert 'across matchers' not in capsys.readouterr().err
    wrong_arch = [*TINY, '--arch', 'cvanet_lite', '--init-weights', str(teacher_path)]
    assert main([*wrong_arch, '--out', str(tmp_path / 'other')]) == 2
    assert "expected 'cvanet_lite'" in capsys.readouterr().err
    assert 'labelled pixels' not in (tmp_path / 'other' / 'train.log').read_text()

    # Weights of another matcher are a legitimate start, but not a silent one.
    sgm = [a if a != 'census_bm' else 'census_sgm' for a in args]
    assert main([*sgm[:-1], str(tmp_path / 'sgm'), '--epochs', '1', '--epochs-low-lr', '0']) == 0
    assert 'trained on census_bm cost volumes; this run trains for census_sgm' in (
        capsys.readouterr().err
    )


def test_transfer_state_across_depths():
    torch.manual_seed(0)
    shallow, deep = CVANet(16), CVANet(24)
    moved = transfer_state(shallow.state_dict(), deep.state_dict())
    key = 'classification.fc1.weight'
    assert moved[key].shape == deep.state_dict()[key].shape == (16, 32, 12, 1)
    # Depth index i is the same disparity at any D: D = 16 keeps indices 0…3, zeros beyond.
    assert torch.equal(moved[key][:, :, :4], shallow.state_dict()[key])
    assert not moved[key][:, :, 4:].any()
    for name, value in shallow.state_dict().items():
        if name != key:
            assert torch.equal(moved[name], value)

    cut = transfer_state(deep.state_dict(), shallow.state_dict())  # a deeper source is cut
    assert torch.equal(cut[key], deep.state_dict()[key][:, :, :4])


def test_transfer_state_refuses_other_shapes():
    state = CVANet(16).state_dict()
    target = {**state, 'classification.fc2.weight': torch.zeros(2, 16, 1, 1)}
    with pytest.raises(
        ModelError, match=r'classification.fc2.weight: stored shape \(1, 16, 1, 1\)'
    ):
        transfer_state(state, target)
    with pytest.raises(ModelError, match='missing'):
        transfer_state({k: v for k, v in state.items() if 'fc2' not in k}, state)


def test_init_weights_of_another_depth(tmp_path, teacher_path):
    net = CVANet(24)
    meta = load_init_weights(net, str(teacher_path), 'cvanet')
    assert meta['max_disparity'] == 16
    source = load_weights(teacher_path)[0].state_dict()
    assert torch.equal(net.state_dict()['fusion.convs.0.weight'], source['fusion.convs.0.weight'])

    weights = tmp_path / 'deeper.pt'
    args = [*TINY, '--max-disparity', '24', '--synthetic-size', '24x48']  # later flags win
    args += ['--init-weights', str(teacher_path)]
    assert main([*args, '--out', str(tmp_path / 'run'), '--weights-out', str(weights)]) == 0
    meta = load_weights(weights, max_disparity=24)[1]
    assert meta['init_meta']['max_disparity'] == 16

"""``cva-train`` end to end on tiny synthetic pairs: weights, card, checkpoints, resume."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
import torch
from train_test_utils import TINY

from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.model import CVANet, load_weights, save_weights
from cva_confidence_ros.training import TrainConfig
from cva_confidence_ros.training.cli import main


def _data_root() -> Path:
    env = os.environ.get('CVA_DATA_ROOT')
    root = Path(env) if env else Path(__file__).resolve().parents[2] / '..' / 'shared' / 'data'
    if not (root / 'kitti2012').is_dir() or not (root / 'eth3d').is_dir():
        pytest.skip(f'shared stereo data not found at {root}')
    return root


def _history(out: Path) -> list[dict]:
    return json.loads((out / 'history.json').read_text())


def test_train_writes_weights_and_card_then_resumes(tmp_path):
    out, weights = tmp_path / 'run', tmp_path / 'models' / 'cvanet_census_bm_d16.pt'
    args = [*TINY, '--out', str(out), '--weights-out', str(weights)]
    assert main([*args, '--epochs', '1', '--epochs-low-lr', '1']) == 0

    net, meta = load_weights(weights, matcher='census_bm', max_disparity=16)
    assert net.max_disparity == 16
    assert meta['epochs'] == 1 and meta['epochs_low_lr'] == 1 and meta['batch_size'] == 16
    assert [s['name'] for s in meta['scenes']] == ['synthetic/seed0', 'synthetic/seed1']
    assert [s['name'] for s in meta['val_scenes']] == ['synthetic/seed1000000']
    assert meta['samples_seen'] == 64 and meta['val_pixels'] == 40
    assert 0.0 <= meta['fraction_wrong'] <= 1.0
    assert 0.0 <= meta['final_val_auc'] <= 1.0 and meta['final_train_loss'] > 0
    assert meta['command'].startswith('cva-train --matcher census_bm')
    assert meta['hardware']['torch_threads'] == 1
    card = json.loads(weights.with_suffix('.json').read_text())
    assert card['final_val_auc'] == meta['final_val_auc']
    markdown = weights.with_suffix('.md').read_text()
    for fact in ('census_bm', 'synthetic/seed1', 'wall time', 'Adam', 'validation AUC'):
        assert fact in markdown
    history = _history(out)
    assert [h['lr'] for h in history] == pytest.approx([1e-4, 1e-5])
    assert (out / 'checkpoint.pt').is_file() and (out / 'train.log').is_file()

    # One more low-lr epoch: only epoch 3 runs, epochs 1-2 are kept as they were.
    assert main([*args, '--epochs', '1', '--epochs-low-lr', '2', '--resume']) == 0
    resumed = _history(out)
    assert [h['epoch'] for h in resumed] == [1, 2, 3]
    assert resumed[:2] == history
    assert 'resumed from' in (out / 'train.log').read_text()
    assert load_weights(weights)[1]['samples_seen'] == 96


def test_interrupted_run_resumes_as_if_uninterrupted(tmp_path, monkeypatch):
    from cva_confidence_ros.training import trainer

    straight, broken = tmp_path / 'straight', tmp_path / 'broken'
    args = [*TINY, '--epochs', '2', '--epochs-low-lr', '0']
    assert main([*args, '--out', str(straight)]) == 0

    real_epoch = trainer._run_epoch
    calls = []

    def crash_in_second_epoch(*a, **k):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt  # Ctrl-C in the middle of epoch 2
        return real_epoch(*a, **k)

    monkeypatch.setattr(trainer, '_run_epoch', crash_in_second_epoch)
    assert main([*args, '--out', str(broken)]) == 130
    assert [h['epoch'] for h in _history(broken)] == [1]
    monkeypatch.setattr(trainer, '_run_epoch', real_epoch)
    assert main([*args, '--out', str(broken), '--resume']) == 0

    a = torch.load(straight / 'checkpoint.pt', weights_only=True)
    b = torch.load(broken / 'checkpoint.pt', weights_only=True)
    assert a['epoch'] == b['epoch'] == 2
    for key in a['model']:
        torch.testing.assert_close(a['model'][key], b['model'][key], atol=1e-6, rtol=1e-5)
    losses = [h['train_loss'] for h in _history(straight)]
    assert [h['train_loss'] for h in _history(broken)] == pytest.approx(losses, rel=1e-5)


def test_dense_mode_counts_labelled_outputs(tmp_path):
    out = tmp_path / 'dense'
    args = [*TINY, '--out', str(out), '--mode', 'dense', '--crop-size', '8']
    assert (
        main([*args, '--epochs', '1', '--epochs-low-lr', '0', '--samples-per-epoch', '100']) == 0
    )
    (record,) = _history(out)
    assert record['samples'] >= 100 and record['train_loss'] > 0


@pytest.mark.parametrize('mode', ['sparse', 'dense'])
def test_vflip_changes_the_samples_and_is_recorded(tmp_path, mode, capsys):
    base = [*TINY, '--mode', mode, '--crop-size', '8', '--epochs', '1', '--epochs-low-lr', '0']
    base += ['--samples-per-epoch', '320']  # dense: enough crops that some are flipped
    plain, flipped = tmp_path / 'plain', tmp_path / 'flipped'
    weights = tmp_path / 'cvanet_census_bm_d16.pt'
    assert main([*base, '--out', str(plain)]) == 0
    assert main([*base, '--out', str(flipped), '--vflip', '--weights-out', str(weights)]) == 0
    # Same seed, same samples and initialisation: only the flips make the loss differ.
    assert _history(flipped)[0]['train_loss'] != _history(plain)[0]['train_loss']
    meta = load_weights(weights)[1]
    assert meta['vflip'] is True and '--vflip' in meta['command']
    assert 'upside down' in weights.with_suffix('.md').read_text()
    # A run started without flips cannot be resumed with them.
    assert main([*base, '--out', str(plain), '--vflip', '--epochs-low-lr', '1', '--resume']) == 2
    assert 'vflip' in capsys.readouterr().err


def test_bf16_mixed_precision_trains_and_says_so_on_the_card(tmp_path):
    out, weights = tmp_path / 'bf16', tmp_path / 'cvanet_census_bm_d16.pt'
    args = [*TINY, '--out', str(out), '--weights-out', str(weights), '--precision', 'bf16']
    assert main([*args, '--mode', 'dense', '--crop-size', '8', '--epochs', '1',
                 '--epochs-low-lr', '0']) == 0
    (record,) = _history(out)
    assert record['train_loss'] > 0 and record['val_auc'] is not None
    net, meta = load_weights(weights, matcher='census_bm', max_disparity=16)
    assert meta['precision'] == 'bf16'
    # The weights stay float32: autocast changes the arithmetic, not the parameters.
    assert all(p.dtype == torch.float32 for p in net.parameters())
    assert 'arithmetic: bf16 autocast' in weights.with_suffix('.md').read_text()


def test_bad_settings_exit_2(tmp_path, capsys):
    assert main(['--max-disparity', '16', '--out', str(tmp_path)]) == 2
    assert 'no training data' in capsys.readouterr().err
    args = ['--data-root', str(tmp_path), '--datasets', 'kitti2015', '--out', str(tmp_path)]
    assert main(args) == 2
    assert 'develop data set' in capsys.readouterr().err
    args = ['--data-root', str(tmp_path), '--datasets', 'eth3d', '--val-datasets', 'eth3d']
    assert main(args) == 2
    assert 'held apart' in capsys.readouterr().err


@pytest.mark.parametrize('arch', ['cvanet', 'ccnn'])
def test_diverged_training_stops_without_writing_weights(tmp_path, capsys, arch):
    out, weights = tmp_path / 'run', tmp_path / 'w.pt'
    args = [*TINY, '--arch', arch, '--out', str(out), '--weights-out', str(weights)]
    assert main([*args, '--epochs', '1', '--epochs-low-lr', '0', '--lr', '1e30']) == 2
    assert 'training diverged: the loss of epoch 1 is nan' in capsys.readouterr().err
    assert not weights.exists() and not (out / 'checkpoint.pt').exists()
    assert main([*args, '--lr', 'inf']) == 2
    assert 'lr must be finite' in capsys.readouterr().err


def test_resume_with_other_settings_is_refused(tmp_path, capsys):
    out = tmp_path / 'run'
    assert main([*TINY, '--out', str(out), '--epochs', '1', '--epochs-low-lr', '0']) == 0
    args = [*TINY, '--out', str(out), '--epochs', '2', '--resume', '--seed', '8']
    assert main(args) == 2
    assert 'seed: 7' in capsys.readouterr().err


def test_resume_keeps_the_learning_rate_of_every_finished_epoch(tmp_path, capsys, monkeypatch):
    from cva_confidence_ros.training import trainer

    out = tmp_path / 'run'
    base = [*TINY, '--out', str(out)]
    assert main([*base, '--epochs', '1', '--epochs-low-lr', '1']) == 0  # 1e-4, then 1e-5
    first = (out / 'checkpoint.pt').read_bytes()
    capsys.readouterr()

    def no_data(*args, **kwargs):
        raise AssertionError('a refused resume prepared the training data')

    real_prepare = trainer._prepare
    monkeypatch.setattr(trainer, '_prepare', no_data)
    refused = {
        # Another rate for epochs already trained: two schedules mixed in one run.
        ('--lr', '1e-3'): 'finished epoch 1 ran at lr 0.0001, this command would run it at '
        'lr 0.001 (lr: 0.0001 → 0.001)',
        ('--low-lr-factor', '0.5'): 'finished epoch 2 ran at lr 1e-05, this command would run '
        'it at lr 5e-05 (low_lr_factor: 0.1 → 0.5)',
        # Epoch 2 ran at the low rate; two epochs at the first rate would redo it at 1e-4.
        ('--epochs', '2'): 'finished epoch 2 ran at lr 1e-05, this command would run it at '
        'lr 0.0001 (epochs: 1 → 2)',
        # Fewer epochs than are finished: the weights would have more than the card says.
        ('--epochs-low-lr', '0'): 'it holds 2 finished epochs, this command trains 1 in all '
        '(epochs_low_lr: 1 → 0)',
    }
    for change, message in refused.items():
        args = [*base, '--epochs', '1', '--epochs-low-lr', '1', *change, '--resume']
        assert main(args) == 2, change
        err = capsys.readouterr().err.strip().splitlines()[-1]
        assert err.startswith('cva-train: error: cannot resume from'), err
        assert message in err, err
    assert (out / 'checkpoint.pt').read_bytes() == first

    # Training longer at the low rate keeps epochs 1-2 as they were: allowed.
    monkeypatch.setattr(trainer, '_prepare', real_prepare)
    assert main([*base, '--epochs', '1', '--epochs-low-lr', '2', '--resume']) == 0
    assert [h['lr'] for h in _history(out)] == pytest.approx([1e-4, 1e-5, 1e-5])


def test_resume_may_add_epochs_at_the_first_rate_while_none_ran_at_the_low_one(tmp_path):
    out = tmp_path / 'run'
    base = [*TINY, '--out', str(out)]
    assert main([*base, '--epochs', '1', '--epochs-low-lr', '0']) == 0
    assert main([*base, '--epochs', '2', '--epochs-low-lr', '1', '--resume']) == 0
    assert [h['lr'] for h in _history(out)] == pytest.approx([1e-4, 1e-4, 1e-5])


def test_resume_under_another_number_of_processes_is_refused(tmp_path, capsys):
    out = tmp_path / 'run'
    args = [*TINY, '--out', str(out), '--epochs', '1', '--epochs-low-lr', '1']
    assert main([*args[:-1], '0']) == 0
    state = torch.load(out / 'checkpoint.pt', weights_only=True)
    assert state['processes'] == 1
    # As if written by two processes under torchrun: a step averaged 2 × --batch-size samples.
    state['processes'] = 2
    torch.save(state, out / 'checkpoint.pt')
    assert main([*args, '--resume']) == 2
    assert 'the run trained in 2 processes, this one in 1 (processes: 2 → 1)' in (
        capsys.readouterr().err
    )
    # Checkpoints written before the count was recorded resume as before.
    del state['processes']
    torch.save(state, out / 'checkpoint.pt')
    assert main([*args, '--resume']) == 0
    assert [h['epoch'] for h in _history(out)] == [1, 2]


def test_a_fresh_run_does_not_overwrite_an_earlier_checkpoint(tmp_path, capsys):
    out = tmp_path / 'run'
    args = [*TINY, '--out', str(out), '--epochs', '1', '--epochs-low-lr', '0']
    assert main(args) == 0
    first = (out / 'checkpoint.pt').read_bytes()
    capsys.readouterr()
    assert main([*args, '--seed', '8']) == 2
    err = capsys.readouterr().err.strip()
    assert err.count('\n') == 0
    assert err.startswith(f'cva-train: error: --out {out} holds the checkpoint of an earlier run')
    assert '--resume to continue it, --overwrite to start over' in err
    assert (out / 'checkpoint.pt').read_bytes() == first
    assert main([*args, '--seed', '8', '--overwrite']) == 0
    assert (out / 'checkpoint.pt').read_bytes() != first


def test_config_validation():
    with pytest.raises(ConfigError, match='mode'):
        TrainConfig(synthetic=1, mode='fancy')
    with pytest.raises(ConfigError, match='2·D'):
        TrainConfig(synthetic=1, max_disparity=64, synthetic_size=(64, 100))
    with pytest.raises(ConfigError, match="precision must be one of.*'fp16'"):
        TrainConfig(synthetic=1, precision='fp16')
    with pytest.raises(ConfigError, match="unknown arch 'resnet'.*cvanet"):
        TrainConfig(synthetic=1, arch='resnet')
    config = TrainConfig(synthetic=1, epochs=2, epochs_low_lr=1, lr=1e-3)
    assert [config.lr_at(e) for e in range(3)] == pytest.approx([1e-3, 1e-3, 1e-4])
    assert config.synthetic_hw == (128, 256)


@pytest.mark.parametrize(
    ('train', 'val', 'named'),
    [
        ('kitti2012', 'kitti2012', 'both use kitti2012'),
        ('kitti2012', 'kitti2012:training', 'kitti2012 (kitti2012 and kitti2012:training; the '
         'splits of kitti2012 are sizes or subsets of the same scenes)'),
        ('eth3d', 'eth3d:two_view_training', 'eth3d (eth3d and eth3d:two_view_training;'),
        ('middlebury2005:HalfSize', 'middlebury2005:ThirdSize', 'middlebury2005 ('),
        ('middlebury2001,middlebury2006:FullSize', 'middlebury2006', 'both use middlebury2006'),
        ('flyingthings3d', 'flyingthings3d:TEST', 'flyingthings3d without a split is all of '
         'its splits, TRAIN, TEST'),
        ('flyingthings3d:TEST', 'flyingthings3d:TEST', 'both use flyingthings3d:TEST'),
    ],
)
def test_validation_data_of_the_same_scenes_is_refused_whatever_the_split(train, val, named):
    with pytest.raises(ConfigError, match='held apart') as caught:
        TrainConfig(data_root='/nonexistent', datasets=train.split(','), val_datasets=(val,))
    assert named in str(caught.value)


def test_disjoint_splits_may_train_and_validate():
    # FlyingThings3D's TRAIN and TEST are different scenes; other data sets are held apart.
    config = TrainConfig(data_root='/nonexistent', datasets=('flyingthings3d:TRAIN', 'eth3d'),
                         val_datasets=('flyingthings3d:TEST', 'middlebury2005'))
    assert config.val_datasets == ('flyingthings3d:TEST', 'middlebury2005')


@pytest.mark.parametrize(
    ('specs', 'message'),
    [
        (('kitti2012', 'eth3d', 'kitti2012'), 'kitti2012 is given twice'),
        (('kitti2012', 'kitti2012:training'), 'kitti2012:training and kitti2012 hold the same'),
        (('flyingthings3d:TRAIN', 'flyingthings3d'), 'flyingthings3d and flyingthings3d:TRAIN'),
    ],
)
def test_scenes_given_twice_are_refused(specs, message):
    # Before: each scene of a data set given twice was prepared and trained on twice as often.
    with pytest.raises(ConfigError, match=message):
        TrainConfig(data_root='/nonexistent', datasets=specs)
    with pytest.raises(ConfigError, match=message):
        TrainConfig(data_root='/nonexistent', datasets=('middlebury2005',), val_datasets=specs)
    # Sizes of the same scenes are a choice (each size its own samples); disjoint splits too.
    sizes = ('middlebury2006:ThirdSize', 'middlebury2006:HalfSize', 'flyingthings3d:TRAIN')
    TrainConfig(data_root='/nonexistent', datasets=sizes, val_datasets=('flyingthings3d:TEST',))


@pytest.mark.parametrize(
    ('dataset', 'split'), [('middlebury2014', ''), ('motorcycle', ''), ('motorcycle', ':x')]
)
def test_develop_data_is_never_trained_on(dataset, split):
    with pytest.raises(ConfigError, match=f'{dataset} is .*develop') as caught:
        TrainConfig(data_root='/nonexistent', datasets=('kitti2012', dataset + split))
    assert 'never train on it' in str(caught.value)
    if dataset == 'motorcycle':
        assert 'Middlebury 2014 Motorcycle scene of middlebury2014' in str(caught.value)
    # Validating on it is allowed, as for the develop data sets.
    TrainConfig(data_root='/nonexistent', datasets=('kitti2012',), val_datasets=(dataset,))


def test_train_on_real_data_sets(tmp_path):
    """The loader path: one KITTI 2012 scene, halved until it fits D, validated on ETH3D."""
    root = _data_root()
    out, weights = tmp_path / 'real', tmp_path / 'w.pt'
    args = [
        '--max-disparity', '16', '--data-root', str(root), '--datasets', 'kitti2012',
        '--max-scenes', '1', '--val-datasets', 'eth3d', '--val-pixels', '20',
        '--epochs', '1', '--epochs-low-lr', '0', '--batch-size', '16',
        '--samples-per-epoch', '16', '--threads', '1', '--no-progress',
        '--out', str(out), '--weights-out', str(weights),
    ]  # fmt: skip
    assert main(args) == 0
    meta = load_weights(weights)[1]
    (scene,) = meta['scenes']
    assert scene['name'] == 'kitti2012/000000'
    assert scene['factor'] == 8  # KITTI disparities reach ~230 px: 230 / 8 < 16
    assert meta['val_scenes'][0]['name'].startswith('eth3d/')
    assert meta['datasets'] == ['kitti2012'] and meta['val_pixels'] == 20


def test_unwritable_outputs_are_refused_before_training(tmp_path, capsys):
    afile = tmp_path / 'afile'
    afile.write_text('not a folder')
    one = ['--epochs', '1', '--epochs-low-lr', '0']
    assert main([*TINY, *one, '--out', str(afile)]) == 2
    assert '--out' in capsys.readouterr().err
    out = tmp_path / 'run'
    assert main([*TINY, *one, '--out', str(out), '--weights-out', str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert 'error: --weights-out' in err and 'is a folder' in err
    assert not out.exists()  # refused before the run folder, its log or any scene


def test_resume_from_something_that_is_not_a_checkpoint(tmp_path, capsys):
    out = tmp_path / 'run'
    args = [*TINY, '--out', str(out), '--epochs', '1', '--epochs-low-lr', '0', '--resume']
    out.mkdir()
    checkpoint = out / 'checkpoint.pt'
    save_weights(CVANet(16), checkpoint, {'matcher': 'census_bm'})
    assert main(args) == 2
    assert 'is a weights file, not a training checkpoint; to start from weights use ' \
        '--init-weights' in capsys.readouterr().err
    torch.save([1, 2, 3], checkpoint)
    assert main(args) == 2
    assert 'not a cva-train checkpoint' in capsys.readouterr().err
    # A real checkpoint of a network of another depth, relabelled: the tensors do not fit.
    other = tmp_path / 'other'
    assert main([*TINY, '--out', str(other), '--epochs', '1', '--epochs-low-lr', '0']) == 0
    state = torch.load(other / 'checkpoint.pt', weights_only=True)
    state['model'] = CVANet(20).state_dict()
    torch.save(state, checkpoint)
    assert main(args) == 2
    err = capsys.readouterr().err
    assert 'does not fit this network' in err.splitlines()[-1] and 'size mismatch' in err

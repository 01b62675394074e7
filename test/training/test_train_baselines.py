"""``cva-train --arch ccnn|lfn|lgcnet`` on tiny synthetic pairs: weights, card, stages, resume."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.model import load_weights
from cva_confidence_ros.training import TrainConfig
from cva_confidence_ros.training.baselines import crop_side, split_scenes, train_baseline
from cva_confidence_ros.training.cli import main

TINY = [
    '--matcher', 'census_bm',
    '--max-disparity', '16',
    '--synthetic', '2',
    '--synthetic-size', '32x40',
    '--val-synthetic', '1',
    '--val-pixels', '60',
    '--mode', 'dense',
    '--crop-size', '16',
    '--batch-size', '256',
    '--samples-per-epoch', '400',
    '--lr', '1e-3',
    '--seed', '3',
    '--threads', '1',
    '--no-progress',
]  # fmt: skip


def _history(out: Path) -> list[dict]:
    return json.loads((out / 'history.json').read_text())


@pytest.mark.parametrize(
    ('arch', 'title'), [('ccnn', '# CCNN weights'), ('lfn', '# LFN weights'),
                        ('lgcnet', '# LGC-Net weights')]
)
def test_each_arch_trains_through_cva_train(tmp_path, arch, title):
    out, weights = tmp_path / 'run', tmp_path / 'models' / f'{arch}_census_bm_d16.pt'
    args = [*TINY, '--arch', arch, '--out', str(out), '--weights-out', str(weights),
            '--epochs', '1', '--epochs-low-lr', '1']
    assert main(args) == 0
    net, meta = load_weights(weights, matcher='census_bm', max_disparity=16, arch=arch)
    assert meta['arch'] == arch and meta['command'].startswith('cva-train')
    assert [s['name'] for s in meta['scenes']] == ['synthetic/seed0', 'synthetic/seed1']
    assert 0.0 <= meta['final_val_auc'] <= 1.0 and meta['final_train_loss'] > 0
    history = _history(out)
    markdown = weights.with_suffix('.md').read_text()
    assert markdown.startswith(title)
    assert 'CVA-Net' not in markdown.split('\n')[2]
    # CCNN reads the disparity alone; LFN and LGC-Net also the grey image.
    inputs = 'disparity ÷ D (NaN → 0) only' if arch == 'ccnn' else 'grey'
    assert inputs in markdown and 'wall time' in markdown
    if arch == 'lgcnet':
        # Two stages, each with the 1 + 1 epoch schedule; stage 1 reports both parts' AUCs.
        assert [h['stage'] for h in history] == ['parts', 'parts', 'fusion', 'fusion']
        assert [h['lr'] for h in history] == pytest.approx([1e-3, 1e-4, 1e-3, 1e-4])
        assert all(0 <= h['val_auc_global'] <= 1 for h in history[:2])
        assert meta['storage'] == 'float16' and meta['crop_size'] == 16
        # Default split: parts on seed0, fusion on seed1 (sorted names, alternating).
        assert meta['fusion_split'] == 'alternate'
        assert meta['parts_scenes'] == ['synthetic/seed0']
        assert meta['fusion_scenes'] == ['synthetic/seed1']
        # The written fusion is the stage-2 epoch with the best validation AUC.
        fusion_aucs = {h['epoch']: h['val_auc'] for h in history[2:]}
        assert meta['fusion_epoch_selected'] == min(fusion_aucs, key=fusion_aucs.get)
        assert meta['final_val_auc'] == pytest.approx(min(fusion_aucs.values()))
        assert 'fusion split alternate' in markdown
        assert 'ConfNet' in markdown and 'stage 1 epoch 1' in markdown
    else:
        assert [h['lr'] for h in history] == pytest.approx([1e-3, 1e-4])
        assert all(h['samples'] >= 400 for h in history)


def test_resume_repeats_an_uninterrupted_run(tmp_path):
    straight = tmp_path / 'straight'
    common = [*TINY, '--arch', 'ccnn', '--epochs-low-lr', '0']
    assert main([*common, '--epochs', '2', '--out', str(straight)]) == 0
    split = tmp_path / 'split'
    assert main([*common, '--epochs', '1', '--out', str(split)]) == 0
    assert main([*common, '--epochs', '2', '--out', str(split), '--resume']) == 0
    a = torch.load(straight / 'checkpoint.pt', weights_only=True)['model']
    b = torch.load(split / 'checkpoint.pt', weights_only=True)['model']
    for key in a:
        torch.testing.assert_close(a[key], b[key], rtol=0, atol=0)
    assert len(_history(split)) == 2
    # Another arch's checkpoint is refused with exit code 2.
    assert main([*TINY, '--arch', 'lfn', '--epochs', '2', '--out', str(split), '--resume']) == 2


def test_lgcnet_resume_keeps_the_stage_of_every_finished_epoch(tmp_path, capsys):
    out = tmp_path / 'run'
    args = [*TINY, '--arch', 'lgcnet', '--out', str(out), '--epochs-low-lr', '0',
            '--fusion-split', 'none']
    assert main([*args, '--epochs', '1']) == 0  # epoch 1: CCNN + ConfNet, epoch 2: fusion
    capsys.readouterr()
    # Two epochs per stage would make finished epoch 2 a CCNN + ConfNet epoch again.
    assert main([*args, '--epochs', '2', '--resume']) == 2
    err = capsys.readouterr().err
    assert ('finished epoch 2 ran at lr 0.001 (fusion stage), this command would run it at '
            'lr 0.001 (parts stage) (epochs: 1 → 2)') in err
    assert [h['stage'] for h in _history(out)] == ['parts', 'fusion']


def test_resume_refuses_other_arch(tmp_path):
    common = [*TINY, '--epochs', '1', '--epochs-low-lr', '0', '--out', str(tmp_path)]
    assert main([*common, '--arch', 'ccnn']) == 0
    config = TrainConfig(arch='lfn', synthetic=2, synthetic_size=(32, 40), max_disparity=16,
                         out=str(tmp_path), resume=True, progress=False, threads=1)
    with pytest.raises(ConfigError, match="arch: 'ccnn' → 'lfn'"):
        train_baseline(config)


def test_warm_start_and_teacher_are_refused(tmp_path, capsys):
    common = [*TINY, '--arch', 'ccnn', '--out', str(tmp_path)]
    assert main([*common, '--init-weights', str(tmp_path / 'any.pt')]) == 2
    assert '--arch ccnn trains from scratch' in capsys.readouterr().err
    assert main([*common, '--teacher', str(tmp_path / 'any.pt'), '--distill-weight', '0.5']) == 2
    assert '--arch ccnn trains from scratch' in capsys.readouterr().err


def test_crop_side_rules():
    class _Scene:
        def __init__(self, shape):
            self.shape = shape

    scenes = [_Scene((40, 90)), _Scene((50, 60))]
    base = TrainConfig(synthetic=1, max_disparity=16, mode='dense', crop_size=64)
    assert crop_side(base.replace(arch='ccnn'), scenes) == 40
    assert crop_side(base.replace(arch='lgcnet'), scenes) == 32
    assert crop_side(base.replace(arch='lfn', mode='sparse'), scenes) == 1
    with pytest.raises(ConfigError, match='--mode dense'):
        crop_side(base.replace(arch='lgcnet', mode='sparse'), scenes)
    with pytest.raises(ConfigError, match='at least 16 px'):
        crop_side(base.replace(arch='lgcnet'), [_Scene((12, 90))])


def test_split_scenes_is_deterministic_disjoint_and_covering():
    names = [f'synthetic/seed{i}' for i in range(12)] + ['kitti2012/000001', 'eth3d/a',
                                                         'kitti2012/000000']
    parts, fusion = split_scenes(names, 'alternate')
    assert set(parts).isdisjoint(fusion)
    assert sorted(parts + fusion) == list(range(len(names)))
    assert abs(len(parts) - len(fusion)) <= 1
    # Alternating over the names in sorted order, whatever the loading order.
    ordered = sorted(names)
    assert sorted(names[i] for i in parts) == ordered[0::2]
    assert sorted(names[i] for i in fusion) == ordered[1::2]
    shuffled = names[::-1]
    parts_b, fusion_b = split_scenes(shuffled, 'alternate')
    assert {shuffled[i] for i in parts_b} == {names[i] for i in parts}
    assert split_scenes(names, 'alternate') == (parts, fusion)
    everything = list(range(len(names)))
    assert split_scenes(names, 'none') == (everything, everything)
    with pytest.raises(ConfigError, match='at least 2 training scenes'):
        split_scenes(['synthetic/seed0'], 'alternate')
    with pytest.raises(ConfigError, match='distinct'):
        split_scenes(['a/b', 'a/b'], 'alternate')
    with pytest.raises(ConfigError, match='unknown fusion split'):
        split_scenes(names, 'halves')


def test_fusion_split_none_and_resume_guard(tmp_path):
    out, weights = tmp_path / 'run', tmp_path / 'lgcnet.pt'
    args = [*TINY, '--arch', 'lgcnet', '--out', str(out), '--weights-out', str(weights),
            '--epochs', '1', '--epochs-low-lr', '0', '--fusion-split', 'none']
    assert main(args) == 0
    _, meta = load_weights(weights, matcher='census_bm', max_disparity=16, arch='lgcnet')
    both = ['synthetic/seed0', 'synthetic/seed1']
    assert meta['parts_scenes'] == both and meta['fusion_scenes'] == both
    assert [h['stage'] for h in _history(out)] == ['parts', 'fusion']
    # Resuming with the other split is refused (exit code 2), an unknown split too.
    resumed = [*args[:-1], 'alternate', '--resume']
    assert main(resumed) == 2
    with pytest.raises(ConfigError, match='fusion_split'):
        TrainConfig(synthetic=1, fusion_split='halves')

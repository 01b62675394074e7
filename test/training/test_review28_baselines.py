"""Review regressions: training of the disparity-map baselines (CCNN, LFN, LGC-Net)."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest
from train_test_utils import TINY

from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.model import load_weights
from cva_confidence_ros.training import TrainConfig, baselines
from cva_confidence_ros.training.baselines import (
    DisparityScene,
    crop_side,
    pixel_crops,
    split_scenes,
    train_baseline,
)
from cva_confidence_ros.training.cli import main
from cva_confidence_ros.training.data import sample_index


def _scene(name: str, height: int, width: int) -> DisparityScene:
    planes = np.zeros((height + 16, width + 16), np.float32)
    labelled = np.ones((height, width), bool)
    return DisparityScene(name, 1, planes, planes.copy(), labelled, labelled.copy())


def test_pixel_crops_take_every_labelled_pixel_once_before_any_repeats():
    scenes = [_scene('toy/0', 50, 60), _scene('toy/1', 40, 30)]  # 4200 pixels, > 4096
    index = sample_index(scenes)
    n = len(index)
    crops = pixel_crops(index, 2 * n + 7, seed=1, epoch=0)
    assert crops.scene.size == 2 * n + 7 and set(crops.n_labelled.tolist()) == {1}
    keys = list(zip(crops.scene.tolist(), crops.y0.tolist(), crops.x0.tolist(), strict=True))
    assert len(set(keys[:n])) == n and len(set(keys[n : 2 * n])) == n
    assert sorted(Counter(keys).values())[-1] == 3
    for column in (crops.scene, crops.y0, crops.x0, crops.n_labelled):
        assert column.dtype == np.int32


def test_a_sparse_epoch_trains_on_every_labelled_pixel_once(tmp_path, monkeypatch):
    # dense_crops with 1-pixel crops drew a new permutation per 4096 samples: of the 9216
    # labelled pixels of an epoch about a quarter went unseen, others twice.
    seen: list[tuple[int, int, int]] = []

    def record(net, stage, scenes, crops, step, side, device):
        assert side == 1
        seen.extend(zip(crops.scene[step].tolist(), crops.y0[step].tolist(),
                        crops.x0[step].tolist(), strict=True))
        return sum(p.sum() for p in net.parameters()) * 0.0, len(step)

    monkeypatch.setattr(baselines, '_step_loss', record)
    config = TrainConfig(arch='ccnn', matcher='census_bm', max_disparity=16, synthetic=2,
                         synthetic_size=(48, 96), mode='sparse', batch_size=512, epochs=1,
                         epochs_low_lr=0, out=str(tmp_path), progress=False, threads=1)
    summary = train_baseline(config)
    assert summary['labelled_pixels'] == 2 * 48 * 96
    assert len(seen) == len(set(seen)) == summary['labelled_pixels']


def test_lgcnet_crops_below_16_px_are_refused_before_preparing(tmp_path, capsys):
    args = [*TINY, '--arch', 'lgcnet', '--mode', 'dense', '--crop-size', '8',
            '--out', str(tmp_path / 'run')]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert 'lgcnet needs crops of at least 16 px' in err and 'got --crop-size 8' in err
    assert 'scene synthetic/seed0' not in err  # no scene matched before the refusal
    # Without scenes only the options are checked.
    config = TrainConfig(arch='lgcnet', synthetic=1, max_disparity=16, mode='dense',
                         crop_size=40)
    assert crop_side(config, []) == 32
    assert crop_side(config.replace(arch='ccnn'), []) == 40


def test_repeated_scene_names_are_named_in_the_split_error():
    names = ['middlebury2014/Adirondack', 'middlebury2014/Jadeplant',
             'middlebury2014/Adirondack', 'middlebury2014/Motorcycle']
    with pytest.raises(ConfigError, match='given more than once: middlebury2014/Adirondack '
                                          r'\(a scene in two sizes'):
        split_scenes(names, 'alternate')


@pytest.mark.parametrize('arch', ['ccnn', 'lgcnet'])
def test_the_card_states_the_share_of_confident_outputs(tmp_path, arch):
    # The card's '… of the outputs ≥ 0.5' was '—' for every baseline.
    weights = tmp_path / f'{arch}.pt'
    args = [*TINY, '--arch', arch, '--mode', 'dense', '--crop-size', '16', '--epochs', '1',
            '--epochs-low-lr', '1', '--out', str(tmp_path / 'run'),
            '--weights-out', str(weights)]
    assert main(args) == 0
    _, meta = load_weights(weights, arch=arch)
    history = meta['history']
    assert 0.0 <= meta['final_val_high'] <= 1.0
    if arch == 'lgcnet':  # the fusion epoch whose weights were written
        chosen = [h for h in history if h['epoch'] == meta['fusion_epoch_selected']]
        assert meta['final_val_high'] == chosen[0]['val_high']
    else:
        assert meta['final_val_high'] == history[-1]['val_high']
    assert '— of the outputs' not in weights.with_suffix('.md').read_text()

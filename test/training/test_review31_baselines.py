"""Review 31 of the disparity-map baselines (CCNN, LFN, LGC-Net) and their training."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.model.baselines import CCNN, LFN, ConfNet, FusionNet, network_inputs
from cva_confidence_ros.training import TrainConfig, trainer
from cva_confidence_ros.training.baselines import train_baseline

# Two 32×40 synthetic training scenes (every pixel labelled), one validation scene.
TINY = TrainConfig(
    arch='lgcnet', matcher='census_bm', max_disparity=16, synthetic=2, synthetic_size=(32, 40),
    val_synthetic=1, val_pixels=60, mode='dense', crop_size=16, batch_size=256, lr=1e-3,
    seed=3, threads=1, progress=False, epochs=1, epochs_low_lr=0,
)


@pytest.mark.parametrize(
    'disparity',
    [
        np.full((2, 3), 8 + 5j),  # was 0.5: the imaginary part dropped with a warning
        np.ones((2, 3), bool),  # was 1 px (0.0625 at D = 16)
        np.full((2, 3), '8'),  # was parsed: 0.5
    ],
)
def test_network_inputs_refuses_a_disparity_that_is_not_real_numbers(disparity):
    with pytest.raises(InputError, match=f'disparity must hold real numbers.*{disparity.dtype}'):
        network_inputs(disparity, np.zeros((2, 3), np.uint8), 16)
    # Integer disparities stay welcome.
    plane, _ = network_inputs(np.full((2, 3), 8, np.int16), np.zeros((2, 3), np.uint8), 16)
    assert plane.dtype == np.float32 and float(plane[0, 0]) == 0.5


def _zeros(*shape: int) -> torch.Tensor:
    return torch.zeros((1, 1, *shape))


@pytest.mark.parametrize(
    ('call', 'message'),
    [
        # Each was a raw torch RuntimeError ("Kernel size can't be greater than actual input
        # size" / "Sizes of tensors must match").
        (lambda: CCNN(16)(_zeros(7, 7), _zeros(7, 7)), r'at least 9 px .*got \(7, 7\)'),
        (lambda: LFN(16).forward_logits(_zeros(8, 9), _zeros(8, 9)), r'at least 9 px'),
        (lambda: ConfNet(4).forward_logits(_zeros(16, 16), _zeros(32, 32)),
         r'expected image of the disparity shape \(1, 1, 16, 16\); got \(1, 1, 32, 32\)'),
        (lambda: FusionNet().forward_logits(_zeros(9, 9), _zeros(9, 9), _zeros(8, 9)),
         r'expected global confidence of the disparity shape'),
    ],
)
def test_forward_logits_name_inputs_that_do_not_fit(call, message):
    with pytest.raises(InputError, match=message):
        call()


def test_lgcnet_stage_epochs_draw_as_many_samples_as_the_stage_has_labelled_pixels(tmp_path):
    # With the default alternate split each stage learns from one of the two scenes (1280
    # labelled pixels), yet every stage epoch drew all 2560 training pixels' worth: each stage
    # saw its scene twice an epoch.
    summary = train_baseline(TINY.replace(out=str(tmp_path)))
    assert summary['labelled_pixels'] == 2560
    history = json.loads((tmp_path / 'history.json').read_text())
    assert [h['stage'] for h in history] == ['parts', 'fusion']
    # Dense crops stop once they hold at least the epoch's samples (crops of 16² outputs).
    assert all(1280 <= h['samples'] < 1280 + 256 for h in history)
    assert summary['samples_per_epoch'] == summary['fusion_samples_per_epoch'] == 1280


def test_lgcnet_resume_keeps_the_validation_its_best_fusion_epoch_was_chosen_on(
    tmp_path, monkeypatch
):
    # Resumed with other validation pixels, the next fusion epochs were compared with the kept
    # one on another set: stopped after run epoch 3 (fusion epoch 1) with 300 pixels and
    # resumed with 20, it kept epoch 3 (0.534 on 300 px beat 0.685 on 20 px), where 300
    # pixels throughout pick epoch 4.
    config = TINY.replace(out=str(tmp_path), epochs_low_lr=1, fusion_split='none')
    save = trainer._save_checkpoint

    class Stop(Exception):
        pass

    def save_then_stop(path, state):
        save(path, state)
        if state['epoch'] == 3:
            raise Stop

    monkeypatch.setattr(trainer, '_save_checkpoint', save_then_stop)
    with pytest.raises(Stop):
        train_baseline(config)
    monkeypatch.setattr(trainer, '_save_checkpoint', save)
    with pytest.raises(ConfigError, match=r'val_pixels: 60 → 200\).*best fusion epoch'):
        train_baseline(config.replace(val_pixels=200, resume=True))
    with pytest.raises(ConfigError, match=r'val_synthetic: 1 → 2'):
        train_baseline(config.replace(val_synthetic=2, resume=True))

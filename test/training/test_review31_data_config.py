"""Review regressions: training samples, the training configuration and ``cva-train --help``."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.training.cli import build_parser
from cva_confidence_ros.training.config import TrainConfig
from cva_confidence_ros.training.data import PreparedScene, epoch_order, validation_subset


def _scene(height: int = 4, width: int = 5) -> PreparedScene:
    volume = torch.zeros((16, height + 12, width + 12), dtype=torch.float16)
    labelled = np.ones((height, width), dtype=bool)
    return PreparedScene('toy/0', 1, volume, labelled, labelled.copy())


@pytest.mark.parametrize('n_samples', [0, -3])
def test_an_epoch_of_no_samples_is_empty(n_samples):
    # np.concatenate of no permutation raised 'need at least one array to concatenate'
    # (dense_crops already returned no crops for such counts).
    order = epoch_order(10, n_samples, seed=0, epoch=0)
    assert order.shape == (0,) and order.dtype == np.int64


def test_a_negative_validation_pixel_count_takes_no_pixel():
    # permutation(20)[:-3] took 17 of the 20 pixels.
    subset = validation_subset([_scene()], -3, seed=0)
    assert [ys.size for ys, _ in subset] == [0]
    assert [ys.size for ys, _ in validation_subset([_scene()], 30, seed=0)] == [20]


@pytest.mark.parametrize('device', ['cuda:x', 'cuda:', 'cuda:-1', 'cuda:0x'])
def test_a_cuda_device_without_a_gpu_number_is_refused_by_the_config(device):
    # Anything starting with 'cuda:' passed, although the message asks for cuda:N.
    with pytest.raises(ConfigError, match=f"cuda:N; got '{device}'"):
        TrainConfig(synthetic=1, device=device)
    assert TrainConfig(synthetic=1, device='cuda:1').device == 'cuda:1'


@pytest.mark.parametrize('size', [(128, 256, 3), (128,), (128.9, 256), '128x256', 128])
def test_a_synthetic_size_that_is_not_two_integers_is_refused(size):
    # (128, 256, 3) ended in 'too many values to unpack', (128.9, 256) became 128×256
    # silently, '128x256' raised 'invalid literal for int()'.
    with pytest.raises(ConfigError, match=r'synthetic_size must be two integers \(H, W\)'):
        TrainConfig(synthetic=1, synthetic_size=size)
    assert TrainConfig(synthetic=1, synthetic_size=[np.int64(64), 256]).synthetic_hw == (64, 256)


def test_numpy_integers_and_floats_are_numbers_and_stay_json():
    # np.int64(64) was refused as 'max_disparity must be an integer >= 13; got np.int64(64)'.
    config = TrainConfig(
        synthetic=np.int64(2),
        max_disparity=np.int32(32),
        batch_size=np.int64(8),
        lr=np.float32(1e-3),
    )
    assert (config.synthetic, config.max_disparity, config.batch_size) == (2, 32, 8)
    assert type(config.max_disparity) is int and type(config.lr) is float
    json.dumps(config.to_dict())


@pytest.mark.parametrize(
    ('option', 'value'),
    [('lr', '1e-4'), ('lr', True), ('low_lr_factor', None), ('distill_weight', 'x')],
)
def test_a_rate_that_is_not_a_number_is_a_config_error(option, value):
    # A string ended in a TypeError from math.isfinite or '<='; lr=True trained at 1.0.
    with pytest.raises(ConfigError, match=f'{option} must be a real number; got'):
        TrainConfig(synthetic=1, **{option: value})


@pytest.mark.parametrize('option', ['datasets', 'val_datasets'])
def test_a_string_of_data_sets_is_refused_as_a_string(option):
    # tuple('kitti2012') made nine one-letter data sets: "unknown data set 'k'".
    expected = f"{option} must be a sequence.*got the string 'kitti2012'"
    with pytest.raises(ConfigError, match=expected):
        TrainConfig(synthetic=1, data_root='/nonexistent', **{option: 'kitti2012'})


def test_help_shows_every_default_once(monkeypatch):
    # --epochs, --epochs-low-lr, --batch-size, --lr and --seed had no help text, so argparse
    # showed no default for them; --synthetic-size and --samples-per-epoch named their
    # default and then '(default: None)'.
    monkeypatch.setenv('COLUMNS', '400')
    lines: dict[str, str] = {}  # option → its entry (a long option's help is on the next line)
    option = ''
    for line in build_parser().format_help().splitlines():
        if line.startswith('  --'):
            option = line.split()[0]
            lines[option] = line
        elif option and line.startswith('      '):
            lines[option] += line
        else:
            option = ''
    for option, default in [
        ('--epochs', '10'),
        ('--epochs-low-lr', '3'),
        ('--batch-size', '256'),
        ('--lr', '0.0001'),
        ('--seed', '0'),
        ('--max-scenes', 'all'),
    ]:
        assert f'(default: {default})' in lines[option], lines[option]
    for option in ('--synthetic-size', '--samples-per-epoch', '--data-root', '--datasets'):
        assert 'default: None' not in lines[option] and 'default: ()' not in lines[option]
        assert lines[option].count('default') <= 1, lines[option]

"""Review regressions: the training configuration's bool, path and data-set fields."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.training.config import TrainConfig


@pytest.mark.parametrize('option', ['vflip', 'resume', 'overwrite', 'progress'])
@pytest.mark.parametrize('value', ['false', 'no', 1, None])
def test_a_switch_that_is_not_a_bool_is_refused(option, value):
    # vflip='no' was kept as it was and is true: the run flipped half of its samples.
    with pytest.raises(ConfigError, match=f'{option} must be True or False; got'):
        TrainConfig(synthetic=1, **{option: value})


def test_a_numpy_bool_switch_becomes_a_plain_bool():
    # np.True_ stayed: the run ended with 'Object of type bool is not JSON serializable'
    # after its training, and its checkpoint could not be read back (weights_only).
    config = TrainConfig(synthetic=1, vflip=np.bool_(True), progress=np.bool_(False))
    assert config.vflip is True and config.progress is False
    json.dumps(config.to_dict())


def test_path_options_are_kept_as_strings(tmp_path):
    # A Path went into the checkpoint's config, which torch.load(weights_only=True) refuses:
    # '--resume' failed with 'cannot read checkpoint ... (UnpicklingError ...)'.
    config = TrainConfig(
        synthetic=1,
        out=tmp_path / 'run',
        weights_out=tmp_path / 'w.pt',
        init_weights=tmp_path / 'init.pt',
        teacher=tmp_path / 'teacher.pt',
        distill_weight=0.5,
    )
    data = config.to_dict()
    for option in ('out', 'weights_out', 'init_weights', 'teacher'):
        assert type(data[option]) is str
    assert data['out'] == str(tmp_path / 'run')
    json.dumps(data)
    torch.save({'config': data}, tmp_path / 'state.pt')
    assert torch.load(tmp_path / 'state.pt', weights_only=True)['config'] == data
    assert TrainConfig(**data) == config  # the round trip changes nothing


@pytest.mark.parametrize(('option', 'value'), [('out', None), ('out', 3), ('data_root', 1.5)])
def test_a_path_option_that_is_not_a_path_is_refused(option, value):
    # out=None ended in check_run_setup with 'expected str, bytes or os.PathLike object'.
    with pytest.raises(ConfigError, match=f'{option} must be a path'):
        TrainConfig(synthetic=1, **{option: value})


@pytest.mark.parametrize('option', ['datasets', 'val_datasets'])
@pytest.mark.parametrize('value', [None, [3], ('kitti2012', Path('eth3d'))])
def test_data_sets_that_are_not_strings_are_refused(option, value):
    # None raised "'NoneType' object is not iterable"; [3] an AttributeError ('partition').
    with pytest.raises(ConfigError, match=f'{option} must be a sequence of data set specs'):
        TrainConfig(synthetic=1, data_root='/nonexistent', **{option: value})


@pytest.mark.parametrize('option', ['lr', 'low_lr_factor', 'distill_weight'])
def test_an_int_beyond_float_is_a_config_error(option):
    # float(10**400) raised a bare OverflowError.
    with pytest.raises(ConfigError, match=option):
        TrainConfig(synthetic=1, **{option: 10**400})

"""Review regressions: training configuration, model card."""

from __future__ import annotations

import pytest
from train_test_utils import TINY

from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.training import TrainConfig
from cva_confidence_ros.training.card import write_model_card
from cva_confidence_ros.training.cli import build_parser, main


def test_card_names_the_crop_side_that_was_run(tmp_path):
    # Dense crops are clipped to the smallest training scene side (16 here); the card said
    # 'crops of 32² outputs', the requested --crop-size.
    scenes = [
        {'name': 'synthetic/seed0', 'factor': 1, 'height': 16, 'width': 40},
        {'name': 'synthetic/seed1', 'factor': 1, 'height': 24, 'width': 40},
    ]
    facts = {
        'arch': 'cvanet',
        'matcher': 'census_bm',
        'mode': 'dense',
        'crop_size': 32,
        'scenes': scenes,
    }
    md_path, _ = write_model_card(tmp_path / 'w.pt', facts)
    assert 'crops of 16² outputs' in md_path.read_text()
    md_path, _ = write_model_card(tmp_path / 'v.pt', {**facts, 'crop_size': 8})
    assert 'crops of 8² outputs' in md_path.read_text()


@pytest.mark.parametrize(
    ('train', 'val'),
    [
        (('kitti2012:testing',), ()),
        (('kitti2012',), ('kitti2015:foo',)),
        (('flyingthings3d:TRAIN',), ('flyingthings3d:test',)),
        (('sceneflow_extra:a',), ()),
    ],
)
def test_a_split_the_data_set_lacks_is_refused_by_the_config(train, val):
    # It was accepted here and refused only when the scenes were listed: for validation data
    # after every training scene had been matched.
    with pytest.raises(ConfigError, match='has splits'):
        TrainConfig(data_root='/nonexistent', datasets=train, val_datasets=val)


def test_a_seed_torch_cannot_take_is_a_config_error(tmp_path, capsys):
    # --seed 20000000000000 passed the config, then the epoch's torch.manual_seed(seed ·
    # 1 000 003 + …) raised a ValueError traceback after the data were prepared.
    with pytest.raises(ConfigError, match='seed must be an integer in'):
        TrainConfig(synthetic=1, seed=2**64)
    assert main([*TINY, '--seed', '20000000000000', '--out', str(tmp_path / 'run')]) == 2
    assert 'seed must be an integer in [0, 4294967295]' in capsys.readouterr().err
    assert TrainConfig(synthetic=1, seed=2**32 - 1).seed == 2**32 - 1


@pytest.mark.parametrize('arch', ['ccnn', 'lfn', 'lgcnet'])
def test_baselines_refuse_the_options_they_ignore(arch):
    # The baselines' training has no flips and no bf16 autocast: both were accepted and
    # silently ignored.
    with pytest.raises(ConfigError, match=f'--arch {arch} .*--vflip'):
        TrainConfig(synthetic=1, arch=arch, vflip=True)
    with pytest.raises(ConfigError, match="precision 'bf16'"):
        TrainConfig(synthetic=1, arch=arch, precision='bf16')
    TrainConfig(synthetic=1, arch=arch)
    TrainConfig(synthetic=1, arch='cvanet_lite', vflip=True, precision='bf16')


@pytest.mark.parametrize('name', ['w.json', 'w.md'])
def test_weights_the_card_would_overwrite_are_refused(tmp_path, name):
    # --weights-out w.json: the weights were saved, then the JSON card replaced them.
    with pytest.raises(ConfigError, match='--weights-out .*would overwrite'):
        TrainConfig(synthetic=1, weights_out=str(tmp_path / name))
    for fine in ('w.pt', 'w', 'w.v2.pt'):
        TrainConfig(synthetic=1, weights_out=str(tmp_path / fine))


def test_help_of_samples_per_epoch_says_what_dense_mode_does():
    # With the default, dense mode's random crops left ~40 % of a scene's labelled pixels
    # unused and used others up to 6 times, but --help promised 'every labelled pixel once'.
    (action,) = [a for a in build_parser()._actions if a.dest == 'samples_per_epoch']
    assert action.help is not None
    assert 'every labelled pixel once' not in action.help and 'dense mode' in action.help


@pytest.mark.parametrize('arch', ['cvanet', 'ccnn'])
def test_missing_validation_data_is_refused_before_training_data_are_prepared(
    tmp_path, capsys, arch
):
    # The validation scenes were listed only after every training scene had been matched
    # (minutes on real data) and the card recorded the requested crop side.
    args = [*TINY, '--arch', arch, '--out', str(tmp_path / 'run'), '--data-root', str(tmp_path)]
    assert main([*args, '--val-datasets', 'eth3d']) == 2
    err = capsys.readouterr().err
    assert 'eth3d' in err and 'scene synthetic/seed0' not in err


def test_the_summary_records_the_crop_side_that_was_run(tmp_path):
    from cva_confidence_ros.model import load_weights

    weights = tmp_path / 'cvanet_census_bm_d16.pt'
    args = [*TINY, '--out', str(tmp_path / 'run'), '--weights-out', str(weights)]
    args += ['--mode', 'dense', '--crop-size', '64', '--epochs', '1', '--epochs-low-lr', '0']
    assert main(args) == 0
    assert load_weights(weights)[1]['crop_size'] == 24  # the 24×40 scenes' smaller side


@pytest.mark.parametrize(
    ('extra', 'message'),
    [
        (['--synthetic', '1', '--mode', 'dense'], 'at least 2 training scenes'),
        (['--mode', 'sparse'], 'lgcnet trains ConfNet on image crops'),
    ],
)
def test_lgcnet_settings_that_cannot_train_are_refused_before_preparing(
    tmp_path, capsys, extra, message
):
    args = [*TINY, '--arch', 'lgcnet', '--out', str(tmp_path / 'run'), *extra]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert message in err and 'scene synthetic/seed0' not in err

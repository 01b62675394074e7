"""Weights files: round trip, meta checks, corrupt files, shipped-weights lookup."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch

from cva_confidence_ros.errors import ConfigError, ModelError
from cva_confidence_ros.model import (
    CVANet,
    default_weights_path,
    load_weights,
    save_weights,
    weights_file_name,
    weights_search_dirs,
)
from cva_confidence_ros.model import weights as weights_module


def _trained_like(depth: int = 16) -> CVANet:
    torch.manual_seed(3)
    net = CVANet(depth)
    with torch.no_grad():
        for module in net.modules():
            if isinstance(module, torch.nn.modules.batchnorm._BatchNorm):
                module.running_mean.uniform_(-1, 1)
    return net


def test_round_trip(tmp_path):
    net = _trained_like()
    path = save_weights(net, tmp_path / 'sub' / 'w.pt', {'matcher': 'census_bm', 'epochs': 3})
    loaded, meta = load_weights(path, matcher='census_bm', max_disparity=16)
    assert meta == {'matcher': 'census_bm', 'epochs': 3, 'max_disparity': 16, 'arch': 'cvanet'}
    assert not loaded.training
    for key, value in net.state_dict().items():
        assert torch.equal(loaded.state_dict()[key], value), key
    # Checks are optional.
    assert load_weights(path)[0].max_disparity == 16


def test_wrong_matcher_or_depth(tmp_path):
    path = save_weights(_trained_like(), tmp_path / 'w.pt', {'matcher': 'census_bm'})
    with pytest.raises(
        ModelError, match="matcher 'census_bm' and D = 16.*asked for matcher 'mccnn_fast'"
    ):
        load_weights(path, matcher='mccnn_fast')
    with pytest.raises(ModelError, match='D = 16.*asked for D = 64'):
        load_weights(path, matcher='census_bm', max_disparity=64)


@pytest.mark.filterwarnings('ignore:Detected pickle protocol')
def test_corrupt_empty_missing_and_foreign_files(tmp_path):
    empty = tmp_path / 'empty.pt'
    empty.write_bytes(b'')
    with pytest.raises(ModelError, match='empty'):
        load_weights(empty)
    corrupt = tmp_path / 'corrupt.pt'
    corrupt.write_bytes(b'\x80\x04 this is not a torch file')
    with pytest.raises(ModelError, match='cannot read') as caught:
        load_weights(corrupt)
    # One short line: torch's own dozen lines (advising weights_only=False) are not passed on.
    message = str(caught.value)
    assert '\n' not in message and len(message) < 400 and 'weights_only' not in message
    truncated = tmp_path / 'truncated.pt'
    save_weights(_trained_like(), truncated, {'matcher': 'census_bm'})
    truncated.write_bytes(truncated.read_bytes()[:5000])
    with pytest.raises(ModelError):
        load_weights(truncated)
    with pytest.raises(ModelError, match='does not exist'):
        load_weights(tmp_path / 'missing.pt')
    foreign = tmp_path / 'foreign.pt'
    torch.save({'weights': 1}, foreign)
    with pytest.raises(ModelError, match='state_dict and meta'):
        load_weights(foreign)
    other_arch = tmp_path / 'other.pt'
    torch.save({'state_dict': {}, 'meta': {'arch': 'ccnn', 'matcher': 'census_bm'}}, other_arch)
    with pytest.raises(ModelError, match="'ccnn'"):
        load_weights(other_arch)
    mismatched = tmp_path / 'mismatched.pt'
    blob = {
        'state_dict': _trained_like(16).state_dict(),
        'meta': {'arch': 'cvanet', 'matcher': 'census_bm', 'max_disparity': 20},
    }
    torch.save(blob, mismatched)
    with pytest.raises(ModelError, match='do not fit'):
        load_weights(mismatched)
    with pytest.raises(ModelError, match='is a directory'):
        load_weights(tmp_path)


def test_weights_of_a_diverged_training_are_refused(tmp_path):
    net = _trained_like()
    with torch.no_grad():
        net.classification.fc2.weight.view(-1)[0] = float('nan')
    path = save_weights(net, tmp_path / 'w.pt', {'matcher': 'census_bm'})
    with pytest.raises(ModelError, match=r'NaN or infinite values in 1 tensors .*diverged'):
        load_weights(path)


def test_save_needs_matcher(tmp_path):
    with pytest.raises(ModelError, match='matcher'):
        save_weights(_trained_like(), tmp_path / 'w.pt', {})
    with pytest.raises(ModelError, match='contradicts'):
        save_weights(_trained_like(), tmp_path / 'w.pt', {'matcher': 'x', 'max_disparity': 8})


def test_save_to_an_unwritable_path(tmp_path):
    blocker = tmp_path / 'file'
    blocker.write_text('not a folder')
    target = blocker / 'w.pt'
    written = re.escape(str(target))
    with pytest.raises(ModelError, match=rf'cannot write weights file {written} \('):
        save_weights(_trained_like(), target, {'matcher': 'census_bm'})
    folder = tmp_path / 'folder'
    folder.mkdir()
    with pytest.raises(ModelError, match=rf'{re.escape(str(folder))} is a directory'):
        save_weights(_trained_like(), folder, {'matcher': 'census_bm'})
    assert sorted(p.name for p in tmp_path.iterdir()) == ['file', 'folder']


def test_save_leaves_no_temporary_file_when_the_rename_fails(tmp_path, monkeypatch):
    def refuse(src, dst):
        raise PermissionError(13, 'Permission denied', str(dst))

    monkeypatch.setattr(weights_module.os, 'replace', refuse)
    with pytest.raises(ModelError, match=r'cannot write weights file .*PermissionError'):
        save_weights(_trained_like(), tmp_path / 'w.pt', {'matcher': 'census_bm'})
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize('meta', [None, 'census_bm', [('matcher', 'census_bm')]], ids=repr)
def test_save_needs_a_mapping_meta(tmp_path, meta):
    with pytest.raises(ModelError, match='meta must be a mapping'):
        save_weights(_trained_like(), tmp_path / 'w.pt', meta)


@pytest.mark.parametrize(
    'meta, match',
    [
        (5, 'expected meta to be a dict; got int'),
        ([1], 'expected meta to be a dict; got list'),
        ({'arch': ['cvanet'], 'matcher': 'census_bm', 'max_disparity': 16}, "'arch'.*list"),
        ({'matcher': 'census_bm', 'max_disparity': 16}, "'arch'.*NoneType"),
        ({'arch': 'cvanet', 'matcher': 'census_bm', 'max_disparity': 16.7}, 'float 16.7'),
        ({'arch': 'cvanet', 'matcher': 'census_bm', 'max_disparity': '16'}, "str '16'"),
    ],
    ids=['int', 'list', 'list-arch', 'no-arch', 'float-depth', 'str-depth'],
)
@pytest.mark.parametrize('arch', ['cvanet', None])
def test_load_refuses_a_malformed_meta(tmp_path, meta, match, arch):
    path = tmp_path / 'w.pt'
    torch.save({'state_dict': _trained_like().state_dict(), 'meta': meta}, path)
    with pytest.raises(ModelError, match=match):
        load_weights(path, arch=arch)


@pytest.mark.parametrize(
    'options, match',
    [
        ({'max_disparity': 16.7}, 'max_disparity must be an integer or None; got float'),
        ({'max_disparity': 16.0}, 'max_disparity must be an integer or None; got float'),
        ({'max_disparity': 'x'}, 'max_disparity must be an integer or None; got str'),
        ({'max_disparity': True}, 'max_disparity must be an integer or None; got bool'),
        ({'arch': ['cvanet']}, 'arch must be an architecture name or None; got list'),
    ],
    ids=repr,
)
def test_load_refuses_bad_options(tmp_path, options, match):
    path = save_weights(_trained_like(), tmp_path / 'w.pt', {'matcher': 'census_bm'})
    with pytest.raises(ConfigError, match=match):
        load_weights(path, **options)


@pytest.mark.parametrize('path', [None, 5])
def test_weights_path_must_be_path_like(tmp_path, path):
    with pytest.raises(ConfigError, match='weights path must be a str or os.PathLike'):
        load_weights(path)
    with pytest.raises(ConfigError, match='weights path must be a str or os.PathLike'):
        save_weights(_trained_like(), path, {'matcher': 'census_bm'})


def test_load_takes_a_numpy_depth(tmp_path):
    path = save_weights(_trained_like(), str(tmp_path / 'w.pt'), {'matcher': 'census_bm'})
    assert load_weights(path, max_disparity=np.int64(16))[0].max_disparity == 16


@pytest.mark.parametrize('depth', [16, 16.0, np.int64(16), np.float32(16)], ids=repr)
def test_a_saved_depth_of_any_number_type_loads_back(tmp_path, depth):
    meta = {'matcher': 'census_bm', 'max_disparity': depth, 'scale': np.float64(0.5),
            'count': np.int64(7), 'flag': np.bool_(True), 'version': (1, 2)}
    path = save_weights(_trained_like(), tmp_path / 'w.pt', meta)
    _, loaded = load_weights(path, matcher='census_bm', max_disparity=16)
    assert loaded['max_disparity'] == 16 and type(loaded['max_disparity']) is int
    # numpy scalars are stored as numbers, not as their strings.
    assert (loaded['scale'], loaded['count'], loaded['flag']) == (0.5, 7, True)
    assert type(loaded['count']) is int and type(loaded['flag']) is bool
    assert loaded['version'] == [1, 2]


def test_default_weights_path(tmp_path, monkeypatch):
    assert weights_file_name('census_bm', 64) == 'cvanet_census_bm_d64.pt'
    assert weights_search_dirs()[0].name == 'models'
    monkeypatch.setattr(
        weights_module, 'weights_search_dirs', lambda: [tmp_path / 'a', tmp_path / 'b']
    )
    with pytest.raises(ModelError, match=r'cvanet_nomatcher_d32\.pt.*looked in.*cva-train'):
        default_weights_path('nomatcher', 32)
    (tmp_path / 'b').mkdir()
    target = tmp_path / 'b' / 'cvanet_census_bm_d16.pt'
    save_weights(_trained_like(), target, {'matcher': 'census_bm'})
    assert default_weights_path('census_bm', 16) == target

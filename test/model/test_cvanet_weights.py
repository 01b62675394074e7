"""Weights files: round trip, meta checks, corrupt files, shipped-weights lookup."""

from __future__ import annotations

import pytest
import torch

from cva_confidence_ros.errors import ModelError
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

"""Review 32: weights files (checkpoints, non-regular files, device) and tiled inference."""

from __future__ import annotations

import os
from pathlib import Path
import sys

import numpy as np
import pytest
import torch

from cva_confidence_ros.errors import ConfigError, InputError, ModelError
from cva_confidence_ros.model import (
    CVANet,
    load_weights,
    predict_confidence,
    predict_confidence_at,
    save_weights,
    tile_shape,
)

DEPTH = 16

pytestmark = pytest.mark.usefixtures('one_torch_thread')


@pytest.fixture(scope='module')
def net() -> CVANet:
    torch.manual_seed(0)
    return CVANet(DEPTH).eval()


def _volume(height: int = 4, width: int = 5) -> np.ndarray:
    return np.random.default_rng(0).random((DEPTH, height, width)).astype(np.float32)


def test_a_budget_near_the_float_maximum_gives_the_whole_image(net: CVANet) -> None:
    # budget · 1e6 overflowed to inf: "OverflowError: cannot convert float infinity to integer".
    assert tile_shape(4, 5, DEPTH, sys.float_info.max) == (4, 5)
    volume = _volume()
    whole = predict_confidence(net, volume, tile_budget_mb=1e4)
    huge = predict_confidence(net, volume, tile_budget_mb=1e303)
    np.testing.assert_array_equal(huge, whole)


def test_nan_hidden_by_a_mask_is_refused(net: CVANet) -> None:
    # The checks looked at the masked array, the network at its data: 20 NaN confidences.
    volume = _volume()
    volume[0, 0, 0] = np.nan
    masked = np.ma.masked_invalid(volume)
    with pytest.raises(InputError, match='NaN or infinite'):
        predict_confidence(net, masked)
    with pytest.raises(InputError, match='NaN or infinite'):
        predict_confidence_at(net, masked, np.array([0, 3]), np.array([0, 4]))


def test_a_training_checkpoint_is_named_as_such(tmp_path: Path) -> None:
    net = CVANet(DEPTH)
    checkpoint = tmp_path / 'checkpoint.pt'
    torch.save(
        {
            'format': 1,
            'epoch': 3,
            'model': net.state_dict(),
            'optimizer': torch.optim.Adam(net.parameters()).state_dict(),
            'history': [],
            'config': {'matcher': 'census_bm'},
        },
        checkpoint,
    )
    with pytest.raises(ModelError, match=r'is a cva-train checkpoint.*--weights-out'):
        load_weights(checkpoint)


@pytest.mark.skipif(not hasattr(os, 'mkfifo'), reason='needs named pipes')
def test_a_path_that_is_no_regular_file_is_not_called_missing(tmp_path: Path) -> None:
    pipe = tmp_path / 'weights.pt'
    os.mkfifo(pipe)
    with pytest.raises(ModelError, match='is not a regular file'):
        load_weights(pipe)


def test_cuda_where_there_is_none_is_refused_before_the_file_is_read(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A damaged file asked for on CUDA reported the file (the device only after a good read).
    monkeypatch.setattr(torch.cuda, 'is_available', lambda: False)
    damaged = tmp_path / 'damaged.pt'
    save_weights(CVANet(DEPTH), damaged, {'matcher': 'census_bm'})
    damaged.write_bytes(damaged.read_bytes()[:1000])
    with pytest.raises(ConfigError, match="device 'cuda' asked for, but CUDA is not available"):
        load_weights(damaged, device='cuda')


def test_sparse_extract_batch_of_a_budget_near_the_float_maximum() -> None:
    # int(inf) before the cap: OverflowError.
    from cva_confidence_ros.model import CVANet
    from cva_confidence_ros.model.sparse import SparseEvaluator

    evaluator = SparseEvaluator(CVANet(max_disparity=16).eval(), tile_budget_mb=1e303)
    assert evaluator.extract_batch == 512


def test_a_tile_budget_beyond_float_is_a_config_error() -> None:
    # math.isfinite(2**2000) raised a bare OverflowError.
    from cva_confidence_ros.errors import ConfigError
    from cva_confidence_ros.model.inference import _check_tile_budget

    with pytest.raises(ConfigError, match='tile_budget_mb must be a finite number > 0'):
        _check_tile_budget(2**2000)
    assert _check_tile_budget(np.int64(64)) == 64.0

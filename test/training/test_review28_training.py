"""Review regressions: training samples and the training loop."""

from __future__ import annotations

from collections.abc import Iterator
import contextlib
import json
import signal

import numpy as np
import pytest
import torch
from train_test_utils import TINY

from cva_confidence_ros.datasets import StereoSample
from cva_confidence_ros.errors import DataError
from cva_confidence_ros.training.cli import main
from cva_confidence_ros.training.data import (
    PreparedScene,
    dense_crops,
    prepare_scene,
    sample_index,
)


@contextlib.contextmanager
def _deadline(seconds: float) -> Iterator[None]:
    """Turn a hang into a failure."""

    def expire(*_: object) -> None:
        raise TimeoutError(f'still running after {seconds} s')

    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def test_dense_crops_without_labelled_pixels_raise_instead_of_hanging():
    # With no labelled pixel the loop drew no crop and never reached n_samples: it hung.
    with _deadline(5), pytest.raises(DataError, match='no labelled training samples'):
        dense_crops([], sample_index([]), n_samples=5, crop_size=8, seed=0, epoch=0)


def test_dense_crops_of_no_samples_are_empty():
    # zip(*[]) gave no columns: CropBatch() raised a TypeError.
    volume = torch.zeros((16, 20, 22), dtype=torch.float16)
    labelled = np.ones((8, 10), dtype=bool)
    scenes = [PreparedScene('toy/0', 1, volume, labelled, labelled.copy())]
    crops = dense_crops(scenes, sample_index(scenes), n_samples=0, crop_size=8, seed=0, epoch=0)
    for column in (crops.scene, crops.y0, crops.x0, crops.n_labelled):
        assert column.shape == (0,) and column.dtype == np.int32


def test_a_scene_shrunk_below_d_is_named():
    # An outlier in the ground truth shrinks the pair until it is narrower than D; the error
    # was the matcher's 'max_disparity must be smaller than the image width 12; got 16',
    # naming neither the scene nor the shrinking.
    rng = np.random.default_rng(0)
    left = rng.integers(0, 256, (40, 200), dtype=np.uint8)
    truth = np.full((40, 200), 5.0, np.float32)
    truth[3, 100] = 200.0
    sample = StereoSample('kitti2012', '000007', left, left, truth)
    with pytest.raises(DataError, match=r'kitti2012/000007: .*200 px.*by 16 to 12×2.*D = 16'):
        prepare_scene(sample, 'census_bm', 16)
    small = StereoSample('toy', 'narrow', left[:, :16], left[:, :16], truth[:, :16] * 0)
    with pytest.raises(DataError, match=r'toy/narrow: it is 16×40; .*wider than D = 16'):
        prepare_scene(small, 'census_bm', 16)


def test_a_last_step_of_one_extract_joins_the_one_before():
    from cva_confidence_ros.training.trainer import _steps

    assert [s.size for s in _steps(33, 16, single_extract=True)] == [16, 17]
    assert np.array_equal(np.concatenate(_steps(33, 16, single_extract=True)), np.arange(33))
    # Dense crops larger than one output keep their steps.
    assert [s.size for s in _steps(33, 16, single_extract=False)] == [16, 16, 1]
    assert [s.size for s in _steps(32, 16, single_extract=True)] == [16, 16]
    assert [s.size for s in _steps(1, 16, single_extract=True)] == [1]


def test_cvanet_fast_trains_an_epoch_that_ends_in_one_sample(tmp_path):
    # 33 samples in batches of 16: the last step of one extract raised batch norm's
    # 'Expected more than 1 value per channel when training' after the whole epoch.
    out = tmp_path / 'run'
    args = [*TINY, '--arch', 'cvanet_fast', '--epochs', '1', '--epochs-low-lr', '0']
    assert main([*args, '--samples-per-epoch', '33', '--out', str(out)]) == 0
    (record,) = json.loads((out / 'history.json').read_text())
    assert record['samples'] == 33


@pytest.mark.parametrize(
    ('extra', 'named'),
    [
        (['--batch-size', '1'], '--batch-size 1 makes'),
        (['--samples-per-epoch', '1'], '--samples-per-epoch 1 makes'),
        (['--mode', 'dense', '--crop-size', '1', '--batch-size', '1'], '--crop-size 1 make'),
    ],
)
def test_steps_of_one_extract_are_refused_before_preparing(tmp_path, capsys, extra, named):
    # They raised a ValueError traceback once the data were prepared.
    args = [*TINY, '--arch', 'cvanet_fast', '--out', str(tmp_path / 'run'), *extra]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert named in err and 'cvanet_fast cannot train on' in err
    assert 'scene synthetic/seed0' not in err

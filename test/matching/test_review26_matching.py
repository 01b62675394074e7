"""Regressions of review 26: speckle filter on Fortran-ordered maps, MC-CNN weights and dtype,
unknown options of the CVA-Net methods."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from cva_confidence_ros.confidence import CONFIDENCE_METHODS
from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.matching import compute_cost_volume, mccnn_fast, mccnn_net, remove_speckles


def _random_weights(path: Path, seed: int) -> Path:
    """A state dict of a randomly initialised MC-CNN fast network (no mccnn package needed)."""
    torch.manual_seed(seed)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(mccnn_net.McCnnFastFeatures().state_dict(), path)
    return path


def _pair(seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return (
        rng.integers(0, 256, (8, 16), dtype=np.uint8),
        rng.integers(0, 256, (8, 16), dtype=np.uint8),
    )


@pytest.mark.parametrize('layout', ['fortran', 'transposed', 'fortran_float64'])
def test_speckles_go_from_a_fortran_ordered_disparity(layout: str) -> None:
    rng = np.random.default_rng(0)
    disparity = rng.integers(0, 6, (23, 31)).astype(np.float32)
    disparity[3, :] = np.nan
    expected = remove_speckles(disparity, max_size=3)
    assert not expected.all()  # there are speckles to drop
    if layout == 'fortran':
        other = np.asfortranarray(disparity)
    elif layout == 'transposed':
        other = disparity.T.copy().T
    else:
        other = np.asfortranarray(disparity.astype(np.float64))
    np.testing.assert_array_equal(remove_speckles(other, max_size=3), expected)
    keep = np.asfortranarray(np.isfinite(disparity))
    np.testing.assert_array_equal(remove_speckles(other, keep, max_size=3), expected)


def _direct_volume(weights: str | Path, left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """The left volume from the network and the correlation, without the feature cache."""
    network = mccnn_net.load_network(weights)
    features = mccnn_net.extract_features(network, [left, right], torch.device('cpu'))
    return mccnn_fast.cosine_cost_volume(features[0], features[1], 4, -1)


def test_mccnn_runs_under_a_float64_torch_default(tmp_path: Path) -> None:
    weights = str(_random_weights(tmp_path / 'w.pt', seed=1))
    left, right = _pair(3)
    expected = _direct_volume(weights, left, right)
    mccnn_net._cached_network.cache_clear()  # loaded again under the float64 default
    previous = torch.get_default_dtype()
    try:
        torch.set_default_dtype(torch.float64)
        with mccnn_fast.preserved_features():
            volume = compute_cost_volume(left, right, 'mccnn_fast', 4, weights=weights)
    finally:
        torch.set_default_dtype(previous)
        mccnn_net._cached_network.cache_clear()
    assert volume.dtype == np.float32
    np.testing.assert_allclose(volume, expected, atol=1e-6)


def test_mccnn_relative_weights_follow_the_working_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path_a = _random_weights(tmp_path / 'a' / 'w.pt', seed=1)
    path_b = _random_weights(tmp_path / 'b' / 'w.pt', seed=2)
    left, right = _pair(4)
    with mccnn_fast.preserved_features():
        monkeypatch.chdir(path_a.parent)
        compute_cost_volume(left, right, 'mccnn_fast', 4, weights='w.pt')
        monkeypatch.chdir(path_b.parent)
        volume = compute_cost_volume(left, right, 'mccnn_fast', 4, weights='w.pt')
    np.testing.assert_allclose(volume, _direct_volume(path_b, left, right), atol=1e-6)


@pytest.mark.parametrize('name', ['cva_net', 'cva_net_fast', 'cva_net_lite'])
def test_cva_net_methods_refuse_an_unknown_option(name: str) -> None:
    with pytest.raises(ConfigError, match=r"unknown options \['cva_strid'\]"):
        CONFIDENCE_METHODS.get(name)(matcher='census_bm', max_disparity=64, cva_strid=4)

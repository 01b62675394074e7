"""Regressions of review 30: numpy-integer matcher parameters, census codes out of range, MC-CNN
device names."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.matching import (
    CensusBMConfig,
    CensusSGMConfig,
    MCCNNFastConfig,
    compute_cost_volume,
    mccnn_net,
)
from cva_confidence_ros.matching.census import (
    census_transform,
    hamming_cost_volume,
    hamming_distance,
)
from cva_confidence_ros.matching.sgm import census_sgm_volume


def _pair() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(30)
    left = rng.integers(0, 256, (7, 14), dtype=np.uint8)
    return left, np.roll(left, -2, axis=1)


@pytest.mark.parametrize('kind', [np.uint8, np.uint16])
def test_census_bm_takes_a_numpy_integer_window(kind: type) -> None:
    # np.uint8(5) reached the numba kernel as an unsigned radius, whose arithmetic with signed
    # indices numba typed as float: a TypingError instead of a volume.
    left, right = _pair()
    expected = compute_cost_volume(left, right, 'census_bm', 4, window=5)
    volume = compute_cost_volume(left, right, 'census_bm', 4, window=kind(5))
    np.testing.assert_array_equal(volume, expected)
    assert type(CensusBMConfig(window=kind(5)).window) is int


@pytest.mark.parametrize('kind', [np.uint8, np.int8])
def test_census_sgm_takes_numpy_integer_penalties(kind: type) -> None:
    # 8·(24 + p2) was computed in p2's dtype: np.uint8(100) wrapped to 8·124 mod 256 = 224
    # (volume scaled wrongly), np.uint8(232) to 0 (volume NaN/inf), np.int8 went negative.
    left, right = _pair()
    p2 = 100
    expected = compute_cost_volume(left, right, 'census_sgm', 4, p1=3, p2=p2)
    volume = compute_cost_volume(left, right, 'census_sgm', 4, p1=kind(3), p2=kind(p2))
    np.testing.assert_array_equal(volume, expected)
    assert volume.max() <= 1.0
    config = CensusSGMConfig(p1=kind(3), p2=kind(p2))
    assert type(config.p1) is int and type(config.p2) is int


def test_census_sgm_volume_scales_with_a_numpy_uint8_p2() -> None:
    rng = np.random.default_rng(31)
    codes_a = census_transform(rng.integers(0, 256, (5, 9), dtype=np.uint8))
    codes_b = census_transform(rng.integers(0, 256, (5, 9), dtype=np.uint8))
    expected = census_sgm_volume(codes_a, codes_b, 3, -1, 2, 232)
    with np.errstate(all='raise'):  # 8·(24 + 232) overflowed uint8 to 0, then 1 / 0
        volume = census_sgm_volume(codes_a, codes_b, 3, -1, np.uint8(2), np.uint8(232))
    np.testing.assert_array_equal(volume, expected)


@pytest.mark.parametrize(
    ('codes', 'message'),
    [
        # 32 set bits gave Hamming costs of 32, above the 24 of a partner outside the image
        (np.full((2, 4), 0xFFFFFFFF, np.uint32), r'census codes in \[0, 2\*\*24\)'),
        (np.full((2, 4), -1, np.int64), r'census codes in \[0, 2\*\*24\)'),
        # a float array was truncated to uint32 without a word
        (np.full((2, 4), 3.9), 'integer census codes'),
    ],
)
def test_hamming_costs_refuse_what_is_not_a_census_code(codes: np.ndarray, message: str) -> None:
    zeros = np.zeros((2, 4), np.uint32)
    with pytest.raises(InputError, match=message):
        hamming_cost_volume(codes, zeros, 2, -1)
    with pytest.raises(InputError, match=message):
        hamming_cost_volume(zeros, codes, 2, 1)
    with pytest.raises(InputError, match=message):
        hamming_distance(codes, zeros)
    with pytest.raises(InputError, match=message):
        census_sgm_volume(codes, zeros, 2, -1, 1, 8)


def test_hamming_distance_refuses_arrays_of_other_shapes() -> None:
    # (3,) against (1,) was broadcast although the docstring asks for the same shape
    with pytest.raises(InputError, match=r'same shape; got \(3,\) and \(1,\)'):
        hamming_distance(np.array([1, 2, 3]), np.array([0]))


@pytest.mark.parametrize('device', ['cuda:x', 'cuda:', 'cuda:-1', 'cuda:01', 'cuda: 1'])
def test_mccnn_config_refuses_a_malformed_cuda_index(device: str) -> None:
    # accepted by the config; on a CUDA machine torch.device() then raised a RuntimeError
    with pytest.raises(ConfigError, match='cuda:N'):
        MCCNNFastConfig(device=device)


@pytest.mark.parametrize('device', ['cuda:0', 'cuda:12', 'cuda', 'auto', 'cpu'])
def test_mccnn_config_keeps_the_good_device_names(device: str) -> None:
    assert MCCNNFastConfig(device=device).device == device


def test_mccnn_device_index_beyond_the_gpus_is_a_config_error(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # A one-GPU machine: 'cuda:3' was passed on to torch, and moving the network there fails
    # with a CUDA error (invalid device ordinal) instead of a ConfigError.
    monkeypatch.setattr(torch.cuda, 'is_available', lambda: True)
    monkeypatch.setattr(torch.cuda, 'device_count', lambda: 1)
    with pytest.raises(ConfigError, match=r"'cuda:3'.* 1 CUDA device"):
        mccnn_net.resolve_device('cuda:3')
    with pytest.raises(ConfigError, match='cuda:N'):
        mccnn_net.resolve_device('cuda:x')
    assert mccnn_net.resolve_device('cuda:0') == torch.device('cuda:0')
    assert mccnn_net.resolve_device('cuda') == torch.device('cuda')


def test_one_reading_of_the_device_for_the_network_and_mccnn(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # The network's resolve_device passed 'cuda:3' on a one-GPU machine on to torch (MC-CNN's
    # own copy checked it): one function serves both now.
    from cva_confidence_ros.model import inference

    assert inference.resolve_device is mccnn_net.resolve_device
    monkeypatch.setattr(torch.cuda, 'is_available', lambda: True)
    monkeypatch.setattr(torch.cuda, 'device_count', lambda: 1)
    with pytest.raises(ConfigError, match=r"'cuda:3'.* 1 CUDA device"):
        inference.resolve_device('cuda:3')
    with pytest.raises(ConfigError, match=r"'cuda:3'.* 1 CUDA device"):
        inference.resolve_device(torch.device('cuda', 3))
    for bad in ('gpu', 'cuda:x', 'cuda:-1', 'meta', 3):
        with pytest.raises(ConfigError, match='cuda:N'):
            inference.resolve_device(bad)  # type: ignore[arg-type]

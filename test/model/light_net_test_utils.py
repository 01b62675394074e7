"""Shared pieces of the CVA-Net-Lite and CVA-Net-Fast network tests: a peaked cost volume, BN
statistics taken from data, a few Adam steps on the logits, and the checks of registration,
weights files and the confidence method that both light networks must pass."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from cva_confidence_ros.confidence import CONFIDENCE_METHODS, ConfidenceInputs
from cva_confidence_ros.errors import InputError, ModelError
from cva_confidence_ros.model import (
    ARCHITECTURES,
    CVANet,
    load_weights,
    predict_confidence,
    save_weights,
    weights_file_name,
)


def peaked_volume(seed: int, depth: int, height: int, width: int) -> np.ndarray:
    """A cost volume with a minimum at a per-pixel disparity, plus noise, in [0, 1]."""
    rng = np.random.default_rng(seed)
    truth = rng.integers(0, depth, size=(height, width))
    d = np.arange(depth)[:, None, None]
    volume = np.abs(d - truth[None]) / 4.0 + rng.normal(0, 0.1, (depth, height, width))
    return np.clip(volume, 0.0, 1.0).astype(np.float32)


def with_data_bn(model: nn.Module, volumes: Iterable[np.ndarray]) -> nn.Module:
    """``model`` in eval mode with BN statistics averaged over ``volumes`` (D, H', W'), so
    that folding the batch normalisations is not trivial."""
    for module in model.modules():
        if isinstance(module, nn.modules.batchnorm._BatchNorm):
            module.momentum = None
    model.train()
    with torch.no_grad():
        for volume in volumes:
            model(torch.from_numpy(volume)[None, None])
    return model.eval()


def adam_losses(model: nn.Module, volume: torch.Tensor, target: torch.Tensor) -> list[float]:
    """Five Adam steps (lr 1e-2) on BCE of ``model.forward_logits``; every parameter must get
    a gradient. Returns the losses before each step."""
    optimiser = torch.optim.Adam(model.parameters(), lr=1e-2)
    losses = []
    for _ in range(5):
        loss = torch.nn.functional.binary_cross_entropy_with_logits(
            model.forward_logits(volume), target
        )
        optimiser.zero_grad()
        loss.backward()
        assert all(p.grad is not None for p in model.parameters())
        optimiser.step()
        losses.append(float(loss.detach()))
    return losses


def gradient_step_losses(
    model: nn.Module, volume: Callable[[int], np.ndarray], height: int, width: int
) -> list[float]:
    """:func:`adam_losses` on two padded volumes ``volume(0)``, ``volume(1)`` and random labels."""
    batch = np.stack([np.pad(volume(s), ((0, 0), (6, 6), (6, 6))) for s in range(2)])
    target = (torch.rand(2, height, width) > 0.5).float()
    return adam_losses(model, torch.from_numpy(batch)[:, None], target)


def check_registered_saved_and_loaded(
    net: nn.Module, arch: str, depth: int, tmp_path: Path, volume: np.ndarray
) -> None:
    """``net``'s architecture ``arch`` is registered, names its files, and survives a save and
    load; loading it as CVA-Net says which architecture the file holds."""
    assert arch in ARCHITECTURES and type(net).arch == arch
    assert weights_file_name('census_bm', 64, arch) == f'{arch}_census_bm_d64.pt'
    path = save_weights(net, tmp_path / f'{arch}.pt', {'matcher': 'census_bm'})
    loaded, meta = load_weights(path, matcher='census_bm', max_disparity=depth, arch=arch)
    assert isinstance(loaded, type(net)) and meta['arch'] == arch
    np.testing.assert_allclose(
        predict_confidence(loaded, volume), predict_confidence(net, volume), atol=1e-6
    )
    with pytest.raises(ModelError, match=f"arch '{arch}'; expected 'cvanet'"):
        load_weights(path)


def method_inputs(volume: np.ndarray, matcher: str = 'census_bm') -> ConfidenceInputs:
    """Confidence-method inputs for ``volume``: its WTA disparity and a black image."""
    return ConfidenceInputs(
        cost_volume=volume,
        disparity=volume.argmin(axis=0).astype(np.float32),
        image=np.zeros(volume.shape[1:], np.uint8),
        matcher=matcher,
    )


def check_confidence_method(
    net: nn.Module,
    arch: str,
    method_name: str,
    depth: int,
    tmp_path: Path,
    volume: Callable[[int], np.ndarray],
) -> Callable[..., object]:
    """The registered method ``method_name`` with ``net``'s weights equals the network on whole
    images and at pixels, and refuses another depth, another matcher and CVA-Net weights.

    Args:
        volume: ``volume(depth)`` gives a (depth, H, W) cost volume.

    Returns:
        The method's factory, for further checks.
    """
    path = save_weights(net, tmp_path / f'{arch}_census_bm_d{depth}.pt', {'matcher': 'census_bm'})
    factory = CONFIDENCE_METHODS.get(method_name)
    method = factory(
        matcher='census_bm', max_disparity=depth, weights=str(path), device='cpu',
        tile_budget_mb=1.0,
    )  # fmt: skip
    inputs = method_inputs(volume(depth))
    expected = predict_confidence(net, inputs.cost_volume)
    np.testing.assert_allclose(method(inputs), expected, atol=1e-5)
    ys, xs = np.array([1, 2]), np.array([3, 20])
    np.testing.assert_allclose(method.confidence_at(inputs, ys, xs), expected[ys, xs], atol=1e-5)
    with pytest.raises(InputError, match=f'{arch} weights .* depth D = {depth}'):
        method(method_inputs(volume(depth + 8)))
    with pytest.raises(InputError, match="for matcher 'census_bm'"):
        method(method_inputs(volume(depth), matcher='census_sgm'))
    cva_net_path = tmp_path / 'cvanet.pt'
    save_weights(CVANet(depth), cva_net_path, {'matcher': 'census_bm'})
    with pytest.raises(ModelError, match=f"expected '{arch}'"):
        factory(matcher='census_bm', max_disparity=depth, weights=str(cva_net_path))
    return factory


def trained_like(cls: type, depth: int, seed: int = 0) -> nn.Module:
    """A ``cls(depth)`` network in eval mode with random weights and batch-norm statistics
    (folding must carry them)."""
    torch.manual_seed(seed)
    net = cls(depth)
    for module in net.modules():
        if isinstance(module, nn.modules.batchnorm._BatchNorm):
            module.running_mean.uniform_(-0.2, 0.2)
            module.running_var.uniform_(0.5, 1.5)
    return net.eval()

"""Shared pieces of the CVA-Net-Lite and CVA-Net-Fast network tests: a peaked cost volume, BN
statistics taken from data, and a few Adam steps on the logits."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import torch
from torch import nn


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

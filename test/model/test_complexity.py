"""Multiply-add counts: analytic formulas against a hook-based count, and the Lite ratio."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.model import CVANet, CVANetFast, CVANetLite, dense_macs, macs_per_pixel
from cva_confidence_ros.model.complexity import layer_table


def _hooked_macs(net: nn.Module, volume: torch.Tensor) -> tuple[int, list[int]]:
    """Multiply-adds of every convolution in one forward pass, counted from its output:
    output elements × input channels × kernel volume (stride and padding included)."""
    per_layer: list[int] = []

    def hook(module: nn.Module, _inputs: tuple, output: torch.Tensor) -> None:
        kernel = 1
        for size in module.kernel_size:
            kernel *= size
        per_layer.append(output.numel() * module.in_channels // module.groups * kernel)

    handles = [
        m.register_forward_hook(hook)
        for m in net.modules()
        if isinstance(m, nn.modules.conv._ConvNd)
    ]
    try:
        with torch.no_grad():
            net.eval()(volume)
    finally:
        for handle in handles:
            handle.remove()
    return sum(per_layer), per_layer


@pytest.mark.parametrize('arch', [CVANet, CVANetLite, CVANetFast])
@pytest.mark.parametrize(('depth', 'height', 'width'), [(16, 1, 1), (24, 5, 3), (33, 4, 7)])
def test_analytic_count_equals_hooked_count(arch, depth, height, width):
    net = arch(depth)
    volume = torch.rand(1, 1, depth, height + 12, width + 12)
    total, per_layer = _hooked_macs(net, volume)
    assert dense_macs(net, None, height, width) == total
    # Layer by layer too, so that two compensating errors cannot pass.
    table = layer_table(net)
    assert len(table) == len(per_layer)
    for layer, counted in zip(table, per_layer, strict=True):
        positions = (height + 12 - layer.shrink) * (width + 12 - layer.shrink)
        assert layer.inputs * layer.channels * layer.depth * positions == counted


@pytest.mark.parametrize('arch', ['cvanet', 'cvanet_lite', 'cvanet_fast'])
def test_per_pixel_count_is_the_large_image_limit(arch):
    per_pixel = macs_per_pixel(arch, 64)
    side = 20_000
    assert dense_macs(arch, 64, side, side) / side**2 == pytest.approx(per_pixel, rel=2e-3)
    assert dense_macs(arch, 64, 1, 1) > per_pixel  # the unpadded fusion's border overhead


def test_cvanet_matches_the_issue_figures():
    """About 160 M multiply-adds per pixel at D = 256: fusion ≈ 34 M, depth ≈ 126 M."""
    table = layer_table('cvanet', 256)
    fusion = sum(layer.inputs * layer.channels * layer.depth for layer in table[:6])
    depth = sum(layer.inputs * layer.channels * layer.depth for layer in table[6:16])
    assert fusion == pytest.approx(34.5e6, rel=0.01)
    assert depth == pytest.approx(125.9e6, rel=0.01)
    assert macs_per_pixel('cvanet', 256) == pytest.approx(160.5e6, rel=0.01)
    # Hand-computed at D = 64: fusion 27·32·62 + 27·32²·(60+58+56+54+52), depth
    # 32²·52·(8+16+32+7·64), classification 52·32·16 + 16.
    assert macs_per_pixel('cvanet', 64) == 53_568 + 7_741_440 + 26_836_992 + 26_624 + 16


@pytest.mark.parametrize('depth', [64, 128])
def test_lite_is_at_least_20_times_cheaper(depth):
    ratio = macs_per_pixel('cvanet', depth) / macs_per_pixel('cvanet_lite', depth)
    assert ratio >= 20
    assert macs_per_pixel(CVANetLite(depth)) == macs_per_pixel('cvanet_lite', depth)


def test_bad_arguments():
    with pytest.raises(ConfigError, match='max_disparity is needed'):
        macs_per_pixel('cvanet')
    with pytest.raises(ConfigError, match='no MAC count'):
        macs_per_pixel('ccnn', 64)
    with pytest.raises(ConfigError, match='built for D = 16'):
        macs_per_pixel(CVANet(16), 64)
    with pytest.raises(ConfigError, match='expected a CVA-Net'):
        macs_per_pixel(nn.Linear(2, 2))


@pytest.mark.parametrize('depth', [16, 64, 128, 256])
def test_fast_costs_the_same_at_every_depth_and_is_far_cheaper(depth):
    # Hand-computed: 10·64 + 64·32 (curve encoder) + 6·9·32² (plane fusion) + 32·16 + 16.
    assert macs_per_pixel('cvanet_fast', depth) == 640 + 2_048 + 55_296 + 512 + 16
    assert macs_per_pixel(CVANetFast(depth)) == macs_per_pixel('cvanet_fast', depth)
    if depth >= 64:
        assert macs_per_pixel('cvanet', depth) / macs_per_pixel('cvanet_fast', depth) >= 500
        assert macs_per_pixel('cvanet_lite', depth) / macs_per_pixel('cvanet_fast', depth) >= 10

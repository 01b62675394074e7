"""Multiply-adds of the cost-volume networks, counted analytically from their layers.

A layer is described by (inputs per output, output channels, output depth, shrink): it does
``inputs × channels × depth`` multiply-adds per output position, and a fusion layer that has
removed ``shrink`` pixels from each side of the padded (H + 12) × (W + 12) input works on
(H + 12 − shrink) × (W + 12 − shrink) positions. Layers that run per output pixel (the depth
processing and classification) have ``shrink = 12``. Biases, batch normalisations (folded at
inference) and ReLUs are not counted.

* :func:`dense_macs` — the exact count of one dense forward pass over an H × W output tile;
* :func:`macs_per_pixel` — its limit per output pixel for a large image (the border overhead
  of the unpadded fusion vanishes), the figure to compare networks by.

Checked against a hook-based count of the (unfolded) networks in
``test/model/test_complexity.py``.
"""

from __future__ import annotations

from typing import NamedTuple

from torch import nn

from cva_confidence_ros.checks import is_int
from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.model.fast import (
    FAST_CURVE_FEATURES,
    FAST_FC_NODES,
    FAST_FILTERS,
    FAST_INPUTS,
    FAST_MIN_DISPARITY,
    CVANetFast,
    FoldedCVANetFast,
)
from cva_confidence_ros.model.inference import FoldedCVANet, _unwrap
from cva_confidence_ros.model.lite import (
    LITE_DEPTH_KERNELS,
    LITE_FC_NODES,
    LITE_FILTERS,
    LITE_FIRST_KERNEL,
    LITE_MIN_DISPARITY,
    CVANetLite,
    FoldedCVANetLite,
    condensed_depth,
)
from cva_confidence_ros.model.network import (
    DEPTH_KERNELS,
    FC_NODES,
    FILTERS,
    FUSION_LAYERS,
    MIN_DISPARITY,
    CVANet,
    check_network_options,
)

__all__ = ['Layer', 'dense_macs', 'layer_table', 'macs_per_pixel']

_BORDER = 2 * FUSION_LAYERS


class Layer(NamedTuple):
    """One convolution: multiply-adds = inputs × channels × depth per output position."""

    inputs: int
    channels: int
    depth: int
    shrink: int


def _cvanet_layers(max_disparity: int) -> list[Layer]:
    layers = [
        Layer(
            27 * (1 if index == 0 else FILTERS),
            FILTERS,
            max_disparity - 2 * (index + 1),
            2 * (index + 1),
        )
        for index in range(FUSION_LAYERS)
    ]
    curve = max_disparity - _BORDER
    layers += [Layer(k * FILTERS, FILTERS, curve, _BORDER) for k in DEPTH_KERNELS]
    layers += [Layer(curve * FILTERS, FC_NODES, 1, _BORDER), Layer(FC_NODES, 1, 1, _BORDER)]
    return layers


def _lite_layers(max_disparity: int) -> list[Layer]:
    curve = condensed_depth(max_disparity)
    layers = [Layer(9 * LITE_FIRST_KERNEL, LITE_FILTERS, curve, 2)]
    layers += [
        Layer(27 * LITE_FILTERS, LITE_FILTERS, curve, 2 * (index + 1))
        for index in range(1, FUSION_LAYERS)
    ]
    layers += [Layer(k * LITE_FILTERS, LITE_FILTERS, curve, _BORDER) for k in LITE_DEPTH_KERNELS]
    layers += [
        Layer(curve * LITE_FILTERS, LITE_FC_NODES, 1, _BORDER),
        Layer(LITE_FC_NODES, 1, 1, _BORDER),
    ]
    return layers


def _fast_layers(max_disparity: int) -> list[Layer]:
    # The curve encoder runs on every pixel of the padded tile (shrink 0), the plane fusion
    # shrinks it by 2 px a layer; the WTA scan before it does comparisons, not multiply-adds.
    del max_disparity  # the cost does not depend on D
    layers = [
        Layer(FAST_INPUTS, FAST_CURVE_FEATURES, 1, 0),
        Layer(FAST_CURVE_FEATURES, FAST_FILTERS, 1, 0),
    ]
    layers += [
        Layer(9 * FAST_FILTERS, FAST_FILTERS, 1, 2 * (index + 1))
        for index in range(FUSION_LAYERS)
    ]
    layers += [Layer(FAST_FILTERS, FAST_FC_NODES, 1, _BORDER), Layer(FAST_FC_NODES, 1, 1, _BORDER)]
    return layers


_TABLES = {'cvanet': _cvanet_layers, 'cvanet_lite': _lite_layers, 'cvanet_fast': _fast_layers}
# Smallest D each architecture is built for (as its constructor checks).
_MIN_DISPARITY = {
    'cvanet': MIN_DISPARITY,
    'cvanet_lite': LITE_MIN_DISPARITY,
    'cvanet_fast': FAST_MIN_DISPARITY,
}


def _resolve(net_or_arch: nn.Module | str, max_disparity: int | None) -> tuple[str, int]:
    if isinstance(net_or_arch, nn.Module):  # a (Distributed)DataParallel wrapper: its network
        net_or_arch = _unwrap(net_or_arch)
    if isinstance(net_or_arch, str):
        arch = net_or_arch
        if max_disparity is None:
            raise ConfigError(f'max_disparity is needed to count the MACs of arch {arch!r}')
    elif isinstance(net_or_arch, (CVANet, FoldedCVANet)):
        arch = 'cvanet'
    elif isinstance(net_or_arch, (CVANetLite, FoldedCVANetLite)):
        arch = 'cvanet_lite'
    elif isinstance(net_or_arch, (CVANetFast, FoldedCVANetFast)):
        arch = 'cvanet_fast'
    else:
        raise ConfigError(
            f'expected a CVA-Net, CVA-Net-Lite or CVA-Net-Fast network or arch name; '
            f'got {type(net_or_arch).__name__}'
        )
    if arch not in _TABLES:
        raise ConfigError(f'no MAC count for arch {arch!r}; expected one of {sorted(_TABLES)}')
    if max_disparity is None:
        assert not isinstance(net_or_arch, str)  # an arch name without a D raised above
        max_disparity = int(net_or_arch.max_disparity)
    elif not isinstance(net_or_arch, str) and max_disparity != net_or_arch.max_disparity:
        raise ConfigError(
            f'the network is built for D = {net_or_arch.max_disparity}; got D = {max_disparity}'
        )
    minimum = _MIN_DISPARITY[arch]
    depth = check_network_options(max_disparity, minimum, f'the smallest D of {arch!r}', 0.0)
    return arch, depth


def layer_table(net_or_arch: nn.Module | str, max_disparity: int | None = None) -> list[Layer]:
    """The :class:`Layer` list of a network (a module or an arch name) for depth D."""
    arch, depth = _resolve(net_or_arch, max_disparity)
    return _TABLES[arch](depth)


def macs_per_pixel(net_or_arch: nn.Module | str, max_disparity: int | None = None) -> int:
    """Multiply-adds per output pixel of dense inference on a large image.

    Args:
        net_or_arch: :class:`CVANet`, :class:`CVANetLite`, :class:`CVANetFast` (or their
            folded forms, or one in a ``DataParallel`` wrapper), or ``'cvanet'`` /
            ``'cvanet_lite'`` / ``'cvanet_fast'``.
        max_disparity: D; defaults to the network's own (required with an arch name).

    Returns:
        Σ over layers of inputs × channels × depth (at D = 64: CVA-Net 34,658,640,
        CVA-Net-Lite 647,056, CVA-Net-Fast 58,512 at any D).
    """
    return sum(
        layer.inputs * layer.channels * layer.depth
        for layer in layer_table(net_or_arch, max_disparity)
    )


def dense_macs(
    net_or_arch: nn.Module | str, max_disparity: int | None, height: int, width: int
) -> int:
    """Exact multiply-adds of one forward pass over an H × W output tile.

    The input is the tile padded to (H + 12) × (W + 12), so the unpadded fusion layers work on
    more positions than H × W; ``dense_macs / (H·W)`` tends to :func:`macs_per_pixel`.
    """
    if not (is_int(height) and is_int(width)) or height < 1 or width < 1:
        raise ConfigError(f'height and width must be integers >= 1; got {height!r}×{width!r}')
    total = 0
    for layer in layer_table(net_or_arch, max_disparity):
        positions = (height + _BORDER - layer.shrink) * (width + _BORDER - layer.shrink)
        total += layer.inputs * layer.channels * layer.depth * positions
    return total

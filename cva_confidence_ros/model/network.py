"""CVA-Net: confidence from a normalised cost-volume extract (paper section 3.2, Table 2).

The network has three stages, one module each:

* :class:`NeighbourhoodFusion` — input batch normalisation and six 3×3×3 3D convolutions
  without padding that fuse a 13×13×D extract into one cost curve of depth D − 12;
* :class:`DepthProcessing` — ten 1×1×k convolutions along the disparity axis
  (k = 8, 16, 32, then 64 seven times) with zero padding that keeps the depth;
* :class:`Classification` — the two fully-connected layers (16 nodes, then 1) as convolutions,
  the first one with a kernel that spans the whole remaining depth D − 12.

Every convolution is followed by batch normalisation and ReLU, except in the classification.

A 1×1×k 3D convolution sees one pixel at a time, so it equals a convolution along the disparity
axis applied to every pixel. The depth and classification stages are therefore written as
``Conv2d`` with a (k, 1) kernel over the fused curves laid out as (1, 32, D − 12, B·H·W):
the same weights and parameter count as the 3D form, and on CPU two to three times faster than
``Conv3d`` with a (k, 1, 1) kernel (forward) or ``Conv1d`` (backward).

Padding of the even depth kernels: ``k/2 − 1`` zeros before and ``k/2`` after on the disparity
axis, which is what both Keras ``padding='same'`` and PyTorch ``padding='same'`` do for an even
kernel. It is applied with an explicit ``F.pad`` (:func:`pad_depth`) so that the choice is visible.
"""

from __future__ import annotations

import math
from typing import ClassVar

import torch
from torch import nn
import torch.nn.functional as F

from cva_confidence_ros.checks import is_int, is_real
from cva_confidence_ros.errors import ConfigError, InputError

__all__ = [
    'CONV_INIT_STD',
    'DEPTH_KERNELS',
    'FUSION_LAYERS',
    'CVANet',
    'Classification',
    'DepthProcessing',
    'NeighbourhoodFusion',
    'check_network_options',
    'confidence_from_logits',
    'keras_parameter_count',
]

#: Number of 3×3×3 fusion convolutions; each one removes 2 pixels from H, W and D.
FUSION_LAYERS = 6
#: Side of the square extract one confidence value depends on (the receptive field).
PATCH_SIZE = 2 * FUSION_LAYERS + 1
#: Kernel depths of the depth-processing convolutions, in order (Table 2, layers 7–16).
DEPTH_KERNELS = (8, 16, 32) + (64,) * 7
#: Filters of every convolution of the fusion and depth stages.
FILTERS = 32
#: Nodes of the first fully-connected layer.
FC_NODES = 16
#: The paper's N(0, 0.0025) is a variance: the standard deviation is 0.05.
CONV_INIT_STD = 0.05
#: Smallest depth that leaves a non-empty cost curve after the fusion.
MIN_DISPARITY = 2 * FUSION_LAYERS + 1


class NeighbourhoodFusion(nn.Module):
    """Input BN and six unpadded 3×3×3 convolutions, each followed by BN and ReLU.

    Maps (B, 1, D, H + 12, W + 12) to (B, 32, D − 12, H, W).
    """

    def __init__(self) -> None:
        super().__init__()
        self.input_bn = nn.BatchNorm3d(1)
        convs, norms = [], []
        for index in range(FUSION_LAYERS):
            convs.append(nn.Conv3d(1 if index == 0 else FILTERS, FILTERS, kernel_size=3))
            norms.append(nn.BatchNorm3d(FILTERS))
        self.convs = nn.ModuleList(convs)
        self.norms = nn.ModuleList(norms)

    def forward(self, volume: torch.Tensor) -> torch.Tensor:
        x = self.input_bn(volume)
        for conv, norm in zip(self.convs, self.norms, strict=True):
            x = F.relu(norm(conv(x)))
        return x


class DepthProcessing(nn.Module):
    """Ten 1×1×k convolutions along the disparity axis with depth-keeping zero padding.

    Works on cost curves laid out as (1, 32, D', N) with N = B·H·W (disparity on the third
    axis, one column per pixel); keeps the shape.
    """

    def __init__(self) -> None:
        super().__init__()
        self.convs = nn.ModuleList(nn.Conv2d(FILTERS, FILTERS, (k, 1)) for k in DEPTH_KERNELS)
        self.norms = nn.ModuleList(nn.BatchNorm2d(FILTERS) for _ in DEPTH_KERNELS)

    def forward(self, curves: torch.Tensor) -> torch.Tensor:
        x = curves
        for conv, norm, kernel in zip(self.convs, self.norms, DEPTH_KERNELS, strict=True):
            x = F.relu(norm(conv(pad_depth(x, kernel))))
        return x


def pad_depth(curves: torch.Tensor, kernel: int) -> torch.Tensor:
    """Zero-pad (…, D', N) curves on the disparity axis so that a depth-k kernel keeps D'.

    ``k // 2 − 1`` zeros before and ``k // 2`` after for even k (Keras and PyTorch 'same').
    """
    before = (kernel - 1) // 2
    return F.pad(curves, (0, 0, before, kernel - 1 - before))


def to_curves(fused: torch.Tensor) -> torch.Tensor:
    """(B, C, D', H, W) → (1, C, D', B·H·W), pixel-major in (b, y, x) order."""
    batch, channels, depth, height, width = fused.shape
    return fused.permute(1, 2, 0, 3, 4).reshape(1, channels, depth, batch * height * width)


class Classification(nn.Module):
    """Fully-connected 16 nodes (ReLU, dropout 0.5) and 1 node, as convolutions.

    Maps curves (1, 32, D', N) to logits of shape (N,).

    Args:
        depth: D' = D − 12, the depth of the fused cost curves; the first layer spans all of it.
        dropout: Dropout rate after the first layer (paper: 0.5).
    """

    def __init__(self, depth: int, dropout: float = 0.5) -> None:
        super().__init__()
        self.fc1 = nn.Conv2d(FILTERS, FC_NODES, (depth, 1))
        self.dropout = nn.Dropout(dropout)
        self.fc2 = nn.Conv2d(FC_NODES, 1, 1)

    def forward(self, curves: torch.Tensor) -> torch.Tensor:
        x = self.dropout(F.relu(self.fc1(curves)))
        return self.fc2(x).reshape(-1)


def confidence_from_logits(logits: torch.Tensor) -> torch.Tensor:
    """``sigmoid(logits)``, in float32 under autocast: a bfloat16 sigmoid rounds every
    confidence above 0.998 to exactly 1.0 and keeps 8 bits below it (``cva_precision: bf16``
    gave 1.0 to half of the pixels of a real volume, and ties that cost the ranking AUC)."""
    if logits.dtype in (torch.bfloat16, torch.float16) and torch.is_autocast_enabled(
        logits.device.type
    ):
        logits = logits.float()
    return torch.sigmoid(logits)


class CVANet(nn.Module):
    """The Cost Volume Analysis Network, fully convolutional.

    Input: normalised cost volume of shape (B, 1, D, H + 12, W + 12), float32, values in [0, 1]
    (0 = perfect match), depth axis before the image axes. Output: confidence of shape (B, H, W)
    in (0, 1), higher = the winner-takes-all disparity of that pixel is more likely correct.
    A 13×13 training extract (B, 1, D, 13, 13) gives (B, 1, 1); any larger input gives one value
    per 13×13 window (stride 1), so a whole image padded by 6 px gives a full confidence map.

    Args:
        max_disparity: D, the depth of the cost volumes this network accepts (paper: 256).
        dropout: Dropout rate of the classification stage (paper: 0.5).

    Raises:
        ConfigError: ``max_disparity`` not an integer or below 13 (nothing left after the
            fusion), or ``dropout`` not a real number in [0, 1).
    """

    #: Architecture name in weights files (``model.weights.ARCHITECTURES``).
    arch: ClassVar[str] = 'cvanet'

    def __init__(self, max_disparity: int = 256, dropout: float = 0.5) -> None:
        super().__init__()
        self.max_disparity = check_network_options(
            max_disparity,
            MIN_DISPARITY,
            f'the fusion removes {2 * FUSION_LAYERS} disparities',
            dropout,
        )
        self.fusion = NeighbourhoodFusion()
        self.depth = DepthProcessing()
        self.classification = Classification(self.max_disparity - 2 * FUSION_LAYERS, dropout)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Initialise as the paper: convolutions N(0, σ=0.05), fully-connected layers Glorot.

        Biases start at zero (the Keras default); batch normalisation gets its defaults
        (:func:`reset_batchnorm`), so that loaded weights are reset completely.
        """
        reset_batchnorm(self)
        for module in (*self.fusion.convs, *self.depth.convs):
            assert isinstance(module, nn.modules.conv._ConvNd)
            nn.init.normal_(module.weight, mean=0.0, std=CONV_INIT_STD)
            nn.init.zeros_(conv_bias(module))
        # Glorot as for the dense layers they stand for: fan-in = all inputs of a node,
        # fan-out = the number of nodes (PyTorch's xavier_ would multiply the fan-out by the
        # kernel depth of the convolution form).
        for module in (self.classification.fc1, self.classification.fc2):
            fan_in = module.weight[0].numel()
            limit = glorot_limit(fan_in, module.out_channels)
            nn.init.uniform_(module.weight, -limit, limit)
            nn.init.zeros_(conv_bias(module))

    def check_input(self, volume: torch.Tensor) -> None:
        """Raise :class:`InputError` unless ``volume`` is a floating-point (B, 1, D, ≥13, ≥13)
        tensor with this D."""
        if not isinstance(volume, torch.Tensor):
            raise InputError(
                f'expected a cost-volume torch.Tensor of shape (B, 1, D, H + 12, W + 12); '
                f'got {type(volume).__name__}'
            )
        if volume.ndim != 5 or volume.shape[1] != 1:
            raise InputError(
                f'expected a cost-volume tensor of shape (B, 1, D, H + 12, W + 12); '
                f'got {tuple(volume.shape)}'
            )
        if volume.shape[2] != self.max_disparity:
            raise InputError(
                f'this network takes cost volumes of depth D = {self.max_disparity}; '
                f'got depth {volume.shape[2]}'
            )
        if volume.shape[3] < PATCH_SIZE or volume.shape[4] < PATCH_SIZE:
            raise InputError(
                f'expected at least {PATCH_SIZE}×{PATCH_SIZE} pixels (H + 12, W + 12); '
                f'got {volume.shape[3]}×{volume.shape[4]}'
            )
        if not volume.dtype.is_floating_point:
            raise InputError(
                f'expected a floating-point cost volume normalised to [0, 1]; got {volume.dtype}'
            )

    def forward_logits(self, volume: torch.Tensor) -> torch.Tensor:
        """Pre-sigmoid scores, for a numerically stable ``binary_cross_entropy_with_logits``.

        Args:
            volume: (B, 1, D, H + 12, W + 12) normalised cost volume, floating point (converted
                to the dtype of the weights, float32 unless the network was converted).

        Returns:
            (B, H, W) logits in the dtype of the weights; ``sigmoid`` of them is :meth:`forward`.
        """
        self.check_input(volume)
        # Any floating-point volume is accepted (check_input): a float64 or float16 one would
        # otherwise stop in the first layer with "mixed dtype" or "Input type ... and bias type".
        fused = self.fusion(volume.to(self.fusion.input_bn.weight.dtype))
        batch, _, _, height, width = fused.shape
        if batch == 0:  # no curves: the depth convolutions cannot run on an empty layout
            return fused.new_zeros((0, height, width))
        logits = self.classification(self.depth(to_curves(fused)))
        return logits.reshape(batch, height, width)

    def forward(self, volume: torch.Tensor) -> torch.Tensor:
        """Confidence in (0, 1) of shape (B, H, W) for an input (B, 1, D, H + 12, W + 12)."""
        return confidence_from_logits(self.forward_logits(volume))

    def fold_batchnorm(self) -> nn.Module:
        """The inference form, as CVA-Net-Lite and -Fast fold themselves:
        :func:`~cva_confidence_ros.model.inference.fold_batchnorm` of this network."""
        from cva_confidence_ros.model.inference import fold_batchnorm

        return fold_batchnorm(self)


def check_network_options(
    max_disparity: int, minimum: int, reason: str, dropout: float
) -> int:
    """Check the options of a cost-volume network; return D as an int.

    Args:
        max_disparity: Cost-volume depth D asked for.
        minimum: Smallest D the architecture accepts.
        reason: Why (ends the error message).
        dropout: Dropout rate of the classification stage.

    Raises:
        ConfigError: D not an integer (a bool, a float or None included) or below ``minimum``,
            or dropout not a real number in [0, 1).
    """
    if not is_int(max_disparity):
        raise ConfigError(
            f'max_disparity must be an integer >= {minimum} ({reason}); '
            f'got {type(max_disparity).__name__} {max_disparity!r}'
        )
    if max_disparity < minimum:
        raise ConfigError(
            f'max_disparity must be an integer >= {minimum} ({reason}); got {max_disparity}'
        )
    if (
        not is_real(dropout)
        or not 0.0 <= float(dropout) < 1.0
    ):
        raise ConfigError(
            f'dropout must be a real number in [0, 1); got {type(dropout).__name__} {dropout!r}'
        )
    return int(max_disparity)


def keras_parameter_count(module: nn.Module) -> int:
    """Count parameters as Keras does: trainable weights plus BN running mean and variance.

    PyTorch's ``num_batches_tracked`` counter has no Keras counterpart and is left out. With
    D = 256, :class:`CVANet` has 782,725 such parameters, the figure of the paper.
    """
    count = sum(p.numel() for p in module.parameters())
    for sub in module.modules():
        if isinstance(sub, nn.modules.batchnorm._BatchNorm) and sub.track_running_stats:
            assert sub.running_mean is not None and sub.running_var is not None
            count += sub.running_mean.numel() + sub.running_var.numel()
    return int(count)


def reset_batchnorm(net: nn.Module) -> None:
    """Every batch normalisation of ``net`` back to γ = 1, β = 0 and running statistics 0 / 1.

    Part of each network's ``reset_parameters``: without it, a reset of loaded weights kept
    the trained statistics (running variances up to 183) under freshly drawn convolutions.
    """
    for module in net.modules():
        if isinstance(module, nn.modules.batchnorm._BatchNorm):
            module.reset_parameters()


def conv_bias(conv: nn.modules.conv._ConvNd) -> torch.Tensor:
    """The bias of a convolution of this network (every one has a bias, as in the paper)."""
    if conv.bias is None:
        raise ConfigError(f'expected a convolution with a bias; got {conv}')
    return conv.bias


def receptive_field() -> int:
    """Side of the square window one confidence value depends on (13)."""
    return PATCH_SIZE


def expected_parameter_count(max_disparity: int) -> int:
    """Keras-style parameter count of :class:`CVANet` for depth D, computed from Table 2."""
    bn = 4 * FILTERS
    fusion = 4 + (27 * FILTERS + FILTERS + bn)
    fusion += (FUSION_LAYERS - 1) * (27 * FILTERS * FILTERS + FILTERS + bn)
    depth = sum(k * FILTERS * FILTERS + FILTERS + bn for k in DEPTH_KERNELS)
    fc = (max_disparity - 2 * FUSION_LAYERS) * FILTERS * FC_NODES + FC_NODES + FC_NODES + 1
    return fusion + depth + fc


def glorot_limit(fan_in: int, fan_out: int) -> float:
    """Half-width of the Glorot uniform distribution for the given fans."""
    return math.sqrt(6.0 / (fan_in + fan_out))

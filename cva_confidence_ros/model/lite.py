"""CVA-Net-Lite: a light network with CVA-Net's contract, meant to be distilled from it.

It reads the same input as :class:`~cva_confidence_ros.model.CVANet` — a zero-padded normalised
cost volume (B, 1, D, H + 12, W + 12) — sees the same 13×13 window per pixel and returns the
same (B, H, W) confidence, so every inference path (tiles, pixel subsets, the node, the
evaluation) runs it unchanged. It keeps the paper's three stages, each made cheaper:

* :class:`LiteFusion` — input batch normalisation; a first 3D convolution with an 8×3×3
  kernel and stride 4 along the disparity axis (16 filters), which condenses the cost curve to
  ⌊(D − 8) / 4⌋ + 1 bins while it starts the spatial fusion (the last (D − 8) mod 4
  disparities fall outside every bin and are not read: all are read for D = 8 + 4k, e.g. 64,
  not the last two for D = 66); five further 3×3×3 convolutions
  with 16 filters, unpadded in the image plane (six in all: the 13×13 window) and zero-padded
  along the disparity axis so that the condensed depth is kept;
* :class:`LiteDepthProcessing` — three convolutions along the disparity axis with kernel
  depths 4, 8 and 16 (the paper's doubling sequence, cut where it spans the condensed curve),
  16 filters, depth-keeping zero padding;
* :class:`LiteClassification` — a fully-connected layer of 16 nodes over the whole condensed
  depth (ReLU, dropout), then 1 node.

Every convolution except the classification is followed by batch normalisation and ReLU.
At D = 64 it costs about 0.65 M multiply-adds per pixel, 54× fewer than CVA-Net's 34.7 M
(:func:`~cva_confidence_ros.model.complexity.macs_per_pixel`).
"""

from __future__ import annotations

from collections.abc import Iterable
import math
from typing import ClassVar, cast

import torch
from torch import nn
import torch.nn.functional as F

from cva_confidence_ros.errors import InputError
from cva_confidence_ros.model.network import (
    CONV_INIT_STD,
    FUSION_LAYERS,
    PATCH_SIZE,
    check_network_options,
    confidence_from_logits,
    conv_bias,
    glorot_limit,
    pad_depth,
    reset_batchnorm,
    to_curves,
)

__all__ = [
    'LITE_DEPTH_KERNELS',
    'LITE_FILTERS',
    'LITE_MIN_DISPARITY',
    'CVANetLite',
    'FoldedCVANetLite',
    'LiteClassification',
    'LiteDepthProcessing',
    'LiteFusion',
    'condensed_depth',
    'init_light_network',
    'lite_activations_per_pixel',
]

#: Filters of every fusion and depth-processing convolution (CVA-Net: 32).
LITE_FILTERS = 16
#: Kernel depth and stride along the disparity axis of the first fusion convolution.
LITE_FIRST_KERNEL = 8
LITE_STRIDE = 4
#: Kernel depths of the depth-processing convolutions (CVA-Net: 8, 16, 32, 64 × 7).
LITE_DEPTH_KERNELS = (4, 8, 16)
#: Nodes of the first fully-connected layer (as CVA-Net).
LITE_FC_NODES = 16
#: Smallest D the first convolution fits in.
LITE_MIN_DISPARITY = LITE_FIRST_KERNEL


def condensed_depth(max_disparity: int) -> int:
    """Depth of the cost curves after the strided first convolution: ⌊(D − 8) / 4⌋ + 1."""
    return (int(max_disparity) - LITE_FIRST_KERNEL) // LITE_STRIDE + 1


def lite_activations_per_pixel(max_disparity: int) -> int:
    """Float32 values per pixel of CVA-Net-Lite's widest activation: max(D, 16 · D'')."""
    return max(int(max_disparity), LITE_FILTERS * condensed_depth(max_disparity))


class LiteFusion(nn.Module):
    """Input BN, a strided 8×3×3 convolution and five 3×3×3 ones, each with BN and ReLU.

    Maps (B, 1, D, H + 12, W + 12) to (B, 16, D'', H, W), D'' = :func:`condensed_depth`.
    """

    def __init__(self) -> None:
        super().__init__()
        self.input_bn = nn.BatchNorm3d(1)
        convs = [nn.Conv3d(1, LITE_FILTERS, (LITE_FIRST_KERNEL, 3, 3), stride=(LITE_STRIDE, 1, 1))]
        convs += [
            nn.Conv3d(LITE_FILTERS, LITE_FILTERS, 3, padding=(1, 0, 0))
            for _ in range(FUSION_LAYERS - 1)
        ]
        self.convs = nn.ModuleList(convs)
        self.norms = nn.ModuleList(nn.BatchNorm3d(LITE_FILTERS) for _ in convs)

    def forward(self, volume: torch.Tensor) -> torch.Tensor:
        x = self.input_bn(volume)
        for conv, norm in zip(self.convs, self.norms, strict=True):
            x = F.relu(norm(conv(x)))
        return x


class LiteDepthProcessing(nn.Module):
    """Convolutions of depth 4, 8, 16 along the disparity axis, depth-keeping zero padding.

    Works on curves laid out as (1, 16, D'', N), N = B·H·W, as CVA-Net's depth stage.
    """

    def __init__(self) -> None:
        super().__init__()
        self.convs = nn.ModuleList(
            nn.Conv2d(LITE_FILTERS, LITE_FILTERS, (k, 1)) for k in LITE_DEPTH_KERNELS
        )
        self.norms = nn.ModuleList(nn.BatchNorm2d(LITE_FILTERS) for _ in LITE_DEPTH_KERNELS)

    def forward(self, curves: torch.Tensor) -> torch.Tensor:
        x = curves
        for conv, norm, kernel in zip(self.convs, self.norms, LITE_DEPTH_KERNELS, strict=True):
            x = F.relu(norm(conv(pad_depth(x, kernel))))
        return x


class LiteClassification(nn.Module):
    """Fully-connected 16 nodes over the condensed depth (ReLU, dropout) and 1 node.

    Maps curves (1, 16, D'', N) to logits of shape (N,).
    """

    def __init__(self, depth: int, dropout: float = 0.5) -> None:
        super().__init__()
        self.fc1 = nn.Conv2d(LITE_FILTERS, LITE_FC_NODES, (depth, 1))
        self.dropout = nn.Dropout(dropout)
        self.fc2 = nn.Conv2d(LITE_FC_NODES, 1, 1)

    def forward(self, curves: torch.Tensor) -> torch.Tensor:
        x = self.dropout(F.relu(self.fc1(curves)))
        return self.fc2(x).reshape(-1)


def init_light_network(convs: Iterable[nn.Module], fully_connected: Iterable[nn.Module]) -> None:
    """Initialise a light cost-volume network: convolutions He-normal (narrow layers: CVA-Net's
    σ = 0.05 would start them almost silent; never below it), fully-connected layers Glorot as in
    CVA-Net, zero biases; BN layers are left to the caller (``reset_batchnorm``)."""
    for module in convs:
        assert isinstance(module, nn.modules.conv._ConvNd)
        fan_in = module.weight[0].numel()
        nn.init.normal_(module.weight, mean=0.0, std=max(CONV_INIT_STD, math.sqrt(2 / fan_in)))
        nn.init.zeros_(conv_bias(module))
    for module in fully_connected:
        assert isinstance(module, nn.modules.conv._ConvNd)
        limit = glorot_limit(module.weight[0].numel(), module.out_channels)
        nn.init.uniform_(module.weight, -limit, limit)
        nn.init.zeros_(conv_bias(module))


class CVANetLite(nn.Module):
    """CVA-Net-Lite, fully convolutional, with the input and output of :class:`CVANet`.

    Input: normalised cost volume (B, 1, D, H + 12, W + 12), float32 in [0, 1]. Output:
    confidence (B, H, W) in (0, 1); a 13×13 extract gives (B, 1, 1).

    Args:
        max_disparity: D, the depth of the cost volumes this network accepts (≥ 8).
        dropout: Dropout rate of the classification stage.

    Raises:
        ConfigError: ``max_disparity`` below 8 or not an integer, or a bad dropout rate.
    """

    #: Architecture name in weights files (``model.weights.ARCHITECTURES``).
    arch: ClassVar[str] = 'cvanet_lite'

    def __init__(self, max_disparity: int = 64, dropout: float = 0.5) -> None:
        super().__init__()
        self.max_disparity = check_network_options(
            max_disparity,
            LITE_MIN_DISPARITY,
            f'the first convolution spans {LITE_FIRST_KERNEL} disparities',
            dropout,
        )
        self.fusion = LiteFusion()
        self.depth = LiteDepthProcessing()
        self.classification = LiteClassification(condensed_depth(self.max_disparity), dropout)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """See :func:`init_light_network`; batch normalisation back to its defaults."""
        reset_batchnorm(self)
        init_light_network(
            (*self.fusion.convs, *self.depth.convs),
            (self.classification.fc1, self.classification.fc2),
        )

    def check_input(self, volume: torch.Tensor) -> None:
        """Raise :class:`InputError` unless ``volume`` is (B, 1, D, ≥13, ≥13) with this D."""
        check_volume_tensor(volume, self.max_disparity)

    def forward_logits(self, volume: torch.Tensor) -> torch.Tensor:
        """(B, 1, D, H + 12, W + 12) floating point (converted to the dtype of the weights) →
        (B, H, W) pre-sigmoid scores."""
        self.check_input(volume)
        fused = self.fusion(volume.to(_weights_dtype(self)))
        batch, _, _, height, width = fused.shape
        if batch == 0:  # no curves: the depth convolutions cannot run on an empty layout
            return fused.new_zeros((0, height, width))
        logits = self.classification(self.depth(to_curves(fused)))
        return logits.reshape(batch, height, width)

    def forward(self, volume: torch.Tensor) -> torch.Tensor:
        """Confidence in (0, 1) of shape (B, H, W)."""
        return confidence_from_logits(self.forward_logits(volume))

    @property
    def activations_per_pixel(self) -> int:
        """Float32 values per pixel of the widest activation (the tile size follows from it)."""
        return lite_activations_per_pixel(self.max_disparity)

    def fold_batchnorm(self) -> FoldedCVANetLite:
        """An inference-only copy with every BN merged into a convolution (this net unchanged)."""
        return FoldedCVANetLite(self)


def _weights_dtype(net: nn.Module) -> torch.dtype:
    """The dtype of ``net``'s first parameter: the one its input is brought to (any
    floating-point volume is taken; a float64 one stopped at the first layer with "mixed
    dtype" or "Input type ... and bias type")."""
    return next(net.parameters()).dtype


def check_volume_tensor(volume: torch.Tensor, max_disparity: int) -> None:
    """Raise :class:`InputError` unless ``volume`` is a floating-point (B, 1, D, ≥13, ≥13)
    tensor with the given D (a numpy array is named, not failed on)."""
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
    if volume.shape[2] != max_disparity:
        raise InputError(
            f'this network takes cost volumes of depth D = {max_disparity}; '
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


class FoldedCVANetLite(nn.Module):
    """CVA-Net-Lite for inference only: BN folded into the convolutions, no dropout.

    Same input and output as :class:`CVANetLite` in eval mode. The input BN (an affine map
    x → a·x + c) moves into the first convolution exactly because that convolution is unpadded.

    The depth and classification stages see one pixel's 16 × D'' features at a time, so each
    of their convolutions is a linear map of that vector: it runs as one matrix product with a
    banded (Toeplitz) matrix of the folded weights, (N, 16·D'') @ (16·D'', 16·D''). That does
    more multiply-adds than the convolution (zeros included) but runs at matrix-multiply speed,
    several times faster on CPU than ``Conv1d`` over 16 channels and a handful of disparities.
    """

    #: Ready for inference as it is; see ``model.inference.predict_confidence``.
    is_folded = True

    # Set by ``setattr`` and ``register_buffer`` in ``__init__`` (types for the checker only).
    fc1: nn.Conv1d
    fc2: nn.Conv1d
    fc1_matrix: torch.Tensor

    def __init__(self, net: CVANetLite) -> None:
        super().__init__()
        from cva_confidence_ros.model.inference import _bn_affine

        self.max_disparity = net.max_disparity
        self.fusion = nn.ModuleList()
        self.depth = nn.ModuleList()
        with torch.no_grad():
            in_scale, in_shift = _bn_affine(net.fusion.input_bn)
            pairs = zip(net.fusion.convs, net.fusion.norms, strict=True)
            for index, (conv, norm) in enumerate(pairs):
                assert isinstance(conv, nn.Conv3d)
                weight, bias = conv.weight.double(), conv_bias(conv).double()
                if index == 0:
                    bias = bias + in_shift[0] * weight.sum(dim=(1, 2, 3, 4))
                    weight = weight * in_scale[0]
                self.fusion.append(_fold(conv, weight, bias, norm))
            depth_convs = cast('Iterable[nn.Conv2d]', net.depth.convs)
            for conv, norm in zip(depth_convs, net.depth.norms, strict=True):
                self.depth.append(
                    _fold(conv, conv.weight.double(), conv_bias(conv).double(), norm)
                )
            for name in ('fc1', 'fc2'):
                conv = getattr(net.classification, name)
                setattr(self, name, _fold(conv, conv.weight.double(), conv_bias(conv).double()))
            depth = condensed_depth(self.max_disparity)
            folded_depth = cast('Iterable[nn.Conv1d]', self.depth)
            for index, (conv, k) in enumerate(zip(folded_depth, LITE_DEPTH_KERNELS, strict=True)):
                matrix = _banded_matrix(conv.weight, depth, (k - 1) // 2)
                self.register_buffer(f'depth_matrix{index}', matrix)
                depth_bias = conv_bias(conv).repeat_interleave(depth)
                self.register_buffer(f'depth_bias{index}', depth_bias)
            # fc1 spans the whole depth: its (16, C, D'') kernel is a (C·D'', 16) matrix.
            self.register_buffer('fc1_matrix', self.fc1.weight.reshape(LITE_FC_NODES, -1).t())
        self.requires_grad_(False)
        self.eval()

    @property
    def activations_per_pixel(self) -> int:
        """Float32 values per pixel of the widest activation (the tile size follows from it)."""
        return lite_activations_per_pixel(self.max_disparity)

    def fusion_features(self, volume: torch.Tensor) -> torch.Tensor:
        """The neighbourhood fusion: (B, 1, D, H + 12, W + 12) → (B, 16, D'', H, W).

        With :meth:`head_logits` it splits the network at the per-pixel curves, as
        CVA-Net's folded form does, so that the sparse evaluation can fuse densely and run the
        depth stage only at the wanted pixels.
        """
        check_volume_tensor(volume, self.max_disparity)
        x = volume.to(_weights_dtype(self))  # a float64 or float16 volume, as unfolded
        for conv in self.fusion:
            # In place on the fresh output: two live activations, not three.
            x = F.relu(_inference_conv3d(conv, x), inplace=True)
        return x

    def head_logits(self, curves: torch.Tensor) -> torch.Tensor:
        """Depth processing and classification of fused curves: (N, 16, D'') → (N,) logits."""
        # (N, C·D'') with feature index c·D'' + d, as the banded matrices expect. N may be 0:
        # flatten, not reshape(N, -1), which the ONNX graph cannot resolve for an empty batch.
        x = curves.flatten(1)
        for index in range(len(LITE_DEPTH_KERNELS)):
            matrix = getattr(self, f'depth_matrix{index}')
            # In place: the (N, 16·D'') product is as wide as the fusion's output.
            x = F.relu(torch.addmm(getattr(self, f'depth_bias{index}'), x, matrix), inplace=True)
        x = F.relu(torch.addmm(conv_bias(self.fc1), x, self.fc1_matrix))
        x = x @ self.fc2.weight[:, :, 0].t() + conv_bias(self.fc2)
        return x.reshape(-1)

    def forward_logits(self, volume: torch.Tensor) -> torch.Tensor:
        """(B, 1, D, H + 12, W + 12) float32 → (B, H, W) float32 logits."""
        x = self.fusion_features(volume)
        batch, channels, depth, height, width = x.shape
        x = x.permute(0, 3, 4, 1, 2).reshape(batch * height * width, channels, depth)
        return self.head_logits(x).reshape(batch, height, width)

    def forward(self, volume: torch.Tensor) -> torch.Tensor:
        """Confidence in (0, 1), (B, H, W)."""
        return confidence_from_logits(self.forward_logits(volume))


def _inference_conv3d(conv: nn.Module, x: torch.Tensor) -> torch.Tensor:
    """``conv(x)`` for a folded (inference-only) network, through oneDNN where it can run.

    PyTorch's CPU heuristic gives a batch-1 Conv3d with a 3-wide kernel and N·C·D·H ≤ 20480 to
    its native vol2col convolution: every layer of a CVA-Net-Lite tile of fewer than 74 rows
    (D = 64), and its one-channel first layer below about 310 rows. Its work buffer holds
    C_in·k values per output voxel, far beyond the widest activation the tile budget counts:
    6 480 float32 a pixel in CVA-Net-Lite's later layers at D = 64 (27×), 1 080 in its first
    (CVA-Net's first layer: 1 674, within its 6 144). oneDNN needs no such buffer and is
    faster. The plain module runs everywhere else: autograd, CUDA, another dtype, autocast,
    tracing or export (the ONNX graph keeps its Conv node).
    """
    assert isinstance(conv, nn.Conv3d)
    if (
        torch.is_inference_mode_enabled()
        and x.device.type == 'cpu'
        and x.dtype == conv.weight.dtype == torch.float32
        and isinstance(conv.padding, tuple)
        and conv.padding_mode == 'zeros'
        and torch.backends.mkldnn.is_available()
        and torch.backends.mkldnn.enabled
        and not torch.is_autocast_enabled('cpu')
        and not torch.jit.is_tracing()
        and not torch.compiler.is_exporting()
    ):
        return torch.mkldnn_convolution(
            x, conv.weight, conv.bias, conv.padding, conv.stride, conv.dilation, conv.groups
        )
    return conv(x)


def _banded_matrix(weight: torch.Tensor, depth: int, before: int) -> torch.Tensor:
    """The (C_in·D'', C_out·D'') matrix of a zero-padded depth convolution.

    ``weight`` is (C_out, C_in, k); the convolution's output at depth d reads inputs
    d − before … d − before + k − 1, zeros outside [0, D''). Feature index = channel·D'' + d.
    """
    out_channels, in_channels, kernel = weight.shape
    matrix = weight.new_zeros(in_channels, depth, out_channels, depth)
    for d_out in range(depth):
        for tap in range(kernel):
            d_in = d_out + tap - before
            if 0 <= d_in < depth:
                matrix[:, d_in, :, d_out] = weight[:, :, tap].t()
    return matrix.reshape(in_channels * depth, out_channels * depth).contiguous()


def _fold(
    conv: nn.Module,
    weight: torch.Tensor,
    bias: torch.Tensor,
    norm: nn.Module | None = None,
) -> nn.Module:
    """A copy of ``conv`` with the BN ``norm`` after it merged in; (k, 1) ``Conv2d`` kernels
    become ``Conv1d`` (the depth stage runs on (N, C, D'') in the folded net)."""
    from cva_confidence_ros.model.inference import _bn_affine

    device = conv.weight.device
    new: nn.Module
    if isinstance(conv, nn.Conv3d):
        # A Conv3d's kernel_size, stride and padding are 3-tuples (or a padding string).
        new = nn.Conv3d(
            conv.in_channels,
            conv.out_channels,
            cast(tuple[int, int, int], conv.kernel_size),
            stride=cast(tuple[int, int, int], conv.stride),
            padding=cast('str | tuple[int, int, int]', conv.padding),
            device=device,
        )
    else:
        assert isinstance(conv, nn.Conv2d)
        weight = weight[..., 0]
        new = nn.Conv1d(conv.in_channels, conv.out_channels, conv.kernel_size[0], device=device)
    if norm is not None:
        scale, shift = _bn_affine(norm)
        weight = weight * scale.reshape(-1, *([1] * (weight.ndim - 1)))
        bias = bias * scale + shift
    new.weight.copy_(weight.float())
    conv_bias(new).copy_(bias.float())
    return new

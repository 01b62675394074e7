"""CVA-Net-Fast: CVA-Net's contract at about 1/600 of its operations, for CPUs.

CVA-Net-Lite showed where a light cost-volume network spends its work: ≈ 83 % of its
multiply-adds are the 3-D neighbourhood fusion, which convolves every condensed disparity bin of
every pixel with its neighbours'. CVA-Net-Fast swaps the order of the paper's two analysis
stages, so that the neighbourhood is fused once per pixel instead of once per disparity, and
reads each cost curve relative to its winner-takes-all minimum:

* :class:`CurveEncoder` (per pixel, along the disparity axis — the paper's *depth processing*,
  moved first) — :func:`aligned_curve` takes the 9 normalised costs around the pixel's WTA
  minimum (d_WTA − 4 … d_WTA + 4, the shape of the minimum the WTA decision rests on,
  independent of where it lies) and d_WTA / D; batch normalisation of those 10 inputs; two
  fully-connected layers per pixel (1×1 convolutions), 64 and 32 features;
* :class:`PlaneFusion` (the paper's *neighbourhood fusion*, now 2-D) — six 3×3 convolutions in
  the image plane, 32 filters, unpadded: the same 13×13 window per pixel as CVA-Net, which
  now compares the neighbours' minima and disparities;
* :class:`FastClassification` — a fully-connected layer of 16 nodes (ReLU, dropout 0.5) and
  one node, as 1×1 convolutions.

Every convolution except the classification is followed by batch normalisation and ReLU. The
input and output are CVA-Net's — a zero-padded normalised cost volume
(B, 1, D, H + 12, W + 12) in, (B, H, W) confidences out — so every inference path of the package
(tiles, pixel subsets, sparse evaluation, the pipeline, the node, ``cva-evaluate``) runs it
unchanged. It costs 58,512 multiply-adds per pixel whatever D
(:func:`~cva_confidence_ros.model.complexity.macs_per_pixel`; the WTA scan of D costs per pixel
comes on top): 592× fewer than CVA-Net and 11× fewer than CVA-Net-Lite at D = 64.

A controlled experiment showed why the WTA alignment matters: the same network fed the raw
D costs per pixel (an MLP over the curve) reached a validation AUC of 0.146 where the aligned
inputs reach 0.072 (``docs/CVA_NET_FAST.md``): a per-pixel MLP cannot find a curve's minimum
by itself.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import ClassVar, cast

from numba import njit, prange
import numpy as np
import torch
from torch import nn
import torch.autograd.forward_ad as fwAD
import torch.nn.functional as F

from cva_confidence_ros.model.lite import check_volume_tensor, init_light_network
from cva_confidence_ros.model.network import (
    FUSION_LAYERS,
    check_network_options,
    confidence_from_logits,
    conv_bias,
    reset_batchnorm,
)

__all__ = [
    'FAST_CURVE_FEATURES',
    'FAST_FILTERS',
    'CVANetFast',
    'CurveEncoder',
    'FastClassification',
    'FoldedCVANetFast',
    'PlaneFusion',
    'fast_activations_per_pixel',
]

#: Costs on each side of the winner-takes-all disparity that the curve encoder reads.
FAST_ALIGN = 4
#: Per-pixel inputs of the curve encoder: the 2·4 + 1 costs around the WTA minimum and d_WTA / D.
FAST_INPUTS = 2 * FAST_ALIGN + 2
#: Features of the first per-pixel layer.
FAST_CURVE_FEATURES = 64
#: Curve features per pixel, and filters of every plane-fusion convolution (CVA-Net: 32).
FAST_FILTERS = 32
#: Nodes of the first fully-connected layer (as CVA-Net).
FAST_FC_NODES = 16
#: Smallest D accepted: the aligned window must fit in the curve.
FAST_MIN_DISPARITY = 2 * FAST_ALIGN + 1
#: Cost given to disparities outside [0, D) in the aligned window (the worst normalised cost).
OUTSIDE_COST = 1.0


def fast_activations_per_pixel(max_disparity: int) -> int:
    """Float32 values per pixel of CVA-Net-Fast's widest activation: max(D, 64)."""
    return max(int(max_disparity), FAST_CURVE_FEATURES, FAST_FILTERS)


def aligned_curve(
    costs: torch.Tensor, memory_format: torch.memory_format = torch.contiguous_format
) -> torch.Tensor:
    """The curve encoder's inputs: (B, D, H, W) normalised costs → (B, 10, H, W).

    Channels 0–8: the costs at d_WTA − 4 … d_WTA + 4 (1.0 outside [0, D)); channel 9:
    d_WTA / D. d_WTA is the smallest d of the lowest cost (ties as ``argmin``). Float32 CPU
    tensors without gradient go through a compiled one-pass kernel (6× faster than the
    torch ops here), everything else (CUDA, autograd, forward-mode AD, tracing for an ONNX or
    TorchScript export, ``torch.func.vmap``) through torch; both give the same values (tested).
    ``memory_format``: the layout of the result (the kernel writes channels-last directly,
    which the folded network's convolutions take without a copy).
    """
    source: np.ndarray | None = None
    if (
        costs.device.type == 'cpu'
        and costs.dtype == torch.float32
        and not (torch.is_grad_enabled() and costs.requires_grad)
        # A forward-mode dual tensor (torch.autograd.forward_ad): the kernel's output carried
        # no tangent, and CVA-Net-Fast's jvp came out None where float64 gave it.
        and fwAD.unpack_dual(costs).tangent is None
        and not torch.jit.is_tracing()
        and not torch.compiler.is_exporting()
    ):
        try:
            source = costs.detach().contiguous().numpy()
        except RuntimeError:
            # A tensor without storage (torch.func.vmap's batched ones): the kernel cannot
            # read it, and its output would drop the vmap batch ("Cannot access data pointer").
            source = None
    if source is not None:
        result = torch.empty(
            (costs.shape[0], FAST_INPUTS, *costs.shape[2:]),
            dtype=torch.float32,  # the costs' own, whatever the default dtype
            memory_format=memory_format,
        )
        out = result.numpy()
        for index in range(costs.shape[0]):
            # (H, W, 10) view: C-contiguous for channels-last, strided for NCHW.
            _aligned_kernel(source[index], FAST_ALIGN, out[index].transpose(1, 2, 0))
        return result
    depth = costs.shape[1]
    wta = costs.argmin(dim=1, keepdim=True)
    padded = F.pad(costs, (0, 0, 0, 0, FAST_ALIGN, FAST_ALIGN), value=OUTSIDE_COST)
    offsets = torch.arange(2 * FAST_ALIGN + 1, device=costs.device).reshape(1, -1, 1, 1)
    aligned = torch.cat([padded.gather(1, wta + offsets), wta.to(costs.dtype) / depth], 1)
    return aligned.contiguous(memory_format=memory_format)


# Rows in parallel (numba threads), each in memory order: the first pass streams the row's
# costs once with a running minimum per pixel (strict '<': the smallest d among equal costs,
# and the first NaN, like argmin), the second reads only the 2·align + 1 costs around it. Per
# row, the running minimum stays in cache: 3× faster than whole planes at 320×240 on one
# thread, and the two threads share the rows.
@njit(cache=True, parallel=True)
def _aligned_kernel(volume: np.ndarray, align: int, out: np.ndarray) -> None:  # pragma: no cover
    depth, height, width = volume.shape
    span = 2 * align + 1
    scale = np.float32(depth)
    for y in prange(height):
        low = volume[0, y].copy()
        index = np.zeros(width, np.int32)
        for d in range(1, depth):
            row = volume[d, y]
            for x in range(width):
                value = row[x]
                # As argmin: a NaN counts as the minimum (the first one wins; a NaN minimum
                # stays), so that a NaN cost reaches the output here as it does through torch.
                if not value >= low[x] and low[x] == low[x]:
                    low[x] = value
                    index[x] = d
        for x in range(width):
            centre = index[x]
            for k in range(span):
                d = centre + k - align
                out[y, x, k] = volume[d, y, x] if 0 <= d < depth else np.float32(OUTSIDE_COST)
            out[y, x, span] = np.float32(centre) / scale  # as torch: a float32 division


class CurveEncoder(nn.Module):
    """Per-pixel cost-curve features: (B, 1, D, H, W) → (B, 32, H, W).

    :func:`aligned_curve` (the 9 costs around the WTA minimum and d_WTA / D), batch
    normalisation of those 10 inputs, then two fully-connected layers per pixel (1×1
    convolutions), 64 and 32 features, each with BN and ReLU.
    """

    def __init__(self) -> None:
        super().__init__()
        self.input_bn = nn.BatchNorm2d(FAST_INPUTS)
        self.fc_curve = nn.Conv2d(FAST_INPUTS, FAST_CURVE_FEATURES, 1)
        self.curve_bn = nn.BatchNorm2d(FAST_CURVE_FEATURES)
        self.squeeze = nn.Conv2d(FAST_CURVE_FEATURES, FAST_FILTERS, 1)
        self.squeeze_bn = nn.BatchNorm2d(FAST_FILTERS)

    def forward(self, volume: torch.Tensor) -> torch.Tensor:
        x = self.input_bn(aligned_curve(volume[:, 0]))
        x = F.relu(self.curve_bn(self.fc_curve(x)))
        return F.relu(self.squeeze_bn(self.squeeze(x)))


class PlaneFusion(nn.Module):
    """Six unpadded 3×3 convolutions with BN and ReLU: (B, 32, H + 12, W + 12) → (B, 32, H, W)."""

    def __init__(self) -> None:
        super().__init__()
        self.convs = nn.ModuleList(
            nn.Conv2d(FAST_FILTERS, FAST_FILTERS, 3) for _ in range(FUSION_LAYERS)
        )
        self.norms = nn.ModuleList(nn.BatchNorm2d(FAST_FILTERS) for _ in range(FUSION_LAYERS))

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        x = features
        for conv, norm in zip(self.convs, self.norms, strict=True):
            x = F.relu(norm(conv(x)))
        return x


class FastClassification(nn.Module):
    """Fully-connected 16 nodes (ReLU, dropout) and 1 node: (B, 32, H, W) → (B, H, W) logits."""

    def __init__(self, dropout: float = 0.5) -> None:
        super().__init__()
        self.fc1 = nn.Conv2d(FAST_FILTERS, FAST_FC_NODES, 1)
        self.dropout = nn.Dropout(dropout)
        self.fc2 = nn.Conv2d(FAST_FC_NODES, 1, 1)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return self.fc2(self.dropout(F.relu(self.fc1(features))))[:, 0]


class CVANetFast(nn.Module):
    """CVA-Net-Fast, fully convolutional, with the input and output of :class:`CVANet`.

    Input: normalised cost volume (B, 1, D, H + 12, W + 12), float32 in [0, 1]. Output:
    confidence (B, H, W) in (0, 1); a 13×13 extract gives (B, 1, 1).

    Args:
        max_disparity: D, the depth of the cost volumes this network accepts (≥ 9: the aligned
            window of 9 costs).
        dropout: Dropout rate of the classification stage.

    Raises:
        ConfigError: ``max_disparity`` below 9 or not an integer, or a bad dropout rate.
    """

    #: Architecture name in weights files (``model.weights.ARCHITECTURES``).
    arch: ClassVar[str] = 'cvanet_fast'

    def __init__(self, max_disparity: int = 64, dropout: float = 0.5) -> None:
        super().__init__()
        self.max_disparity = check_network_options(
            max_disparity,
            FAST_MIN_DISPARITY,
            f'the curve encoder reads at least {FAST_MIN_DISPARITY} disparities',
            dropout,
        )
        self.encoder = CurveEncoder()
        self.fusion = PlaneFusion()
        self.classification = FastClassification(dropout)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """As CVA-Net-Lite (:func:`~cva_confidence_ros.model.lite.init_light_network`): the
        per-pixel layers and the plane fusion He-normal, the classification Glorot; batch
        normalisation back to its defaults."""
        reset_batchnorm(self)
        init_light_network(
            (self.encoder.fc_curve, self.encoder.squeeze, *self.fusion.convs),
            (self.classification.fc1, self.classification.fc2),
        )

    def check_input(self, volume: torch.Tensor) -> None:
        """Raise :class:`InputError` unless ``volume`` is (B, 1, D, ≥13, ≥13) with this D."""
        check_volume_tensor(volume, self.max_disparity)

    def forward_logits(self, volume: torch.Tensor) -> torch.Tensor:
        """(B, 1, D, H + 12, W + 12) floating point (converted to the dtype of the weights) →
        (B, H, W) pre-sigmoid scores."""
        self.check_input(volume)
        volume = volume.to(self.encoder.fc_curve.weight.dtype)
        return self.classification(self.fusion(self.encoder(volume)))

    def forward(self, volume: torch.Tensor) -> torch.Tensor:
        """Confidence in (0, 1) of shape (B, H, W)."""
        return confidence_from_logits(self.forward_logits(volume))

    @property
    def activations_per_pixel(self) -> int:
        """Float32 values per pixel of the widest activation (the tile size follows from it)."""
        return fast_activations_per_pixel(self.max_disparity)

    def fold_batchnorm(self) -> FoldedCVANetFast:
        """An inference-only copy with every BN merged into a convolution (this net unchanged)."""
        return FoldedCVANetFast(self)


class FoldedCVANetFast(nn.Module):
    """CVA-Net-Fast for inference only: BN folded into the convolutions, no dropout.

    Same input and output as :class:`CVANetFast` in eval mode; after :func:`aligned_curve`
    every layer is a 2-D convolution on (B, C, H, W) tensors.
    """

    #: Ready for inference as it is; see ``model.inference.predict_confidence``.
    is_folded = True

    def __init__(self, net: CVANetFast) -> None:
        super().__init__()
        from cva_confidence_ros.model.inference import _bn_affine

        self.max_disparity = net.max_disparity
        encoder = net.encoder
        with torch.no_grad():
            # The first layer is a 1×1 convolution: the per-channel input BN x → a·x + c moves
            # into it exactly, w' = w·a (per input channel), b' = b + Σ w·c.
            in_scale, in_shift = _bn_affine(encoder.input_bn)
            weight = encoder.fc_curve.weight.double()
            bias = conv_bias(encoder.fc_curve).double() + (weight[:, :, 0, 0] * in_shift).sum(1)
            weight = weight * in_scale.reshape(1, -1, 1, 1)
            self.curve = _folded_conv2d(weight, bias, encoder.curve_bn)
            squeeze = encoder.squeeze
            self.squeeze = _folded_conv2d(
                squeeze.weight.double(), conv_bias(squeeze).double(), encoder.squeeze_bn
            )
            fusion_convs = cast('Iterable[nn.Conv2d]', net.fusion.convs)
            self.fusion = nn.ModuleList(
                _folded_conv2d(conv.weight.double(), conv_bias(conv).double(), norm)
                for conv, norm in zip(fusion_convs, net.fusion.norms, strict=True)
            )
            self.fc1 = _folded_conv2d(
                net.classification.fc1.weight.double(),
                conv_bias(net.classification.fc1).double(),
            )
            self.fc2 = _folded_conv2d(
                net.classification.fc2.weight.double(),
                conv_bias(net.classification.fc2).double(),
            )
        self.to(net.encoder.squeeze.weight.device)
        self.requires_grad_(False)
        self.eval()

    @property
    def activations_per_pixel(self) -> int:
        """Float32 values per pixel of the widest activation (the tile size follows from it)."""
        return fast_activations_per_pixel(self.max_disparity)

    def fusion_features(self, volume: torch.Tensor) -> torch.Tensor:
        """Curve encoding and plane fusion: (B, 1, D, H + 12, W + 12) → (B, 32, 1, H, W).

        With :meth:`head_logits` it splits the network as CVA-Net's folded form does, so that
        the sparse evaluation can run it (the split is at the classification here: every stage
        before it is shared between neighbouring pixels).
        """
        check_volume_tensor(volume, self.max_disparity)
        volume = volume.to(self.curve.weight.dtype)  # a float64 or float16 volume, as unfolded
        # Channels-last (NHWC) convolutions: ≈ 10 % faster on this CPU's oneDNN than NCHW,
        # equal up to float rounding (< 1e-5). The kernel writes NHWC itself (no copy), and
        # the ReLUs work in place on each convolution's fresh output: a new tensor per layer
        # cost a pass over fresh memory (≈ 1 ms of a 320×240 frame for the 64 channels).
        x = aligned_curve(volume[:, 0], torch.channels_last)
        x = F.relu(self.curve(x), inplace=True)
        x = F.relu(self.squeeze(x), inplace=True)
        for conv in self.fusion:
            x = F.relu(conv(x), inplace=True)
        return x[:, :, None]

    def head_logits(self, curves: torch.Tensor) -> torch.Tensor:
        """Classification of fused features: (N, 32, 1) → (N,) logits."""
        x = curves.reshape(curves.shape[0], FAST_FILTERS)
        x = F.relu(F.linear(x, self.fc1.weight[:, :, 0, 0], self.fc1.bias))
        return F.linear(x, self.fc2.weight[:, :, 0, 0], self.fc2.bias).reshape(-1)

    def forward_logits(self, volume: torch.Tensor) -> torch.Tensor:
        """(B, 1, D, H + 12, W + 12) float32 → (B, H, W) float32 logits."""
        x = self.fusion_features(volume)[:, :, 0]
        return self.fc2(F.relu(self.fc1(x), inplace=True))[:, 0]

    def forward(self, volume: torch.Tensor) -> torch.Tensor:
        """Confidence in (0, 1), (B, H, W)."""
        return confidence_from_logits(self.forward_logits(volume))


def _folded_conv2d(
    weight: torch.Tensor,
    bias: torch.Tensor,
    norm: nn.Module | tuple[torch.Tensor, torch.Tensor] | None = None,
) -> nn.Conv2d:
    """A float32 ``Conv2d`` (unpadded, stride 1) with the affine map of ``norm`` merged in."""
    from cva_confidence_ros.model.inference import _bn_affine

    if norm is not None:
        scale, shift = norm if isinstance(norm, tuple) else _bn_affine(norm)
        weight = weight * scale.double().reshape(-1, 1, 1, 1)
        bias = bias * scale.double() + shift.double()
    out_channels, in_channels, kh, kw = weight.shape
    conv = nn.Conv2d(in_channels, out_channels, (kh, kw), device=weight.device)
    # Stored channels-last, the layout of the activations: oneDNN reordered an NCHW weight
    # into a new tensor on every call (the same values either way).
    conv.weight = nn.Parameter(weight.float().contiguous(memory_format=torch.channels_last))
    conv_bias(conv).copy_(bias.float())
    return conv

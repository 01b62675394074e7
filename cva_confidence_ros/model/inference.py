"""Inference with CVA-Net on whole cost volumes or on chosen pixels.

Both entry points fold the batch normalisations into the convolutions first
(:func:`fold_batchnorm`): at inference a BN is a fixed per-channel affine map, so it can be merged
into the weights of the convolution before it (and the input BN into the unpadded first
convolution after it), which removes 17 passes over the activations.
"""

from __future__ import annotations

from collections.abc import Iterator
import contextlib
import math
from typing import cast

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
import torch
from torch import nn
import torch.nn.functional as F

from cva_confidence_ros.checks import is_int, is_real
from cva_confidence_ros.devices import resolve_device
from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.model.lite import check_volume_tensor
from cva_confidence_ros.model.network import (
    DEPTH_KERNELS,
    FUSION_LAYERS,
    PATCH_SIZE,
    CVANet,
    confidence_from_logits,
    conv_bias,
)

__all__ = [
    'PAD',
    'FoldedCVANet',
    'activations_per_pixel',
    'fold_batchnorm',
    'pad_cost_volume',
    'predict_confidence',
    'predict_confidence_at',
    'resolve_device',
    'tile_shape',
]

#: Zero padding added on each image side so that every pixel gets a full 13×13 window.
PAD = FUSION_LAYERS
# Rough number of live float32 copies of the widest activation (input, output and the
# convolution's work buffer) used to turn a memory budget into a tile size.
_LIVE_COPIES = 3
_VALUE_TOLERANCE = 1e-3
# Volume dtypes that torch.from_numpy wraps (any floating point passes the checks).
_TORCH_COPIES = (np.dtype(np.float16), np.dtype(np.float32), np.dtype(np.float64))


class FoldedCVANet(nn.Module):
    """CVA-Net for inference only, with every batch normalisation merged into a convolution.

    Same input and output as :class:`CVANet` in eval mode: (B, 1, D, H + 12, W + 12) →
    (B, H, W). Built by :func:`fold_batchnorm`; has no dropout and no BN.
    """

    #: Ready for inference as it is (no BN to fold, no dropout); see :func:`predict_confidence`.
    is_folded = True

    def __init__(self, net: CVANet) -> None:
        super().__init__()
        self.max_disparity = net.max_disparity
        self.fusion = nn.ModuleList()
        self.depth = nn.ModuleList()
        with torch.no_grad():
            in_scale, in_shift = _bn_affine(net.fusion.input_bn)
            pairs = zip(net.fusion.convs, net.fusion.norms, strict=True)
            for index, (conv, norm) in enumerate(pairs):
                assert isinstance(conv, nn.Conv3d)
                weight = conv.weight.double()
                bias = conv_bias(conv).double()
                if index == 0:
                    # The first convolution is unpadded, so the input BN x → a·x + c moves into
                    # it exactly: w' = a·w, b' = b + c·Σw.
                    bias = bias + in_shift[0] * weight.sum(dim=(1, 2, 3, 4))
                    weight = weight * in_scale[0]
                self.fusion.append(_folded_copy(conv, weight, bias, norm))
            for conv, norm in zip(net.depth.convs, net.depth.norms, strict=True):
                self.depth.append(_folded_copy(conv, None, None, norm, as_1d=True))
            self.fc1 = _folded_copy(net.classification.fc1, None, None, None, as_1d=True)
            self.fc2 = _folded_copy(net.classification.fc2, None, None, None, as_1d=True)
        self.eval()

    def fusion_features(self, volume: torch.Tensor) -> torch.Tensor:
        """The neighbourhood fusion: (B, 1, D, H + 12, W + 12) → (B, 32, D − 12, H, W).

        With :meth:`head_logits` this splits the network at the per-pixel cost curves, so
        that :mod:`cva_confidence_ros.model.sparse` can fuse densely and classify only a
        subset of the pixels.

        Raises:
            InputError: ``volume`` not a floating-point (B, 1, D, ≥13, ≥13) tensor with this D.
        """
        check_volume_tensor(volume, self.max_disparity)
        x = volume.to(next(self.parameters()).dtype)  # a float64 or float16 volume, as unfolded
        for conv in self.fusion:
            # In place on the fresh output: two live activations, not three.
            x = F.relu(conv(x), inplace=True)
        return x

    def head_logits(self, curves: torch.Tensor) -> torch.Tensor:
        """Depth processing and classification of fused curves: (N, 32, D − 12) → (N,) logits.

        The depth convolutions zero-pad each curve by up to 63 values (kernel 64), which at
        D = 64 more than doubles it: the pixels go through in chunks whose padded curves are
        no larger than ``curves``, so the head keeps to the memory the fusion needed (all N
        at once, it took 1.6 times the tile budget).
        """
        count, _, depth = curves.shape
        chunk = max(1, count * depth // (depth + max(DEPTH_KERNELS) - 1))
        if count <= chunk or torch.jit.is_tracing():
            # (a traced graph, e.g. the ONNX export, must keep N dynamic)
            return self._head_chunk(curves)
        return torch.cat(
            [self._head_chunk(curves[start : start + chunk]) for start in range(0, count, chunk)]
        )

    def _head_chunk(self, curves: torch.Tensor) -> torch.Tensor:
        x = curves
        for conv, k in zip(self.depth, DEPTH_KERNELS, strict=True):
            x = F.relu(conv(F.pad(x, ((k - 1) // 2, k // 2))))
        return self.fc2(F.relu(self.fc1(x))).reshape(-1)

    def forward_logits(self, volume: torch.Tensor) -> torch.Tensor:
        """(B, 1, D, H + 12, W + 12) float32 → (B, H, W) float32 logits."""
        x = self.fusion_features(volume)
        batch, channels, depth, height, width = x.shape
        # Forward only, Conv1d over (N, C, D') beats the training layout's Conv2d by ~1.5×.
        x = x.permute(0, 3, 4, 1, 2).reshape(batch * height * width, channels, depth)
        return self.head_logits(x).reshape(batch, height, width)

    def forward(self, volume: torch.Tensor) -> torch.Tensor:
        """Confidence in (0, 1), (B, H, W)."""
        return confidence_from_logits(self.forward_logits(volume))


def _bn_affine(norm: nn.Module) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-channel (scale, shift) of a BN in eval mode, float64."""
    assert isinstance(norm, nn.modules.batchnorm._BatchNorm)
    assert norm.running_var is not None and norm.running_mean is not None
    scale = norm.weight.double() / torch.sqrt(norm.running_var.double() + norm.eps)
    shift = norm.bias.double() - norm.running_mean.double() * scale
    return scale, shift


def _folded_copy(
    conv: nn.Module,
    weight: torch.Tensor | None,
    bias: torch.Tensor | None,
    norm: nn.Module | None,
    as_1d: bool = False,
) -> nn.modules.conv._ConvNd:
    """A new convolution like ``conv`` whose weights include the BN ``norm`` after it.

    With ``as_1d`` a (k, 1)-kernel ``Conv2d`` becomes the equivalent k-kernel ``Conv1d``.
    """
    assert isinstance(conv, (nn.Conv2d, nn.Conv3d))
    weight = conv.weight.double() if weight is None else weight
    bias = conv_bias(conv).double() if bias is None else bias
    device = conv.weight.device
    new: nn.modules.conv._ConvNd
    if as_1d:
        weight = weight[..., 0]
        new = nn.Conv1d(conv.in_channels, conv.out_channels, conv.kernel_size[0], device=device)
    else:
        assert isinstance(conv, nn.Conv3d)
        kernel = cast(tuple[int, int, int], conv.kernel_size)
        new = nn.Conv3d(conv.in_channels, conv.out_channels, kernel, device=device)
    if norm is not None:
        scale, shift = _bn_affine(norm)
        weight = weight * scale.reshape(-1, *([1] * (weight.ndim - 1)))
        bias = bias * scale + shift
    new.weight.copy_(weight.float())
    conv_bias(new).copy_(bias.float())
    new.requires_grad_(False)
    return new


def fold_batchnorm(net: CVANet) -> FoldedCVANet:
    """Return an inference-only copy of ``net`` with its batch normalisations folded in.

    The result equals ``net.eval()`` within float32 rounding (about 1e-6 on the confidence);
    ``net`` itself is not changed.
    """
    if not isinstance(net, CVANet):
        raise ConfigError(f'expected a CVANet; got {type(net).__name__}')
    return FoldedCVANet(net)


@contextlib.contextmanager
def _eval_mode(net: nn.Module) -> Iterator[nn.Module]:
    was_training = net.training
    net.eval()
    try:
        yield net
    finally:
        net.train(was_training)


def _unwrap(net: nn.Module) -> nn.Module:
    """The model inside a DistributedDataParallel / DataParallel wrapper."""
    return net.module if hasattr(net, 'module') and isinstance(net.module, nn.Module) else net


def _check_volume(net: nn.Module, cost_volume: np.ndarray) -> np.ndarray:
    if not isinstance(cost_volume, np.ndarray):
        raise InputError(
            f'cost_volume must be a numpy array (D, H, W); got {type(cost_volume).__name__}'
        )
    # The values the network gets: a masked array's mask hid NaN from the checks below.
    cost_volume = np.asarray(cost_volume)
    if cost_volume.ndim != 3 or min(cost_volume.shape) < 1:
        raise InputError(f'cost_volume must have shape (D, H, W); got {cost_volume.shape}')
    if not np.issubdtype(cost_volume.dtype, np.floating):
        raise InputError(f'cost_volume must be floating point in [0, 1]; got {cost_volume.dtype}')
    depth = getattr(net, 'max_disparity', None)
    if not is_int(depth):
        raise ConfigError(
            'expected a cost-volume network that says its depth (max_disparity: CVANet, a '
            f'folded network, CVA-Net-Lite or -Fast); got {type(net).__name__}'
        )
    if cost_volume.shape[0] != depth:
        raise InputError(
            f'the network was built for cost volumes of depth D = {depth}; '
            f'got a volume of depth {cost_volume.shape[0]} (shape {cost_volume.shape})'
        )
    low, high = float(np.min(cost_volume)), float(np.max(cost_volume))
    if not (math.isfinite(low) and math.isfinite(high)):
        raise InputError('cost_volume contains NaN or infinite values; expected [0, 1]')
    if low < -_VALUE_TOLERANCE or high > 1.0 + _VALUE_TOLERANCE:
        raise InputError(
            f'cost_volume must be normalised to [0, 1]; got values in [{low:.4g}, {high:.4g}]'
        )
    # As it is, not copied to float32: tiles and extracts are read from it one at a time and
    # converted then (a float64 volume's whole float32 copy was 4 bytes a voxel beyond the
    # tile budget, as was a non-contiguous one's).
    return cost_volume


def pad_cost_volume(cost_volume: np.ndarray, dtype: np.dtype | type = np.float32) -> np.ndarray:
    """Zero-pad a (D, H, W) volume by 6 px on each image side → (D, H + 12, W + 12)."""
    return np.pad(cost_volume.astype(dtype, copy=False), ((0, 0), (PAD, PAD), (PAD, PAD)))


def _padded_tile(volume: np.ndarray, y0: int, y1: int, x0: int, x1: int) -> torch.Tensor:
    """Output rows y0:y1, columns x0:x1 of a (D, H, W) volume with their 6-px halo:
    ``pad_cost_volume(volume)[:, y0 : y1 + 12, x0 : x1 + 12]`` as a contiguous float32 CPU
    tensor, read from the unpadded volume (zeros outside the image).

    The whole zero-padded copy of the volume (4 bytes a voxel) lay outside the tile budget:
    CVA-Net-Fast needed ≈ 5 bytes a voxel on top of the budget even at 16 MB.
    """
    depth, height, width = volume.shape
    tile = torch.empty((depth, y1 - y0 + 2 * PAD, x1 - x0 + 2 * PAD), dtype=torch.float32)
    top, bottom = max(0, y0 - PAD), min(height, y1 + PAD)
    left, right = max(0, x0 - PAD), min(width, x1 + PAD)
    # Where the image part lies in the tile; the margins around it are zeroed.
    r0, c0 = top - (y0 - PAD), left - (x0 - PAD)
    r1, c1 = r0 + bottom - top, c0 + right - left
    source = volume[:, top:bottom, left:right]
    if source.dtype in _TORCH_COPIES and source.dtype.isnative and source.flags.writeable:
        # torch's copy runs on every thread: half the time of numpy's at 640×480
        tile[:, r0:r1, c0:c1].copy_(torch.from_numpy(source))
    else:  # a read-only, byte-swapped or long-double volume, which torch cannot wrap
        tile[:, r0:r1, c0:c1].numpy()[...] = source
    tile[:, :r0] = 0.0
    tile[:, r1:] = 0.0
    tile[:, r0:r1, :c0] = 0.0
    tile[:, r0:r1, c1:] = 0.0
    return tile


def _extract_batch(volume: np.ndarray, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
    """The 13×13×D extracts around the pixels (ys, xs) of a (D, H, W) volume, (N, 1, D, 13, 13)
    float32: those of :func:`pad_cost_volume`'s copy, read from the unpadded volume.

    Pixels at least 6 px inside the border are read through a window view of the volume; the
    others from clipped indices, with zeros where the window leaves the image.
    """
    depth, height, width = volume.shape
    inside = (ys >= PAD) & (ys < height - PAD) & (xs >= PAD) & (xs < width - PAD)
    if ys.size and inside.all():
        windows = sliding_window_view(volume, (PATCH_SIZE, PATCH_SIZE), axis=(1, 2))
        # (H − 12, W − 12, D, 13, 13) indexed → (n, D, 13, 13) in one copy
        batch = np.moveaxis(windows, 0, 2)[ys - PAD, xs - PAD][:, None]
        return np.ascontiguousarray(batch, dtype=np.float32)
    out = np.empty((ys.size, 1, depth, PATCH_SIZE, PATCH_SIZE), dtype=np.float32)
    if inside.any():
        out[inside] = _extract_batch(volume, ys[inside], xs[inside])
    border = ~inside
    offsets = np.arange(-PAD, PAD + 1)
    rows, columns = ys[border, None] + offsets, xs[border, None] + offsets  # (m, 13) each
    values = volume[
        :, np.clip(rows, 0, height - 1)[:, :, None], np.clip(columns, 0, width - 1)[:, None, :]
    ]  # (D, m, 13, 13)
    outside = ((rows < 0) | (rows >= height))[:, :, None] | (
        (columns < 0) | (columns >= width)
    )[:, None, :]
    out[border, 0] = np.where(outside, np.float32(0.0), values).swapaxes(0, 1)
    return out


def _check_tile_budget(tile_budget_mb: object) -> float:
    """``tile_budget_mb`` as a float; ConfigError unless it is a finite real number > 0."""
    budget = math.inf
    if is_real(tile_budget_mb):
        try:
            budget = float(cast('float | np.integer', tile_budget_mb))
        except OverflowError:  # an int beyond float (2**2000): math.isfinite raised it bare
            budget = math.inf
    if not is_real(tile_budget_mb) or not (math.isfinite(budget) and budget > 0):
        raise ConfigError(
            f'tile_budget_mb must be a finite number > 0 (megabytes); '
            f'got {type(tile_budget_mb).__name__} {tile_budget_mb!r}'
        )
    return budget


def _check_batch_size(batch_size: object) -> int:
    """``batch_size`` as an int; ConfigError unless it is an integer >= 1 (not a bool)."""
    size = cast('int | np.integer', batch_size)  # only used once is_int holds
    if (
        not is_int(batch_size)
        or size < 1
    ):
        raise ConfigError(
            f'batch_size must be an integer >= 1; got {type(batch_size).__name__} {batch_size!r}'
        )
    return int(size)


def tile_shape(
    height: int,
    width: int,
    max_disparity: int,
    tile_budget_mb: float,
    activations_per_pixel: int | None = None,
) -> tuple[int, int]:
    """Output tile (rows, columns) whose activations fit ``tile_budget_mb`` megabytes.

    The widest activation has ``activations_per_pixel`` float32 values per pixel of the padded
    tile (default CVA-Net's 32-channel fusion output, 32 · D), over
    (rows + 12) · (columns + 12) pixels, counted :data:`_LIVE_COPIES` times. Networks give
    their own figure by :func:`activations_per_pixel`. The smallest tile is 1 × 1: a budget
    below the need of its 13 × 13 padded pixels gives 1 × 1 tiles, which exceed it.

    Raises:
        ConfigError: ``tile_budget_mb`` not a finite number > 0, or ``height``, ``width``,
            ``max_disparity`` or ``activations_per_pixel`` not an integer >= 1.
    """
    tile_budget_mb = _check_tile_budget(tile_budget_mb)
    sizes = {'height': height, 'width': width, 'max_disparity': max_disparity}
    if activations_per_pixel is not None:
        sizes['activations_per_pixel'] = activations_per_pixel
    for name, size in sizes.items():
        # A height of 0 or -3 gave a (0, 1) or (-3, 1) tile; 2.5 values per pixel passed.
        if not is_int(size) or size < 1:
            raise ConfigError(
                f'{name} must be an integer >= 1; got {type(size).__name__} {size!r}'
            )
    values = 32 * max_disparity if activations_per_pixel is None else activations_per_pixel
    per_pixel = 4 * values * _LIVE_COPIES
    # From (max(H, W) + 12)² pixels on the whole image is one tile; capping there keeps a
    # budget near the float maximum (× 1e6 = inf) from failing in int().
    whole = (max(height, width) + 2 * PAD) ** 2
    padded_pixels = max(1, int(min(tile_budget_mb * 1e6 / per_pixel, whole)))
    side = max(1, int(math.sqrt(padded_pixels)) - 2 * PAD)
    columns = min(width, side)
    rows = max(1, padded_pixels // (columns + 2 * PAD) - 2 * PAD)
    return min(height, rows), columns


def activations_per_pixel(net: nn.Module, max_disparity: int) -> int:
    """Float32 values per image pixel of the widest activation of ``net`` at depth D.

    Uses the network's ``activations_per_pixel`` attribute when it has one (CVA-Net-Lite),
    else CVA-Net's 32 · D.
    """
    own = getattr(_unwrap(net), 'activations_per_pixel', None)
    return int(own) if isinstance(own, int) and own >= 1 else 32 * int(max_disparity)


def predict_confidence(
    net: nn.Module,
    cost_volume: np.ndarray,
    device: str | torch.device = 'cpu',
    tile_budget_mb: float = 512.0,
    fold_bn: bool = True,
) -> np.ndarray:
    """Confidence of every pixel of a whole cost volume, processed in memory-bounded tiles.

    The volume is zero-padded by 6 px on each image side, so border pixels get a value too.
    Tiles overlap by 12 px of input and give exactly the whole-image result (up to float32
    rounding, < 1e-5).

    Args:
        net: A trained :class:`CVANet` (its train/eval mode is left as it was), or a
            :class:`FoldedCVANet` from :func:`fold_batchnorm` (used as it is; fold once and
            reuse it when processing many frames).
        cost_volume: (D, H, W) float normalised cost volume, values in [0, 1], with
            D = ``net.max_disparity``.
        device: ``'cpu'``, ``'cuda'`` or ``'auto'``.
        tile_budget_mb: Memory budget of one tile's activations, in megabytes.
        fold_bn: Merge the batch normalisations into the convolutions first (faster).

    Returns:
        (H, W) float32 confidence in (0, 1).

    Raises:
        InputError: Wrong shape, depth, dtype or values of ``cost_volume``.
        ConfigError: Bad device, ``tile_budget_mb`` not a finite number > 0, or a network
            without ``max_disparity``.
    """
    net = _unwrap(net)
    volume = _check_volume(net, cost_volume)
    tile_budget_mb = _check_tile_budget(tile_budget_mb)
    torch_device = resolve_device(device)
    depth, height, width = volume.shape
    rows, columns = tile_shape(
        height, width, depth, tile_budget_mb, activations_per_pixel(net, depth)
    )
    result = np.empty((height, width), dtype=np.float32)
    with contextlib.ExitStack() as stack:
        stack.enter_context(torch.inference_mode())
        model = _inference_model(net, torch_device, fold_bn, stack)
        dtype = _input_dtype(model)
        for y0 in range(0, height, rows):
            y1 = min(height, y0 + rows)
            for x0 in range(0, width, columns):
                x1 = min(width, x0 + columns)
                tile = _padded_tile(volume, y0, y1, x0, x1).to(torch_device, dtype)[None, None]
                result[y0:y1, x0:x1] = model(tile)[0].float().cpu().numpy()
                del tile  # not alive while the next one is built
    return result


def _inference_model(
    net: nn.Module, device: torch.device, fold_bn: bool, stack: contextlib.ExitStack
) -> nn.Module:
    """The module to run: ``net`` itself if it is already folded (``is_folded``), else its
    folded copy (CVA-Net, or any other cost-volume network with a ``fold_batchnorm()``
    method returning an inference module), else ``net`` in eval mode (``fold_bn=False``)."""
    if getattr(net, 'is_folded', False):
        return net.to(device)
    if fold_bn:
        fold = getattr(net, 'fold_batchnorm', None)
        if not callable(fold):
            raise ConfigError(
                f'expected a CVANet, a folded network or one with fold_batchnorm(); '
                f'got {type(net).__name__}'
            )
        return fold().to(device)
    if not same_device(next(net.parameters()).device, device):
        raise ConfigError(
            f'fold_bn=False runs the network where it lies ({next(net.parameters()).device}); '
            f'got device {device}'
        )
    return stack.enter_context(_eval_mode(net))


def same_device(a: torch.device, b: torch.device) -> bool:
    """Whether two devices are one: ``cuda`` is the current CUDA device (a tensor there says
    ``cuda:0``, and ``torch.device('cuda') != torch.device('cuda:0')``)."""

    def index(device: torch.device) -> int | None:
        if device.type == 'cuda' and device.index is None:
            return torch.cuda.current_device()
        return device.index

    return a.type == b.type and index(a) == index(b)


def _input_dtype(model: nn.Module) -> torch.dtype:
    """The dtype the module's input must have: that of its parameters (float32 for the folded
    networks; a network run as it is with ``fold_bn=False`` may be float64 or half)."""
    parameter = next(model.parameters(), None)
    return torch.float32 if parameter is None else parameter.dtype


def predict_confidence_at(
    net: nn.Module,
    cost_volume: np.ndarray,
    ys: np.ndarray,
    xs: np.ndarray,
    device: str | torch.device = 'cpu',
    batch_size: int = 512,
    fold_bn: bool = True,
) -> np.ndarray:
    """Confidence of the given pixels only, from batched 13×13×D extracts.

    Each pixel costs a full 13×13 fusion (about ten times a pixel of
    :func:`predict_confidence`), so this pays off for sparse subsets only.

    Args:
        net: A trained :class:`CVANet` or a :class:`FoldedCVANet`.
        cost_volume: (D, H, W) float normalised cost volume in [0, 1], D = ``net.max_disparity``.
        ys: (N,) integer rows in [0, H).
        xs: (N,) integer columns in [0, W).
        device: ``'cpu'``, ``'cuda'`` or ``'auto'``.
        batch_size: Extracts per forward pass.
        fold_bn: Merge the batch normalisations into the convolutions first.

    Returns:
        (N,) float32 confidence in (0, 1), equal to ``predict_confidence(...)[ys, xs]``.

    Raises:
        InputError: Bad volume, or coordinates of the wrong shape or outside the image.
        ConfigError: Bad device, ``batch_size`` not an integer >= 1, or a network without
            ``max_disparity``.
    """
    net = _unwrap(net)
    volume = _check_volume(net, cost_volume)
    ys, xs = _check_pixels(ys, xs, volume.shape[1:])
    batch_size = _check_batch_size(batch_size)
    torch_device = resolve_device(device)
    result = np.empty(len(ys), dtype=np.float32)
    with contextlib.ExitStack() as stack:
        stack.enter_context(torch.inference_mode())
        model = _inference_model(net, torch_device, fold_bn, stack)
        dtype = _input_dtype(model)
        for start in range(0, len(ys), batch_size):
            stop = min(len(ys), start + batch_size)
            batch = _extract_batch(volume, ys[start:stop], xs[start:stop])
            extracts = torch.from_numpy(batch).to(torch_device, dtype)
            result[start:stop] = model(extracts)[:, 0, 0].float().cpu().numpy()
    return result


def _check_pixels(
    ys: np.ndarray, xs: np.ndarray, shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    ys, xs = np.asarray(ys), np.asarray(xs)
    if ys.ndim != 1 or ys.shape != xs.shape:
        raise InputError(
            f'ys and xs must be (N,) arrays of equal length; got {ys.shape}, {xs.shape}'
        )
    if ys.size and not (
        np.issubdtype(ys.dtype, np.integer) and np.issubdtype(xs.dtype, np.integer)
    ):
        raise InputError(f'ys and xs must be integer pixel indices; got {ys.dtype}, {xs.dtype}')
    ys, xs = ys.astype(np.intp), xs.astype(np.intp)
    height, width = shape
    if ys.size and (ys.min() < 0 or ys.max() >= height or xs.min() < 0 or xs.max() >= width):
        raise InputError(
            f'pixel indices must lie in [0, {height}) × [0, {width}); got rows '
            f'[{ys.min()}, {ys.max()}] and columns [{xs.min()}, {xs.max()}]'
        )
    return ys, xs

"""The paper's comparison networks, which learn confidence from the disparity map (and image).

* :class:`CCNN` (Poggi & Mattoccia, BMVC 2016): a 9×9 disparity patch → four 3×3
  convolutions with 64 filters (ReLU, no padding) → two 1×1 layers of 100 (ReLU) → 1 output
  (sigmoid). The disparity is divided by the maximum disparity D.
* :class:`LFN` (Fu et al. 2017, late fusion): the CCNN tower on the disparity and a second
  tower of the same shape on the reference image, concatenated, then 1×1 layers of 100, 100, 1.
* :class:`LGCNet` (Tosi et al., ECCV 2018): a local network (:class:`CCNN`), ConfNet
  (:class:`ConfNet`, an encoder–decoder on disparity and image) and a fusion network with
  three towers (disparity, local confidence, global confidence; four 3×3 convolutions of 64
  each) and 1×1 layers of 100, 100, 1.

All of them are fully convolutional: a patch gives the confidence of its centre pixel, a
whole (padded) image gives the whole confidence map in one pass.

Inputs (:func:`network_inputs`): disparity ``d / D`` (invalid NaN disparities are filled with 0
before the division, i.e. "disparity 0", the value a matcher gives where it found nothing) and
the left image as one grey channel in [0, 1]. Choices made where the papers leave freedom or
the CPU budget asks for one (also written on every model card):

* Grey image instead of RGB for LFN and ConfNet: the training data mixes grey (KITTI 2012
  ``image_0``, Middlebury 2001) and colour pairs, and the node also runs on mono cameras.
* Border handling: the inputs of a whole image are padded by edge replication (4 px for
  CCNN/LFN, 8 px for LGC-Net's local + fusion stack), and training crops are cut from scenes
  padded in exactly the same way, so training and inference see the same borders.
* ConfNet as in Tosi et al.'s description: one 3×3 convolution of 32 filters per input,
  concatenated; four encoders (3×3 convolution of 64/128/256/512 + ReLU + 2×2 max pooling);
  four decoders (3×3 stride-2 transposed convolution to 256/128/64/32, concatenation with the
  encoder feature map of the same resolution (the last one with the 64-channel input
  features), 3×3 convolution + ReLU); a 3×3 convolution to 1 logit. No batch normalisation:
  on CPU the training batches are one or two crops, too few for stable batch statistics.
  Inputs are padded (edge replication, bottom/right) to a multiple of 16 and the output
  cropped back.
* LGC-Net's local network is CCNN (Tosi et al. evaluate both CCNN and LFN; CCNN keeps the
  local part independent of the image, which ConfNet already sees).
* Initialisation: PyTorch's default (Kaiming-uniform) for every layer.
"""

from __future__ import annotations

from collections.abc import Mapping
import math
from typing import Any, cast

import numpy as np
import torch
from torch import nn
import torch.nn.functional as F

from cva_confidence_ros.checks import is_int, is_real
from cva_confidence_ros.devices import resolve_device
from cva_confidence_ros.errors import ConfigError, InputError, ModelError
from cva_confidence_ros.model.inference import same_device
from cva_confidence_ros.model.weights import ARCHITECTURES

__all__ = [
    'BASELINE_ARCHS',
    'CCNN',
    'CONFNET_FACTOR',
    'LFN',
    'MARGIN',
    'ConfNet',
    'FusionNet',
    'LGCNet',
    'ccnn_parameter_count',
    'confnet_parameter_count',
    'fusion_parameter_count',
    'lfn_parameter_count',
    'lgcnet_parameter_count',
    'network_inputs',
    'predict_disparity_confidence',
]

#: 3×3 convolutions in a tower; each removes one pixel on every side (no padding).
TOWER_CONVS = 4
TOWER_FILTERS = 64
HEAD_UNITS = 100
#: Pixels a tower consumes on each side: a 9×9 patch gives one output.
TOWER_MARGIN = TOWER_CONVS
#: Border a training scene is padded by: LGC-Net's local tower feeds its fusion tower.
MARGIN = 2 * TOWER_MARGIN
#: ConfNet pools four times by 2: its input sides must be multiples of 16.
CONFNET_FACTOR = 16
CONFNET_WIDTH = 32


def _conv_count(c_in: int, c_out: int, k: int) -> int:
    return c_in * c_out * k * k + c_out


def _tower_count(c_in: int) -> int:
    return _conv_count(c_in, TOWER_FILTERS, 3) + (TOWER_CONVS - 1) * _conv_count(
        TOWER_FILTERS, TOWER_FILTERS, 3
    )


def _head_count(c_in: int) -> int:
    return (
        _conv_count(c_in, HEAD_UNITS, 1)
        + _conv_count(HEAD_UNITS, HEAD_UNITS, 1)
        + _conv_count(HEAD_UNITS, 1, 1)
    )


def ccnn_parameter_count() -> int:
    """Weights + biases of :class:`CCNN`: one tower on 1 channel and the 1×1 head (128,125)."""
    return _tower_count(1) + _head_count(TOWER_FILTERS)


def lfn_parameter_count() -> int:
    """Weights + biases of :class:`LFN`: two towers on 1 channel, head on 128 channels."""
    return 2 * _tower_count(1) + _head_count(2 * TOWER_FILTERS)


def confnet_parameter_count(width: int = CONFNET_WIDTH) -> int:
    """Weights + biases of :class:`ConfNet` with input features of ``width`` per input."""
    w = width
    count = 2 * _conv_count(1, w, 3)
    encoders = [2 * w, 4 * w, 8 * w, 16 * w]
    c_in = 2 * w
    for c_out in encoders:
        count += _conv_count(c_in, c_out, 3)
        c_in = c_out
    # Decoder k: transposed conv to out_k, concatenated with the skip of the same resolution.
    skips = [16 * w, 8 * w, 4 * w, 2 * w]
    outs = [8 * w, 4 * w, 2 * w, w]
    for out, skip in zip(outs, skips, strict=True):
        count += _conv_count(c_in, out, 3) + _conv_count(out + skip, out, 3)
        c_in = out
    return count + _conv_count(w, 1, 3)


def fusion_parameter_count() -> int:
    """Weights + biases of LGC-Net's fusion network: three towers, head on 192 channels."""
    return 3 * _tower_count(1) + _head_count(3 * TOWER_FILTERS)


def lgcnet_parameter_count(width: int = CONFNET_WIDTH) -> int:
    """Weights + biases of :class:`LGCNet`: CCNN + ConfNet + fusion."""
    return ccnn_parameter_count() + confnet_parameter_count(width) + fusion_parameter_count()


def _tower(c_in: int) -> nn.Sequential:
    layers: list[nn.Module] = []
    for index in range(TOWER_CONVS):
        layers += [nn.Conv2d(c_in if index == 0 else TOWER_FILTERS, TOWER_FILTERS, 3), nn.ReLU()]
    return nn.Sequential(*layers)


def _head(c_in: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(c_in, HEAD_UNITS, 1),
        nn.ReLU(),
        nn.Conv2d(HEAD_UNITS, HEAD_UNITS, 1),
        nn.ReLU(),
        nn.Conv2d(HEAD_UNITS, 1, 1),
    )


def _check_size(name: str, value: object) -> int:
    """``value`` as an int, or :class:`ConfigError` unless it is an integer >= 1."""
    # int() truncated 16.7 to 16 (a disparity scale other than the one asked for), took True
    # as 1 and parsed '64'; a 0 or negative size failed later, at the first input.
    if not is_int(value) or int(cast('int', value)) < 1:
        raise ConfigError(
            f'{name} must be an integer >= 1; got {type(value).__name__} {value!r}'
        )
    return int(cast('int', value))


def _as_weights(module: nn.Module, *planes: torch.Tensor) -> list[torch.Tensor]:
    """The input planes in the dtype of ``module``'s weights (a float64 or float16 input stopped
    at the first convolution with "Input type ... and bias type ... should be the same")."""
    dtype = next(module.parameters()).dtype
    return [plane.to(dtype) for plane in planes]


def _check_pair(
    disparity: torch.Tensor, image: torch.Tensor, min_side: int, name: str = 'image'
) -> None:
    if disparity.ndim != 4 or disparity.shape[1] != 1:
        raise InputError(f'expected disparity (B, 1, H, W); got {tuple(disparity.shape)}')
    for plane, label in ((disparity, 'disparity'), (image, name)):
        if not plane.dtype.is_floating_point:
            raise InputError(
                f'expected a floating-point {label} (normalised as network_inputs does); '
                f'got {plane.dtype}'
            )
    if image.shape != disparity.shape:
        raise InputError(
            f'expected {name} of the disparity shape {tuple(disparity.shape)}; '
            f'got {tuple(image.shape)}'
        )
    if min(disparity.shape[2:]) < min_side:
        raise InputError(f'inputs must be at least {min_side} px on each side; got '
                         f'{tuple(disparity.shape[2:])}')


class CCNN(nn.Module):
    """CCNN: confidence from a 9×9 patch of the normalised disparity map.

    ``forward_logits(disparity, image)`` maps (B, 1, h + 8, w + 8) inputs to (B, 1, h, w)
    logits; the image is accepted and ignored so that every baseline has one signature.
    Floating-point inputs of another dtype are converted to the weights' dtype (as every
    network of the package does); integer inputs are an :class:`InputError`.

    Raises:
        ConfigError: ``max_disparity`` not an integer >= 1 (LFN and LGC-Net alike; for
            LGC-Net also a ``confnet_width`` that is not).
    """

    arch = 'ccnn'
    margin = TOWER_MARGIN

    def __init__(self, max_disparity: int) -> None:
        super().__init__()
        self.max_disparity = _check_size('max_disparity', max_disparity)
        self.tower = _tower(1)
        self.head = _head(TOWER_FILTERS)

    def forward_logits(self, disparity: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
        """Logits of the centre pixels of (B, 1, h + 8, w + 8) inputs: (B, 1, h, w)."""
        _check_pair(disparity, image, 2 * TOWER_MARGIN + 1)
        (disparity,) = _as_weights(self, disparity)
        return self.head(self.tower(disparity))

    def forward(self, disparity: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
        """Confidence in (0, 1), shape as :meth:`forward_logits`."""
        return torch.sigmoid(self.forward_logits(disparity, image))

    def dense_confidence(self, disparity: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
        """(B, 1, H, W) confidence of whole (B, 1, H, W) inputs (edge-replicated borders)."""
        _check_pair(disparity, image, 1)
        pad = (self.margin,) * 4
        return self(F.pad(disparity, pad, mode='replicate'), F.pad(image, pad, mode='replicate'))


class LFN(CCNN):
    """LFN: late fusion of a disparity tower and a reference-image tower (9×9 patches)."""

    arch = 'lfn'

    def __init__(self, max_disparity: int) -> None:
        nn.Module.__init__(self)
        self.max_disparity = _check_size('max_disparity', max_disparity)
        self.tower = _tower(1)
        self.image_tower = _tower(1)
        self.head = _head(2 * TOWER_FILTERS)

    def forward_logits(self, disparity: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
        """Logits of the centre pixels of (B, 1, h + 8, w + 8) inputs: (B, 1, h, w)."""
        _check_pair(disparity, image, 2 * TOWER_MARGIN + 1)
        disparity, image = _as_weights(self, disparity, image)
        return self.head(torch.cat([self.tower(disparity), self.image_tower(image)], dim=1))


class ConfNet(nn.Module):
    """Tosi et al.'s ConfNet: encoder–decoder on disparity and image (global context).

    ``forward_logits`` takes (B, 1, H, W) inputs with H, W multiples of 16 and gives
    (B, 1, H, W) logits; :meth:`dense_confidence` pads any size.
    """

    def __init__(self, width: int = CONFNET_WIDTH) -> None:
        super().__init__()
        w = _check_size('ConfNet width', width)
        self.width = w
        self.disparity_in = nn.Conv2d(1, w, 3, padding=1)
        self.image_in = nn.Conv2d(1, w, 3, padding=1)
        chans = [2 * w, 2 * w, 4 * w, 8 * w, 16 * w]
        self.encoders = nn.ModuleList(
            nn.Conv2d(chans[i], chans[i + 1], 3, padding=1) for i in range(4)
        )
        outs = [8 * w, 4 * w, 2 * w, w]
        skips = [16 * w, 8 * w, 4 * w, 2 * w]
        ins = [16 * w, *outs[:-1]]
        self.upsamples = nn.ModuleList(
            nn.ConvTranspose2d(c_in, c_out, 3, stride=2, padding=1, output_padding=1)
            for c_in, c_out in zip(ins, outs, strict=True)
        )
        self.decoders = nn.ModuleList(
            nn.Conv2d(c_out + skip, c_out, 3, padding=1)
            for c_out, skip in zip(outs, skips, strict=True)
        )
        self.out = nn.Conv2d(w, 1, 3, padding=1)

    def forward_logits(self, disparity: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
        """(B, 1, H, W) logits of inputs whose sides are multiples of 16."""
        _check_pair(disparity, image, 1)
        height, width = disparity.shape[2:]
        if height % CONFNET_FACTOR or width % CONFNET_FACTOR:
            raise InputError(
                f'ConfNet inputs must have sides that are multiples of {CONFNET_FACTOR}; '
                f'got {height}×{width}'
            )
        disparity, image = _as_weights(self, disparity, image)
        x = torch.cat(
            [F.relu(self.disparity_in(disparity)), F.relu(self.image_in(image))], dim=1
        )
        skips = [x]
        for encoder in self.encoders:
            x = F.relu(encoder(x))
            skips.append(x)
            x = F.max_pool2d(x, 2)
        # skips: input features (full), enc1 (full), enc2 (1/2), enc3 (1/4), enc4 (1/8);
        # decoder k upsamples to the resolution of enc(5-k) and takes it as skip (the last one
        # the input features, as enc1 has the same resolution but is already in the path).
        for k, (upsample, decoder) in enumerate(zip(self.upsamples, self.decoders, strict=True)):
            x = F.relu(upsample(x))
            skip = skips[4 - k] if k < 3 else skips[0]
            x = F.relu(decoder(torch.cat([x, skip], dim=1)))
        return self.out(x)

    def dense_confidence(self, disparity: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
        """(B, 1, H, W) confidence of whole inputs, padded (edge) to multiples of 16."""
        _check_pair(disparity, image, 1)
        height, width = disparity.shape[2:]
        pad = (0, -width % CONFNET_FACTOR, 0, -height % CONFNET_FACTOR)
        logits = self.forward_logits(
            F.pad(disparity, pad, mode='replicate'), F.pad(image, pad, mode='replicate')
        )
        return torch.sigmoid(logits[:, :, :height, :width])


class FusionNet(nn.Module):
    """LGC-Net's final network: towers on disparity, local and global confidence, 1×1 head."""

    def __init__(self) -> None:
        super().__init__()
        self.disparity_tower = _tower(1)
        self.local_tower = _tower(1)
        self.global_tower = _tower(1)
        self.head = _head(3 * TOWER_FILTERS)

    def forward_logits(
        self, disparity: torch.Tensor, local: torch.Tensor, global_: torch.Tensor
    ) -> torch.Tensor:
        """(B, 1, h, w) logits of three (B, 1, h + 8, w + 8) inputs."""
        _check_pair(disparity, local, 2 * TOWER_MARGIN + 1, 'local confidence')
        _check_pair(disparity, global_, 2 * TOWER_MARGIN + 1, 'global confidence')
        disparity, local, global_ = _as_weights(self, disparity, local, global_)
        features = [
            self.disparity_tower(disparity),
            self.local_tower(local),
            self.global_tower(global_),
        ]
        return self.head(torch.cat(features, dim=1))


class LGCNet(nn.Module):
    """LGC-Net: local (CCNN) and global (ConfNet) confidence, fused by :class:`FusionNet`.

    Trained in two stages as Tosi et al. do: CCNN and ConfNet first, then the fusion network
    with both frozen (``cva-train --arch lgcnet`` runs both stages).
    """

    arch = 'lgcnet'
    margin = MARGIN

    def __init__(self, max_disparity: int, confnet_width: int = CONFNET_WIDTH) -> None:
        super().__init__()
        self.max_disparity = _check_size('max_disparity', max_disparity)
        self.local = CCNN(max_disparity)
        self.confnet = ConfNet(confnet_width)
        self.fusion = FusionNet()

    def parts(self, disparity: torch.Tensor, image: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Local and global confidence of whole (B, 1, H, W) inputs, padded for the fusion.

        Returns:
            ``(disparity4, local4, global4)``: each (B, 1, H + 8, W + 8), i.e. the fusion
            network's inputs (disparity edge-padded by 4, CCNN on the disparity edge-padded
            by 8, ConfNet's map edge-padded by 4).
        """
        pad4, pad8 = (TOWER_MARGIN,) * 4, (MARGIN,) * 4
        disparity8 = F.pad(disparity, pad8, mode='replicate')
        image8 = F.pad(image, pad8, mode='replicate')
        local4 = self.local(disparity8, image8)
        global4 = F.pad(self.confnet.dense_confidence(disparity, image), pad4, mode='replicate')
        return F.pad(disparity, pad4, mode='replicate'), local4, global4

    def forward(self, disparity: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
        """(B, 1, H, W) confidence of whole inputs."""
        _check_pair(disparity, image, 1)
        return torch.sigmoid(self.fusion.forward_logits(*self.parts(disparity, image)))

    def dense_confidence(self, disparity: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
        """Same as :meth:`forward` (whole images are this network's unit)."""
        return self(disparity, image)


#: arch name → network class, the networks that read disparity (+ image), not the cost volume.
BASELINE_ARCHS: dict[str, type[nn.Module]] = {'ccnn': CCNN, 'lfn': LFN, 'lgcnet': LGCNet}


def _build(cls: type[nn.Module]) -> Any:
    def build(meta: Mapping[str, Any]) -> nn.Module:
        if cls is LGCNet:
            return LGCNet(int(meta['max_disparity']), int(meta.get('confnet_width', 32)))
        return cls(int(meta['max_disparity']))

    return build


for _name, _cls in BASELINE_ARCHS.items():
    if _name not in ARCHITECTURES:
        ARCHITECTURES.add(_name, _build(_cls))


def network_inputs(
    disparity: np.ndarray, image: np.ndarray, max_disparity: int
) -> tuple[np.ndarray, np.ndarray]:
    """The two input planes of every baseline network.

    Args:
        disparity: (H, W) float disparity in pixels, NaN/inf = invalid.
        image: (H, W) or (H, W, 3) uint8 left image (RGB if colour).
        max_disparity: D; the disparity is divided by it.

    Returns:
        ``(disparity_n, image_n)``: (H, W) float32 each, ``d / D`` with invalid → 0, and the
        grey image (ITU-R 601 luma for colour) / 255.

    Raises:
        InputError: Shapes that do not fit, a disparity that is not real numbers, an image that
            is not uint8, or D not a finite number >= 1.
    """
    disparity = np.asarray(disparity)
    image = np.asarray(image)
    if disparity.dtype.kind not in 'fiu':
        # The float32 cast below dropped an imaginary part, took True as 1 px and parsed strings.
        raise InputError(
            f'disparity must hold real numbers (float or int); got dtype {disparity.dtype}'
        )
    disparity = disparity.astype(np.float32, copy=False)
    if disparity.ndim != 2:
        raise InputError(f'disparity must be (H, W); got shape {disparity.shape}')
    if image.shape[:2] != disparity.shape or not (
        image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)
    ):
        raise InputError(
            f'image must be {disparity.shape} or {disparity.shape + (3,)}; got {image.shape}'
        )
    if image.dtype != np.uint8:
        # Divided by 255 below: a [0, 1] float or a 16-bit image would be silently rescaled.
        raise InputError(f'image must be uint8 (intensities 0..255); got dtype {image.dtype}')
    if not is_real(max_disparity) or not (
        math.isfinite(max_disparity) and max_disparity >= 1
    ):
        raise InputError(f'max_disparity must be a finite number >= 1; got {max_disparity!r}')
    filled = np.where(np.isfinite(disparity), disparity, np.float32(0.0))
    grey = image.astype(np.float32)
    if grey.ndim == 3:
        grey = grey @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
    return (filled / np.float32(max_disparity)).astype(np.float32), grey / np.float32(255.0)


def predict_disparity_confidence(
    net: nn.Module,
    disparity: np.ndarray,
    image: np.ndarray,
    device: str | torch.device = 'cpu',
) -> np.ndarray:
    """Whole-image confidence of a baseline network (one forward pass).

    Args:
        net: A :class:`CCNN`, :class:`LFN` or :class:`LGCNet`.
        disparity: (H, W) float disparity in pixels (NaN = invalid).
        image: (H, W) or (H, W, 3) uint8 left image.
        device: Where to run (``'cpu'``, ``'cuda'``, ``'cuda:N'`` or ``'auto'``): the device
            ``net`` lies on (it is run where it is, not moved).

    Returns:
        (H, W) float32 confidence in (0, 1).

    Raises:
        ModelError: ``net`` is not a baseline network.
        ConfigError: An unknown device, or ``net`` lying on another device.
        InputError: Bad shapes or image dtype.
    """
    if getattr(type(net), 'arch', None) not in BASELINE_ARCHS:
        raise ModelError(
            f'expected a network of {sorted(BASELINE_ARCHS)}; got {type(net).__name__}'
        )
    net = cast('CCNN | LGCNet', net)  # a baseline by the arch check above (LFN is a CCNN)
    disparity_n, image_n = network_inputs(disparity, image, net.max_disparity)
    device = resolve_device(device)
    parameter = next(net.parameters())
    if not same_device(parameter.device, device):
        raise ConfigError(
            f'{type(net).__name__} lies on {parameter.device}; got device {device} '
            f'(move the network there first, or pass device={str(parameter.device)!r})'
        )
    was_training = net.training
    net.eval()
    try:
        with torch.no_grad():
            # Inputs in the network's own dtype (float32 unless it was converted).
            d = torch.from_numpy(disparity_n)[None, None].to(device, parameter.dtype)
            i = torch.from_numpy(image_n)[None, None].to(device, parameter.dtype)
            out = net.dense_confidence(d, i)
    finally:
        net.train(was_training)
    return out[0, 0].float().cpu().numpy()

"""The MC-CNN fast feature network (Žbontar & LeCun, JMLR 2016) and its pretrained weights.

Five 3×3 convolutions with 64 channels, ReLU between them (not after the last), and L2
normalisation of the 64-channel feature vector of every pixel. Its receptive field is 11×11, so
a valid convolution of an image padded by 5 pixels on each side keeps the image size.

The weights are the Middlebury-trained ones that the ``mccnn`` pip package (CNES Pandora MC-CNN)
ships in ``mc_cnn/weights/mc_cnn_fast_mb_weights.pt``. This module imports torch; the matcher
imports it only when MC-CNN is used.
"""

from __future__ import annotations

from functools import lru_cache
from importlib.util import find_spec
from pathlib import Path

import numpy as np
import torch
from torch import nn

from cva_confidence_ros.devices import resolve_device
from cva_confidence_ros.errors import InputError, ModelError, reason

__all__ = [
    'BAND_BYTES',
    'FEATURES',
    'PADDING',
    'McCnnFastFeatures',
    'default_weights_path',
    'extract_features',
    'load_network',
    'normalise_image',
]

#: Channels of a feature vector.
FEATURES = 64
#: Pixels lost on each side by the five valid 3×3 convolutions.
PADDING = 5
#: Bytes of activations :func:`extract_features` lets the network hold at once (one band of rows).
BAND_BYTES = 64 * 2**20
_LAYERS = 5
_WEIGHTS_FILE = 'mc_cnn_fast_mb_weights.pt'
# ITU-R 601 luma weights, as the mccnn package converts colour images for training.
_LUMA = np.array([0.299, 0.587, 0.114], np.float32)


class McCnnFastFeatures(nn.Module):
    """MC-CNN fast feature extractor: (B, 1, H + 10, W + 10) → (B, 64, H, W), unit length.

    The layer names (``conv_blocks.0`` … ``conv_blocks.8``) are those of the pretrained state
    dict, so it loads without renaming.
    """

    def __init__(self) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        for index in range(_LAYERS):
            layers.append(nn.Conv2d(1 if index == 0 else FEATURES, FEATURES, kernel_size=3))
            if index < _LAYERS - 1:
                layers.append(nn.ReLU(inplace=True))
        self.conv_blocks = nn.Sequential(*layers)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """Unit-length features of padded, normalised images.

        Args:
            images: (B, 1, H + 10, W + 10) float tensor.

        Returns:
            (B, 64, H, W) float tensor, L2-normalised over the channel axis.
        """
        # Smaller than the 11×11 receptive field, torch's own error spoke of kernels.
        if images.ndim != 4 or images.shape[1] != 1 or min(images.shape[2:]) <= 2 * PADDING:
            raise ModelError(
                f'expected (B, 1, H + {2 * PADDING}, W + {2 * PADDING}) padded images with H, '
                f'W ≥ 1; got {tuple(images.shape)}'
            )
        return nn.functional.normalize(self.conv_blocks(images), p=2.0, dim=1)


def default_weights_path() -> Path:
    """Path of the Middlebury MC-CNN fast weights inside the installed ``mccnn`` package.

    Raises:
        ModelError: The ``mccnn`` package (module ``mc_cnn``) is not installed.
    """
    # find_spec locates the package without importing it (and its optional dependencies).
    spec = find_spec('mc_cnn')
    if spec is None or not spec.submodule_search_locations:
        raise ModelError(
            'the MC-CNN weights come from the mccnn pip package (module mc_cnn); '
            'it is not installed: pip install mccnn'
        )
    return Path(next(iter(spec.submodule_search_locations))) / 'weights' / _WEIGHTS_FILE


@lru_cache(maxsize=4)
def _cached_network(path: str, device: str) -> McCnnFastFeatures:
    try:
        state = torch.load(path, map_location='cpu', weights_only=True)
    except FileNotFoundError:
        raise ModelError(f'MC-CNN weights file not found: {path}') from None
    except Exception as error:  # torch raises many unrelated types for a damaged file
        raise ModelError(f'cannot read MC-CNN weights {path} ({reason(error)})') from error
    # The package saves a training checkpoint; the network weights sit under 'model'.
    if isinstance(state, dict) and 'model' in state:
        state = state['model']
    if not isinstance(state, dict):
        raise ModelError(f'expected a state dict in {path}; got {type(state).__name__}')
    state = {key.removeprefix('module.'): value for key, value in state.items()}
    network = McCnnFastFeatures()
    try:
        network.load_state_dict(state, strict=True)
    except RuntimeError as error:
        raise ModelError(f'{path} does not hold MC-CNN fast weights: {error}') from error
    network.eval()
    for parameter in network.parameters():
        parameter.requires_grad_(False)
    # float32 whatever torch's default dtype: the images come as float32.
    return network.to(device=torch.device(device), dtype=torch.float32)


def load_network(weights: str | Path | None = None, device: str = 'cpu') -> McCnnFastFeatures:
    """The pretrained network on ``device``, loaded once per process and (path, device).

    Args:
        weights: State-dict file; ``None`` or ``''`` = :func:`default_weights_path`.
        device: ``'cpu'``, ``'cuda'``, ``'cuda:N'`` or ``'auto'``.

    Raises:
        ModelError: Missing or unreadable file, or weights of another architecture.
        ConfigError: Unusable device.
    """
    path = Path(weights) if weights else default_weights_path()
    return _cached_network(str(path.resolve()), str(resolve_device(device)))


def normalise_image(image: np.ndarray) -> np.ndarray:
    """Gray, zero-mean, unit-variance float image, as the network was trained on.

    Args:
        image: (H, W) or (H, W, 3) RGB uint8 image.

    Returns:
        (H, W) float32, (gray − mean) / std (std 1 for a constant image).

    Raises:
        InputError: Not a non-empty (H, W) or (H, W, 3) numpy array.
    """
    # An (H, W, 4) RGBA or (H, W, 1) image failed in the matrix product with the 3 luma
    # weights (a bare ValueError), an empty one gave NaN statistics.
    if (
        not isinstance(image, np.ndarray)
        or image.ndim not in (2, 3)
        or (image.ndim == 3 and image.shape[2] != 3)
        or image.size == 0
    ):
        got = image.shape if isinstance(image, np.ndarray) else type(image).__name__
        raise InputError(f'image must be a non-empty H×W or H×W×3 numpy array; got {got}')
    gray = image.astype(np.float32) @ _LUMA if image.ndim == 3 else image.astype(np.float32)
    std = float(gray.std())
    return ((gray - gray.mean()) / (std if std > 0.0 else 1.0)).astype(np.float32)


def extract_features(
    network: McCnnFastFeatures, images: list[np.ndarray], device: torch.device
) -> torch.Tensor:
    """Unit-length features of images of equal size, one batch through the network.

    Args:
        network: From :func:`load_network`.
        images: (H, W) or (H, W, 3) uint8 images, all the same shape.
        device: Where to run.

    Returns:
        (B, 64, H, W) float32 tensor on ``device``.

    Raises:
        InputError: No images, images of different shapes, or one that
            :func:`normalise_image` refuses.
    """
    shapes = {np.shape(image) for image in images}
    if len(shapes) != 1:
        raise InputError(
            f'extract_features needs at least one image, all of one shape; got shapes '
            f'{sorted(shapes)}'
        )
    # Reflection padding rather than zeros: the border features then see image-like texture.
    batch = np.stack(
        [np.pad(normalise_image(image), PADDING, mode='reflect') for image in images]
    )[:, None]
    count = batch.shape[0]
    height, width = (side - 2 * PADDING for side in batch.shape[2:])
    # In bands of rows (each with the 2·PADDING rows of context its convolutions take): the
    # network's activations of a whole image, about 1 KB per pixel and image, came on top of
    # the features (3.1 GB for a 1920×1080 pair, past a small robot computer's memory).
    rows = max(1, BAND_BYTES // (count * FEATURES * 4 * 4 * width))
    with torch.inference_mode():
        padded = torch.from_numpy(batch)
        # Channels last: each image's (H, W, 64) is then contiguous as the correlation kernel
        # reads it, which took a copy of the features of both images (another 512 B a pixel).
        out = torch.empty(
            (count, FEATURES, height, width), device=device, memory_format=torch.channels_last
        )
        for top in range(0, height, rows):
            bottom = min(height, top + rows)
            out[:, :, top:bottom] = network(padded[:, :, top:bottom + 2 * PADDING].to(device))
        return out

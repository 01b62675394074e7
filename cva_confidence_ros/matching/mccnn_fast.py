"""MC-CNN fast matcher: learned 64-d features, cost = (1 − cos) / 2 between left and right.

Features are computed over the whole image by :mod:`cva_confidence_ros.matching.mccnn_net`
(imported lazily, it pulls in torch); the matching-cost volume is the cosine distance of the
unit-length feature vectors, mapped to [0, 1].
"""

from __future__ import annotations

from collections.abc import Iterator
import contextlib
from dataclasses import dataclass
import hashlib
from pathlib import Path
import re
import threading
from typing import TYPE_CHECKING

from numba import njit, prange
import numpy as np

from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.matching.base import Matcher
from cva_confidence_ros.matching.census import check_depth_and_step, valid_range

if TYPE_CHECKING:
    import torch

__all__ = [
    'MCCNNFastConfig',
    'MCCNNFastMatcher',
    'cosine_cost_volume',
    'cosine_cost_volume_torch',
    'preserved_features',
]

_CUDA_INDEX = re.compile(r'cuda:(0|[1-9][0-9]*)')


@dataclass(frozen=True)
class MCCNNFastConfig:
    """Parameters of :class:`MCCNNFastMatcher`.

    Attributes:
        device: ``'cpu'``, ``'cuda'``, ``'cuda:N'`` or ``'auto'`` (CUDA when available).
        weights: State-dict file of MC-CNN fast; empty = the Middlebury weights shipped with
            the ``mccnn`` pip package.
    """

    device: str = 'cpu'
    weights: str = ''

    def __post_init__(self) -> None:
        # 'cuda:N' with a plain decimal N, as torch.device parses it ('cuda:x', 'cuda:' or
        # 'cuda:01' would only fail later, as a RuntimeError from torch on a CUDA machine).
        if not isinstance(self.device, str) or not (
            self.device in ('cpu', 'cuda', 'auto') or _CUDA_INDEX.fullmatch(self.device)
        ):
            raise ConfigError(
                f"device must be 'cpu', 'cuda', 'cuda:N' or 'auto'; got {self.device!r}"
            )
        if not isinstance(self.weights, str):
            raise ConfigError(f'weights must be a path string; got {type(self.weights).__name__}')


@njit(cache=True, parallel=True, fastmath=True)
def _cosine_kernel(
    features_ref: np.ndarray, features_other: np.ndarray, step: int, volume: np.ndarray
) -> None:
    depth, height, width = volume.shape
    channels = features_ref.shape[2]
    for y in prange(height):
        ref_row = features_ref[y]
        other_row = features_other[y]
        for d in range(depth):
            lo, hi = valid_range(width, d, step)
            row = volume[d, y]
            for x in range(lo):
                row[x] = 1.0
            for x in range(hi, width):
                row[x] = 1.0
            for x in range(lo, hi):
                a = ref_row[x]
                b = other_row[x + step * d]
                dot = np.float32(0.0)
                for c in range(channels):
                    dot += a[c] * b[c]
                # rounding can push |cos| a hair above 1
                row[x] = min(max((np.float32(1.0) - dot) * np.float32(0.5), 0.0), 1.0)


def cosine_cost_volume(
    features_ref: torch.Tensor, features_other: torch.Tensor, depth: int, step: int
) -> np.ndarray:
    """(1 − cos) / 2 between reference features and shifted partner features.

    Args:
        features_ref: (C, H, W) unit-length float32 features of the reference view.
        features_other: (C, H, W) features of the other view, same device.
        depth: D.
        step: −1 when the partner of x is x − d (left reference), +1 when it is x + d.

    Returns:
        (D, H, W) float32 in [0, 1], 1.0 where the partner is outside the image. Computed by a
        numba kernel for CPU tensors and by :func:`cosine_cost_volume_torch` on the GPU.

    Raises:
        InputError: Features that are not non-empty 3-D float tensors of one shape on one
            device, ``depth`` < 1, or ``step`` not ±1.
    """
    _check_features(features_ref, features_other, depth, step)
    if features_ref.device.type != 'cpu':
        return cosine_cost_volume_torch(features_ref, features_other, depth, step)
    channels, height, width = features_ref.shape
    volume = np.empty((int(depth), height, width), np.float32)
    ref = _kernel_features(features_ref)
    other = _kernel_features(features_other)
    _cosine_kernel(ref, other, int(step), volume)
    return volume


def _check_features(
    features_ref: torch.Tensor, features_other: torch.Tensor, depth: int, step: int
) -> None:
    """InputError unless both are (C, H, W) float tensors of one shape and device.

    The numba kernel reads the other view at the reference's channels and columns, and at
    x + step·d: a narrower or thinner other view, or a step other than ±1, was read past its
    end (numba does not check bounds) and gave costs of whatever lay there, NaN included.
    """
    import torch

    for name, features in (('features_ref', features_ref), ('features_other', features_other)):
        if not isinstance(features, torch.Tensor):
            raise InputError(
                f'{name} must be a (C, H, W) torch tensor; got {type(features).__name__}'
            )
        if features.ndim != 3 or 0 in features.shape or not features.is_floating_point():
            raise InputError(
                f'{name} must be a non-empty (C, H, W) float tensor; got shape '
                f'{tuple(features.shape)} and dtype {features.dtype}'
            )
    if features_ref.shape != features_other.shape:
        raise InputError(
            'features_ref and features_other must have the same (C, H, W) shape; got '
            f'{tuple(features_ref.shape)} and {tuple(features_other.shape)}'
        )
    if features_ref.device != features_other.device:
        raise InputError(
            'features_ref and features_other must be on one device; got '
            f'{features_ref.device} and {features_other.device}'
        )
    check_depth_and_step(depth, step)


def _kernel_features(features: torch.Tensor) -> np.ndarray:
    """(H, W, C) C-contiguous numpy copy of (C, H, W) features for the numba kernel.

    Detached (a tensor that requires grad has no .numpy()) and float32 unless float64
    (numba has no float16, numpy no bfloat16), as the torch path takes them all.
    """
    import torch

    features = features.detach()
    if features.dtype not in (torch.float32, torch.float64):
        features = features.float()
    return np.ascontiguousarray(features.permute(1, 2, 0).numpy())


def cosine_cost_volume_torch(
    features_ref: torch.Tensor, features_other: torch.Tensor, depth: int, step: int
) -> np.ndarray:
    """Same as :func:`cosine_cost_volume`, as a loop over d of torch operations on the
    features' device (what CUDA uses)."""
    import torch

    _check_features(features_ref, features_other, depth, step)

    channels, height, width = features_ref.shape
    with torch.inference_mode():
        result = torch.ones((depth, height, width), device=features_ref.device)
        for d in range(depth):
            lo, hi = (d, width) if step < 0 else (0, width - d)
            if hi <= lo:
                continue
            partner = features_other[:, :, lo + step * d:hi + step * d]
            dot = (features_ref[:, :, lo:hi] * partner).sum(0)
            result[d, :, lo:hi] = ((1.0 - dot) * 0.5).clamp_(0.0, 1.0)
        return np.ascontiguousarray(result.cpu().numpy(), dtype=np.float32)


class _FeatureCache:
    """The features of the last image pair, so that the left and the right volume of one pair
    (``view='left'`` then ``'right'``) run the network once."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._key: tuple[object, ...] | None = None
        self._value: tuple[torch.Tensor, torch.Tensor] | None = None

    @staticmethod
    def key(left: np.ndarray, right: np.ndarray, *extra: object) -> tuple[object, ...]:
        digest = hashlib.blake2b(digest_size=16)
        digest.update(np.ascontiguousarray(left).data)
        digest.update(np.ascontiguousarray(right).data)
        return (left.shape, digest.hexdigest(), *extra)

    def get(self, key: tuple[object, ...]) -> tuple[torch.Tensor, torch.Tensor] | None:
        with self._lock:
            return self._value if key == self._key else None

    def put(self, key: tuple[object, ...], value: tuple[torch.Tensor, torch.Tensor]) -> None:
        with self._lock:
            self._key, self._value = key, value

    @contextlib.contextmanager
    def preserved(self) -> Iterator[None]:
        """Put the last pair back after the block, so that a warm-up pair in between does not
        take its place."""
        with self._lock:
            saved = self._key, self._value
        try:
            yield
        finally:
            with self._lock:
                self._key, self._value = saved


_FEATURES = _FeatureCache()


def preserved_features() -> contextlib.AbstractContextManager[None]:
    """A block after which the feature cache holds the pair it held before (a warm-up)."""
    return _FEATURES.preserved()


class MCCNNFastMatcher(Matcher):
    """MC-CNN fast (Žbontar & LeCun) with the pretrained Middlebury weights of ``mccnn``.

    Each image is converted to gray (ITU-R 601 weights), standardised to zero mean and unit
    variance, padded by 5 pixels (reflection) and passed through the network, which keeps the
    image size. Cost of a pixel pair = (1 − cos(f_left, f_right)) / 2 ∈ [0, 1]. The weights
    are loaded once per process; the features of the last pair are kept, so asking for the
    right view after the left one costs only the correlation.
    """

    Config = MCCNNFastConfig
    # The 64 float32 features of both images (kept for the other view's volume).
    bytes_per_pixel = 2 * 64 * 4
    config: MCCNNFastConfig

    def compute(
        self, left: np.ndarray, right: np.ndarray, max_disparity: int, view: str
    ) -> np.ndarray:
        """(D, H, W) float32 costs in [0, 1]; 1.0 where the partner pixel is outside the image.

        See :meth:`Matcher.compute` for the arguments.
        """
        from cva_confidence_ros.matching import mccnn_net

        device = mccnn_net.resolve_device(self.config.device)
        network = mccnn_net.load_network(self.config.weights, str(device))
        # The file, not the string: a relative path names another file after a change of
        # directory (load_network resolves it too).
        weights = str(Path(self.config.weights).resolve()) if self.config.weights else ''
        key = _FEATURES.key(left, right, str(device), weights)
        features = _FEATURES.get(key)
        if features is None:
            batch = mccnn_net.extract_features(network, [left, right], device)
            features = (batch[0], batch[1])
            _FEATURES.put(key, features)
        features_left, features_right = features
        if view == 'left':
            return cosine_cost_volume(features_left, features_right, int(max_disparity), -1)
        return cosine_cost_volume(features_right, features_left, int(max_disparity), 1)

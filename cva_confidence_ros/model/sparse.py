"""Sparse evaluation of a cost-volume confidence network, with edge-aware filling.

The network is the expensive part of the pipeline (≈ 70 MFLOP per pixel at D = 64). This module
runs it on a subset of the pixels and fills in the others:

* **strided grid** (``stride`` s = 2, 4, 8): the network runs on the pixels
  ``(o + i·s, o + j·s)``, ``o = (s − 1) // 2``; the others get a joint-bilateral
  interpolation (Kopf et al., SIGGRAPH 2007) of the network's logits from the 4×4 nearest grid
  samples, weighted by spatial distance, colour difference in the left image and disparity
  difference, so that confidence does not bleed across object edges. Grid pixels keep the
  network's value exactly.
* **cascade** (a cheap measure, PKRN or LRD, computed on every pixel first): the pixels are ranked
  by the cheap measure; the lowest ``fraction`` of that order is *undecided* and goes to the
  network; the rest is *decided* by the cheap measure. A high cheap confidence (one distinct cost
  minimum) is rarely wrong, while the low end mixes right and wrong pixels: that is where ordering
  them needs the network. (A band in the middle of the order was measured too: on the develop crops
  of ``cva-benchmark --suite fast`` its AUC was 4.5 % worse on average over PKRN/LRD, strides 1/8
  and fractions 0.1/0.25/0.5.) To put decided pixels on the network's probability scale, the
  network also runs on a calibration sample of the decided pixels (evenly spaced in the cheap
  order, one for every eight undecided pixels evaluated, at least 16), and an increasing map ``g``
  from the cheap rank to the network's logit is fitted on all evaluated pixels of the same frame
  (isotonic regression, linear between the centres of its steps, plus ``1e-3`` × rank so that the
  cheap order survives inside a step). Decided pixels get ``sigmoid(g(rank))``.
* both (``stride`` > 1 with a cascade): the network runs on the undecided grid pixels; an
  undecided pixel off the grid gets ``g(rank)`` plus the joint-bilateral interpolation of the
  residual ``logit(network) − g(rank)`` of the evaluated pixels around it.

Stride 1 without a cascade is the exact path (:func:`~cva_confidence_ros.model.
predict_confidence`).

Any network with the :class:`~cva_confidence_ros.model.FoldedCVANet` contract works
((B, 1, D, H + 12, W + 12) → (B, H, W) probabilities, ``max_disparity`` attribute; a 13×13
extract gives one value). For each memory-bounded tile the evaluator picks the cheapest of
three ways, by counting the floating-point operations of each for that tile (on tensors
without data, once per tile shape):

* ``tile``: the whole network on the tile, then the wanted pixels picked out;
* ``fused``: only for networks that also offer ``fusion_features`` ((B, 1, D, H + 12, W + 12)
  → (B, C, D', H, W)) and ``head_logits`` ((N, C, D') → (N,) logits), as
  :class:`~cva_confidence_ros.model.FoldedCVANet` does: the neighbourhood fusion densely
  over the tile (shared between neighbouring pixels), the depth processing only at the
  wanted pixels;
* ``extracts``: one 13×13×D extract per wanted pixel, nothing computed for the others
  (charged :data:`_EXTRACT_VALUE_FLOPS` more per value of the extract for its gathering,
  which the count does not see: CVA-Net-Fast fuses densely at stride 8 too).

For CVA-Net at D = 64, dense fusion is ≈ 21 % of a pixel's operations and an extract's fusion
≈ 6.5× a pixel's dense fusion, so stride 2 and 4 fuse densely, and so does a cascade alone at
fraction 0.1 or 0.25 (11–28 % of the pixels); stride 8, and a cascade of fraction ≤ 0.25 on
a stride-4 or -8 grid, use extracts. CVA-Net-Lite
(:class:`~cva_confidence_ros.model.FoldedCVANetLite`) splits the same way, but its fusion is
≈ 83 % of its operations, so stride 2 and 4 save little there.
Tiles are sized by the network's own widest activation
(:func:`~cva_confidence_ros.model.inference.activations_per_pixel`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
import contextlib
import copy
from dataclasses import dataclass
import math
import threading
from typing import cast

import numba
import numpy as np
import torch
from torch import nn

from cva_confidence_ros.checks import is_int, is_real
from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.model.inference import (
    _LIVE_COPIES,
    PAD,
    CVANet,
    _check_pixels,
    _check_tile_budget,
    _check_volume,
    _extract_batch,
    _input_dtype,
    _padded_tile,
    _unwrap,
    activations_per_pixel,
    fold_batchnorm,
    resolve_device,
    tile_shape,
)
from cva_confidence_ros.model.network import PATCH_SIZE

__all__ = [
    'BACKENDS',
    'CASCADES',
    'PRECISIONS',
    'STRIDES',
    'SparseConfig',
    'SparseEvaluator',
    'SparseResult',
    'cascade_selection',
    'check_backend',
    'grid_offset',
    'joint_bilateral_fill',
    'monotone_map',
    'precision_context',
    'sparse_confidence',
]

#: Grid strides of the sparse evaluation (1 = every pixel).
STRIDES = (1, 2, 4, 8)
#: Cheap measures that can decide pixels before the network (``none`` = no cascade).
CASCADES = ('none', 'pkrn', 'lrd')
#: Arithmetic of the network: float32, bfloat16 (CPU and CUDA) or float16 (CUDA only).
PRECISIONS = ('fp32', 'bf16', 'fp16')
#: Ways of evaluating the network on a tile (``auto`` = the cheapest by operation count).
PATHS = ('auto', 'tile', 'fused', 'extracts')
#: Runtimes of the network: PyTorch, or ONNX Runtime on the CPU (``model.export``).
BACKENDS = ('torch', 'onnxruntime')

#: Calibration pixels of a cascade: one per this many evaluated undecided pixels.
CALIBRATION_RATIO = 8
#: Smallest calibration sample of a cascade.
MIN_CALIBRATION = 16
#: Weight of the cheap rank added to the fitted map, so that ties of the map keep its order.
RANK_TIE_BREAK = 1e-3
#: Joint-bilateral weights: colour difference (grey levels, RMS over channels) and
#: disparity difference (pixels) at which the weight has fallen to exp(-1/2).
SIGMA_COLOR = 12.0
SIGMA_DISPARITY = 2.0
# Probabilities are clipped to [ε, 1 − ε] before a logit.
_LOGIT_EPS = 1e-6
#: Most 13×13×D extracts run at once (fewer where ``tile_budget_mb`` asks for it).
_EXTRACT_BATCH = 512
#: What one value of a 13×13×D extract costs beyond the network's counted operations (its
#: gather from the volume into a contiguous batch; CVA-Net-Fast's WTA scan, which the
#: operation count does not see), in operations, when the evaluator picks a way. Measured on
#: the 2-core CPU: CVA-Net-Fast at stride 8 (320×240, D = 64) counts 7.4 GFLOP as extracts
#: against 9.3 fused, yet took 115 ms against 72 (≈ 4.4 ns a value, ≈ 570 operations at the
#: fused rate). Small beside CVA-Net's (600 MFLOP an extract, +1 %) and CVA-Net-Lite's.
_EXTRACT_VALUE_FLOPS = 600.0


@dataclass(frozen=True)
class SparseConfig:
    """How much of the network to run.

    Attributes:
        stride: 1, 2, 4 or 8: the network runs on every stride-th pixel of each axis.
        cascade: ``none``, ``pkrn`` or ``lrd``: the cheap measure that decides the sure pixels.
        cascade_fraction: Share of the pixels (0, 1] the cascade leaves undecided (the least
            confident by the cheap measure) and hands to the network.
        precision: ``fp32``, ``bf16`` or ``fp16`` (CUDA only): autocast dtype of the network.
        path: ``auto`` (cheapest by operation count), ``tile``, ``fused`` or ``extracts``.

    Raises:
        ConfigError: A value outside the choices above, naming the field.
    """

    stride: int = 1
    cascade: str = 'none'
    cascade_fraction: float = 0.25
    precision: str = 'fp32'
    path: str = 'auto'

    def __post_init__(self) -> None:
        stride = self.stride
        # 2.0 == 2 and True == 1 would pass the membership test and fail later as an index.
        if (
            not is_int(stride)
            or stride not in STRIDES
        ):
            raise ConfigError(
                f'cva_stride must be an integer, one of {STRIDES}; '
                f'got {type(stride).__name__} {stride!r}'
            )
        if self.cascade not in CASCADES:
            raise ConfigError(f'cva_cascade must be one of {CASCADES}; got {self.cascade!r}')
        fraction = self.cascade_fraction
        if (
            not is_real(fraction)
            or not 0.0 < float(fraction) <= 1.0
        ):
            raise ConfigError(
                f'cva_cascade_fraction must be a real number in (0, 1]; '
                f'got {type(fraction).__name__} {fraction!r}'
            )
        if self.precision not in PRECISIONS:
            raise ConfigError(
                f'cva_precision must be one of {PRECISIONS}; got {self.precision!r}'
            )
        if self.path not in PATHS:
            raise ConfigError(f'path must be one of {PATHS}; got {self.path!r}')

    @property
    def exact(self) -> bool:
        """True when every pixel goes through the network (stride 1, no cascade)."""
        return self.stride == 1 and self.cascade == 'none'


@dataclass
class SparseResult:
    """Confidence of one frame and what the network computed for it.

    Attributes:
        confidence: (H, W) float32 in (0, 1).
        evaluated: (H, W) bool, True where the network ran (its value kept as is).
        decided: (H, W) bool, True where the cascade's cheap measure decided (all False
            without a cascade).
    """

    confidence: np.ndarray
    evaluated: np.ndarray
    decided: np.ndarray

    @property
    def network_share(self) -> float:
        """Share of the pixels the network ran on."""
        return float(self.evaluated.mean())


def precision_context(device: torch.device, precision: str) -> contextlib.AbstractContextManager:
    """Autocast for ``precision`` on ``device`` (a no-op for ``fp32``).

    Raises:
        ConfigError: Unknown precision, or ``fp16`` on a CPU (no fast float16 kernels there).
    """
    if precision == 'fp32':
        return contextlib.nullcontext()
    if precision == 'bf16':
        return torch.autocast(device.type, dtype=torch.bfloat16)
    if precision == 'fp16':
        if device.type != 'cuda':
            raise ConfigError(f"cva_precision 'fp16' needs a CUDA device; got {device}")
        return torch.autocast('cuda', dtype=torch.float16)
    raise ConfigError(f'cva_precision must be one of {PRECISIONS}; got {precision!r}')


def check_backend(backend: object, device: torch.device, precision: str) -> None:
    """Refuse a backend that is not there or cannot run with ``device`` and ``precision``.

    Raises:
        ConfigError: Unknown backend, or ``onnxruntime`` with a CUDA device or a reduced
            precision (its graph is the float32 network on the CPU).
    """
    if backend not in BACKENDS:
        raise ConfigError(f'cva_backend must be one of {BACKENDS}; got {backend!r}')
    if backend == 'onnxruntime':
        if device.type != 'cpu':
            raise ConfigError(
                f"cva_backend 'onnxruntime' runs the network on the CPU; got device {device} "
                "(device: cpu, or cva_backend: torch on CUDA)"
            )
        if precision != 'fp32':
            raise ConfigError(
                f"cva_backend 'onnxruntime' runs the float32 network; got cva_precision "
                f'{precision!r}'
            )


def grid_offset(stride: int) -> int:
    """First row/column of the stride grid, ``(stride − 1) // 2`` (cells centred on it)."""
    return (stride - 1) // 2


def _grid_axis(size: int, stride: int) -> np.ndarray:
    return np.arange(min(grid_offset(stride), size - 1), size, stride)


def _logit(probability: np.ndarray) -> np.ndarray:
    p = np.clip(probability.astype(np.float64), _LOGIT_EPS, 1.0 - _LOGIT_EPS)
    return np.log(p / (1.0 - p))


def _sigmoid(logit: np.ndarray) -> np.ndarray:
    return (0.5 * (1.0 + np.tanh(0.5 * logit))).astype(np.float32)


class SparseEvaluator:
    """A cost-volume network evaluated at chosen pixels, each tile the cheapest way.

    Args:
        net: A :class:`CVANet` (folded here), a :class:`FoldedCVANet`, or any module with its
            contract ((B, 1, D, H + 12, W + 12) → (B, H, W) probabilities and a
            ``max_disparity`` attribute). Modules that also have ``fusion_features`` and
            ``head_logits`` can fuse densely and classify sparsely. The evaluator runs its
            own copy (folded, or copied as it is): ``net`` is left on its device and in its
            mode, and later changes to its weights do not reach the evaluator.
        device: ``'cpu'``, ``'cuda'`` or ``'auto'``.
        tile_budget_mb: Memory budget of one tile's activations, megabytes.
        precision: ``fp32``, ``bf16`` or ``fp16`` (CUDA).
        path: ``auto`` or one fixed way (``tile``, ``fused``, ``extracts``).
        backend: ``torch``, or ``onnxruntime``: the folded network exported to ONNX once and
            run by ONNX Runtime on the CPU (float32; the ``fused`` way is not available).

    Raises:
        ConfigError: Bad device, budget, precision, path or backend, or ``fused`` for a
            network that cannot be split.
        ModelError: ``onnxruntime`` asked for without the onnx / onnxruntime packages.
    """

    def __init__(
        self,
        net: nn.Module,
        device: str | torch.device = 'cpu',
        tile_budget_mb: float = 512.0,
        precision: str = 'fp32',
        path: str = 'auto',
        backend: str = 'torch',
    ) -> None:
        given = net = _unwrap(net)
        if isinstance(net, CVANet):
            net = fold_batchnorm(net)
        elif not getattr(net, 'is_folded', False) and callable(
            getattr(net, 'fold_batchnorm', None)
        ):
            net = cast('Callable[[], nn.Module]', net.fold_batchnorm)()  # e.g. CVA-Net-Lite
        if net is given and isinstance(net, nn.Module):
            # An inference copy, as folding makes one: moving the caller's module to the
            # device and switching it to eval mode would change it under the caller's feet.
            net = copy.deepcopy(net)
        if not isinstance(getattr(net, 'max_disparity', None), int):
            raise ConfigError(
                f'expected a cost-volume network with an integer max_disparity; '
                f'got {type(net).__name__}'
            )
        tile_budget = _check_tile_budget(tile_budget_mb)
        if path not in PATHS:
            raise ConfigError(f'path must be one of {PATHS}; got {path!r}')
        self.device = resolve_device(device)
        precision_context(self.device, precision)  # validates
        check_backend(backend, self.device, precision)
        self.net = net.to(self.device).eval()
        # Tiles and extracts go in as the network's own dtype (float32 unless it was converted).
        self._dtype = _input_dtype(self.net)
        self.max_disparity: int = cast(int, net.max_disparity)  # checked above
        self.tile_budget_mb = tile_budget
        self.precision = precision
        self.backend = backend
        # What runs the network on tiles and extracts: the module, or its ONNX Runtime copy
        # (which has no separate fusion and head, so the 'fused' way is left out).
        self._run: Callable[[torch.Tensor], torch.Tensor] = self.net
        if backend == 'onnxruntime':
            from cva_confidence_ros.model.export import OnnxRuntimeNet

            self._run = OnnxRuntimeNet(self.net)
        self.splittable = (
            backend == 'torch'
            and callable(getattr(net, 'fusion_features', None))
            and callable(getattr(net, 'head_logits', None))
        )
        if path == 'fused' and not self.splittable:
            raise ConfigError(
                "path 'fused' is not available with cva_backend 'onnxruntime'"
                if backend == 'onnxruntime'
                else f"path 'fused' needs a network with fusion_features and head_logits; "
                f'{type(net).__name__} has not'
            )
        self.path = path
        self._flop_cache: dict[tuple[str, int, int], float] = {}
        self._meta: nn.Module | None = None
        #: Tiles evaluated per way since construction (for benchmarks and tests).
        self.path_counts: dict[str, int] = {'tile': 0, 'fused': 0, 'extracts': 0}
        #: Floating-point operations run since construction (counted, not timed).
        self.flops_done = 0.0
        #: Called as ``progress(done, total)``, in pixels, after each tile or batch of extracts
        #: of a call (for a progress bar over a long whole-image evaluation); None = silent.
        self.progress: Callable[[int, int], None] | None = None
        # Per thread, not per evaluator: a warm-up in one thread (:meth:`uncounted`) must not
        # hide or undo the counts of frames another thread runs meanwhile.
        self._local = threading.local()
        self._count_lock = threading.Lock()

    @contextlib.contextmanager
    def uncounted(self) -> Iterator[None]:
        """Calls from this thread inside the block leave ``path_counts`` and ``flops_done``
        as they are and report no progress; calls from other threads count as ever.

        The pipeline's warm-up runs in it. Saving the counters and putting them back
        afterwards lost every count of the frames processed by other threads meanwhile.
        """
        local = self._local
        local.depth = getattr(local, 'depth', 0) + 1
        try:
            yield
        finally:
            local.depth -= 1

    def _counting(self) -> bool:
        return not getattr(self._local, 'depth', 0)

    def _count(self, way: str, flops: float) -> None:
        if self._counting():
            # Locked: two threads' read-add-write of the same counter could drop one.
            with self._count_lock:
                self.path_counts[way] += 1
                self.flops_done += flops

    def _reporter(self) -> Callable[[int, int], None] | None:
        return self.progress if self._counting() else None

    # -- operation counts ---------------------------------------------------------------------
    def _flops(self, kind: str, rows: int, columns: int) -> float:
        """Operations of ``kind`` (``tile``, ``fusion``, ``head``) on a rows×columns output."""
        key = (kind, rows, columns)
        if key not in self._flop_cache:
            from torch.utils.flop_counter import FlopCounterMode

            if self._meta is None:
                self._meta = copy.deepcopy(self.net).to('meta')
            meta = self._meta
            depth = self.max_disparity
            volume = torch.empty(
                (1, 1, depth, rows + 2 * PAD, columns + 2 * PAD), device='meta', dtype=self._dtype
            )
            curves = None
            if kind == 'head':
                with torch.inference_mode():
                    fused = meta.fusion_features(volume)  # type: ignore[operator]
                shape = (rows * columns, fused.shape[1], fused.shape[2])
                curves = torch.empty(shape, device='meta', dtype=fused.dtype)
            with FlopCounterMode(display=False) as counter, torch.inference_mode():
                if kind == 'tile':
                    meta(volume)
                elif kind == 'fusion':
                    meta.fusion_features(volume)  # type: ignore[operator]
                else:
                    meta.head_logits(curves)  # type: ignore[operator]
            self._flop_cache[key] = float(counter.get_total_flops())
        return self._flop_cache[key]

    def _costs(self, rows: int, columns: int, count: int) -> dict[str, float]:
        """Operations of each available way for ``count`` wanted pixels of a rows×columns tile."""
        costs = {
            'tile': self._flops('tile', rows, columns),
            'extracts': count * self._flops('tile', 1, 1),
        }
        if self.splittable:
            costs['fused'] = self._flops('fusion', rows, columns) + count * self._flops(
                'head', 1, 1
            )
        return costs

    def _choose(self, rows: int, columns: int, count: int) -> str:
        costs = self._costs(rows, columns, count)
        # Chosen by operations plus the extracts' gathering (not counted in flops_done):
        # by operations alone CVA-Net-Fast took extracts at stride 8, 1.6× slower than fused.
        weighed = dict(costs)
        weighed['extracts'] += count * PATCH_SIZE**2 * self.max_disparity * _EXTRACT_VALUE_FLOPS
        way = min(weighed, key=weighed.__getitem__) if self.path == 'auto' else self.path
        self._count(way, costs[way])
        return way

    # -- evaluation ---------------------------------------------------------------------------
    def __call__(self, cost_volume: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
        """Network probabilities at the pixels of ``mask`` (all pixels if None).

        Args:
            cost_volume: (D, H, W) float normalised cost volume in [0, 1], D = max_disparity.
            mask: (H, W) bool, the pixels wanted; None = all.

        Returns:
            (H, W) float32: the network's confidence where ``mask`` is True, NaN elsewhere.

        Raises:
            InputError: Bad volume, or a mask of another shape.
        """
        volume = _check_volume(self.net, cost_volume)
        _, height, width = volume.shape
        # Every pixel (the node's dense frames): a whole tile goes in and out as a block,
        # without the index arrays and their gather and scatter (≈ 0.7 ms at 320×240).
        every = mask is None
        if mask is None:
            mask = np.ones((height, width), dtype=bool)
        mask = np.asarray(mask)
        if mask.shape != (height, width) or mask.dtype != np.bool_:
            raise InputError(
                f'mask must be a ({height}, {width}) bool array; got {mask.shape} {mask.dtype}'
            )
        result = np.full((height, width), np.nan, dtype=np.float32)
        rows, columns = tile_shape(
            height,
            width,
            self.max_disparity,
            self.tile_budget_mb,
            activations_per_pixel(self.net, self.max_disparity),
        )
        total, done = int(np.count_nonzero(mask)), 0
        report = self._reporter()
        with contextlib.ExitStack() as stack:
            stack.enter_context(torch.inference_mode())
            stack.enter_context(precision_context(self.device, self.precision))
            for y0 in range(0, height, rows):
                y1 = min(height, y0 + rows)
                for x0 in range(0, width, columns):
                    x1 = min(width, x0 + columns)
                    ys, xs = (None, None) if every else np.nonzero(mask[y0:y1, x0:x1])
                    count = (y1 - y0) * (x1 - x0) if ys is None else ys.size
                    if count == 0:
                        continue
                    way = self._choose(y1 - y0, x1 - x0, count)
                    if ys is None or xs is None:
                        if way == 'tile':
                            tile = self._tile(volume, y0, y1, x0, x1)
                            result[y0:y1, x0:x1] = self._run(tile)[0].float().cpu().numpy()
                            del tile  # not alive while the next one is built
                            done += count
                            if report is not None:
                                report(done, total)
                            continue
                        ys, xs = np.nonzero(mask[y0:y1, x0:x1])
                    if way == 'extracts':
                        values = self._extracts(volume, ys + y0, xs + x0, (done, total), report)
                    else:
                        values = self._dense(self._tile(volume, y0, y1, x0, x1), way, ys, xs)
                    result[ys + y0, xs + x0] = values
                    done += ys.size
                    if report is not None:
                        report(done, total)
        return result

    def at(self, cost_volume: np.ndarray, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
        """Network confidence at the pixels (ys, xs) from 13×13×D extracts.

        Args:
            cost_volume: (D, H, W) float normalised cost volume in [0, 1].
            ys: (N,) integer rows in [0, H).
            xs: (N,) integer columns in [0, W).

        Returns:
            (N,) float32 in (0, 1), equal to ``self(cost_volume)[ys, xs]`` (within 1e-5).

        Raises:
            InputError: Bad volume, or pixels outside the image.
        """
        volume = _check_volume(self.net, cost_volume)
        ys, xs = _check_pixels(ys, xs, volume.shape[1:])
        self._count('extracts', ys.size * self._flops('tile', 1, 1))
        with torch.inference_mode(), precision_context(self.device, self.precision):
            return self._extracts(volume, ys, xs, (0, ys.size), self._reporter())

    def _tile(self, volume: np.ndarray, y0: int, y1: int, x0: int, x1: int) -> torch.Tensor:
        """The network's input for output rows y0:y1, columns x0:x1: (1, 1, D, h + 12, w + 12)
        on the device, zero-padded tile by tile (no padded copy of the whole volume)."""
        return _padded_tile(volume, y0, y1, x0, x1).to(self.device, self._dtype)[None, None]

    def _dense(self, tile: torch.Tensor, way: str, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
        index_y = torch.from_numpy(ys).to(self.device)
        index_x = torch.from_numpy(xs).to(self.device)
        if way == 'tile':
            return self._run(tile)[0][index_y, index_x].float().cpu().numpy()
        fused = self.net.fusion_features(tile)  # type: ignore[operator]
        # (1, C, D', h, w) → (n, C, D') at the wanted pixels
        curves = fused[0][:, :, index_y, index_x].permute(2, 0, 1).contiguous()
        logits = self.net.head_logits(curves)  # type: ignore[operator]
        return torch.sigmoid(logits.float()).cpu().numpy()

    @property
    def extract_batch(self) -> int:
        """Extracts run at once on the extracts path: as many 13×13 tiles as
        ``tile_budget_mb`` holds by the same count as the dense tiles' (at most 512; at
        D = 128 and 64 MB, 512 extracts took 0.8 GB). On a 2-core CPU, batches of 16–32
        extracts run as fast as 512 or faster (D = 64: 234 against 116 extracts/s)."""
        per_extract = 4 * _LIVE_COPIES * PATCH_SIZE**2 * activations_per_pixel(
            self.net, self.max_disparity
        )
        # Capped before int(): a budget near the float maximum makes the count infinite.
        return max(1, int(min(_EXTRACT_BATCH, self.tile_budget_mb * 1e6 / per_extract)))

    def _extracts(
        self,
        volume: np.ndarray,
        ys: np.ndarray,
        xs: np.ndarray,
        progress: tuple[int, int],
        report: Callable[[int, int], None] | None,
    ) -> np.ndarray:
        """The network on batched 13×13×D extracts; ``progress`` = (pixels done before this
        call, pixels of the whole call), reported to ``report`` after each batch."""
        out = np.empty(ys.size, dtype=np.float32)
        done_before, total = progress
        batch_size = self.extract_batch
        for start in range(0, ys.size, batch_size):
            stop = min(ys.size, start + batch_size)
            batch = _extract_batch(volume, ys[start:stop], xs[start:stop])
            extracts = torch.from_numpy(batch).to(self.device, self._dtype)
            out[start:stop] = self._run(extracts)[:, 0, 0].float().cpu().numpy()
            if report is not None:
                report(done_before + stop, total)
        return out

    def confidence(
        self,
        cost_volume: np.ndarray,
        image: np.ndarray,
        disparity: np.ndarray,
        config: SparseConfig,
        cheap: np.ndarray | None = None,
    ) -> SparseResult:
        """:func:`sparse_confidence` with this network (``config.precision``/``path`` unused:
        they are the evaluator's own)."""
        return sparse_confidence(self, cost_volume, image, disparity, config, cheap)


def sparse_confidence(
    network: Callable[[np.ndarray, np.ndarray], np.ndarray],
    cost_volume: np.ndarray,
    image: np.ndarray,
    disparity: np.ndarray,
    config: SparseConfig,
    cheap: np.ndarray | None = None,
) -> SparseResult:
    """Confidence of every pixel from a sparse evaluation (see the module docstring).

    Args:
        network: ``(cost_volume, mask) -> (H, W)`` probabilities at the pixels of ``mask``, e.g.
            a :class:`SparseEvaluator` (or a lookup in a precomputed exact map: the result
            depends on the network only through its values at the evaluated pixels).
        cost_volume: (D, H, W) float normalised cost volume in [0, 1].
        image: (H, W) or (H, W, 3) uint8 left image (guides the interpolation).
        disparity: (H, W) float32 WTA disparity, NaN = invalid (guides the interpolation).
        config: Stride and cascade.
        cheap: (H, W) cheap confidence (higher = more confident), needed with a cascade.

    Returns:
        A :class:`SparseResult`; with stride 1 and no cascade it is the exact network.

    Raises:
        InputError: An empty volume, shapes that do not fit (``network``'s result included),
            an image that is not uint8, a disparity or ``cheap`` that is not real numbers, or a
            cascade without ``cheap``.
    """
    if not isinstance(cost_volume, np.ndarray) or cost_volume.ndim != 3 or 0 in cost_volume.shape:
        # An empty axis was an IndexError from the stride grid (its first row at -1).
        array = isinstance(cost_volume, np.ndarray)
        got = cost_volume.shape if array else type(cost_volume).__name__
        raise InputError(f'cost_volume must be a (D, H, W) numpy array, no axis empty; got {got}')
    _, height, width = cost_volume.shape
    shape = (height, width)
    _check_guides(image, disparity, shape)
    grid = np.zeros(shape, dtype=bool)
    rows_g, cols_g = _grid_axis(height, config.stride), _grid_axis(width, config.stride)
    grid[np.ix_(rows_g, cols_g)] = True
    base = np.zeros(shape)
    rank = base
    if config.cascade == 'none':
        evaluated = grid
        decided = np.zeros(shape, dtype=bool)
    else:
        if cheap is None or np.shape(cheap) != shape:
            given = None if cheap is None else np.shape(cheap)
            raise InputError(f'cascade {config.cascade!r} needs a {shape} cheap map; got {given}')
        if np.asarray(cheap).dtype.kind not in 'fiu':
            # Strings were parsed as numbers (or a bare ValueError), complex parts dropped.
            raise InputError(
                f'cheap must hold real numbers (float or int); got dtype {np.asarray(cheap).dtype}'
            )
        rank = _ranks(cheap)
        undecided, calibration = cascade_selection(rank, grid, config.cascade_fraction)
        decided = ~undecided
        evaluated = (undecided & grid) | calibration
    probability = np.asarray(network(cost_volume, evaluated), dtype=np.float32)
    if probability.shape != shape:
        # Was a bare IndexError ('boolean index did not match') at the first lookup.
        raise InputError(
            f'network must give {shape} probabilities for this frame; got {probability.shape}'
        )
    if config.exact:
        return SparseResult(probability, evaluated, decided)
    if decided.any():
        base = monotone_map(rank[evaluated], _logit(probability[evaluated]), rank)
    out = _sigmoid(base)
    todo = ~evaluated & ~decided
    if todo.any():
        residual = np.zeros(shape)
        residual[evaluated] = _logit(probability[evaluated]) - base[evaluated]
        sub = np.ix_(rows_g, cols_g)
        filled = joint_bilateral_fill(
            residual[sub], evaluated[sub], config.stride, image, disparity
        )
        out[todo] = _sigmoid(base[todo] + filled[todo])
    out[evaluated] = probability[evaluated]
    return SparseResult(out, evaluated, decided)


def _check_guides(image: object, disparity: object, shape: tuple[int, int]) -> None:
    """InputError unless ``image`` is an (H, W) or (H, W, 3) uint8 array and ``disparity``
    an (H, W) array of real numbers, (H, W) = ``shape``."""
    if not isinstance(image, np.ndarray) or not (
        image.shape[:2] == shape
        and (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3))
    ):
        got = image.shape if isinstance(image, np.ndarray) else type(image).__name__
        raise InputError(f'image must be {shape} or {shape + (3,)}; got {got}')
    if image.dtype != np.uint8:
        # The colour weight's σ is in 8-bit grey levels: a [0, 1] float image would make every
        # neighbour look alike, a 16-bit one make none of them.
        raise InputError(f'image must be uint8 (intensities 0..255); got dtype {image.dtype}')
    if not isinstance(disparity, np.ndarray) or disparity.shape != shape:
        got = disparity.shape if isinstance(disparity, np.ndarray) else type(disparity).__name__
        raise InputError(f'disparity must be {shape}; got {got}')
    if disparity.dtype.kind not in 'fiu':
        # The float32 cast of the fill parsed strings, took True as 1 px, dropped imaginary parts.
        raise InputError(
            f'disparity must hold real numbers (float or int); got dtype {disparity.dtype}'
        )


def _ranks(values: np.ndarray) -> np.ndarray:
    """(H, W) ranks in [0, 1], ties sharing their mean rank; non-finite values last/first."""
    flat = np.asarray(values, dtype=np.float64).ravel()
    flat = np.nan_to_num(flat, nan=-np.inf)
    ordered = np.sort(flat)
    low = np.searchsorted(ordered, flat, side='left')
    high = np.searchsorted(ordered, flat, side='right') - 1
    scale = max(1, flat.size - 1)
    return ((low + high) / (2.0 * scale)).reshape(np.shape(values))


def cascade_selection(
    rank: np.ndarray, candidates: np.ndarray, fraction: float
) -> tuple[np.ndarray, np.ndarray]:
    """Undecided pixels and the calibration sample of a cascade.

    Args:
        rank: (H, W) cheap-confidence ranks in [0, 1] (ties share a rank).
        candidates: (H, W) bool, where the network may run (the stride grid).
        fraction: Share (0, 1] of all pixels left undecided: those of the lowest ranks
            (least confident by the cheap measure).

    Returns:
        ``(undecided, calibration)``: (H, W) bool each. ``calibration`` holds decided
        candidates evenly spaced in rank order, one per :data:`CALIBRATION_RATIO` undecided
        candidates, at least :data:`MIN_CALIBRATION` (fewer only if fewer exist).

    Raises:
        ConfigError: ``fraction`` not a real number in (0, 1].
        InputError: ``candidates`` not a bool array of the shape of ``rank``.
    """
    if not is_real(fraction) or not 0.0 < float(fraction) <= 1.0:
        raise ConfigError(
            f'cva_cascade_fraction must be a real number in (0, 1]; '
            f'got {type(fraction).__name__} {fraction!r}'
        )
    rank, candidates = np.asarray(rank), np.asarray(candidates)
    if candidates.shape != rank.shape or candidates.dtype != np.bool_:
        # A 0/1 integer array picked pixels by index instead of masking: the calibration
        # sample landed off the stride grid, two pixels instead of sixteen.
        raise InputError(
            f'candidates must be a bool array of the rank shape {rank.shape}; '
            f'got {candidates.shape} {candidates.dtype}'
        )
    flat = rank.ravel()
    order = np.argsort(flat, kind='stable')
    count = flat.size
    band = min(count, max(1, round(fraction * count)))
    undecided_flat = np.zeros(count, dtype=bool)
    undecided_flat[order[:band]] = True
    undecided = undecided_flat.reshape(rank.shape)
    pool = order[~undecided_flat[order] & candidates.ravel()[order]]
    undecided_candidates = int((undecided & candidates).sum())
    wanted = max(MIN_CALIBRATION, math.ceil(undecided_candidates / CALIBRATION_RATIO))
    wanted = min(wanted, pool.size)
    calibration = np.zeros(count, dtype=bool)
    if wanted:
        picks = np.unique(np.round(np.linspace(0, pool.size - 1, wanted)).astype(np.intp))
        calibration[pool[picks]] = True
    return undecided, calibration.reshape(rank.shape)


def monotone_map(x_fit: np.ndarray, y_fit: np.ndarray, x_new: np.ndarray) -> np.ndarray:
    """Increasing map fitted on (x_fit, y_fit) by isotonic regression, applied to ``x_new``.

    The isotonic fit's steps are replaced by the line through their centres (mean x, mean y),
    constant beyond the first and last centre; :data:`RANK_TIE_BREAK` · x is added so that the
    map is strictly increasing in x.

    Args:
        x_fit: (N,) explanatory values (cheap ranks), N ≥ 1.
        y_fit: (N,) responses (network logits).
        x_new: Any shape, values to map.

    Returns:
        float64 array of the shape of ``x_new``.

    Raises:
        InputError: Empty or mismatched fit arrays, or fit values that are not finite.
    """
    x_fit = np.asarray(x_fit, dtype=np.float64).ravel()
    y_fit = np.asarray(y_fit, dtype=np.float64).ravel()
    if x_fit.size == 0 or x_fit.shape != y_fit.shape:
        raise InputError(f'need equal, non-empty fit arrays; got {x_fit.shape}, {y_fit.shape}')
    if not (np.isfinite(x_fit).all() and np.isfinite(y_fit).all()):
        # A NaN became a step centre or mean: the map was NaN over whole ranges of x.
        bad = int(np.count_nonzero(~np.isfinite(x_fit) | ~np.isfinite(y_fit)))
        raise InputError(f'fit arrays must be finite; got {bad} NaN or infinite pairs')
    order = np.lexsort((y_fit, x_fit))
    xs, ys = x_fit[order], y_fit[order]
    # Equal x must land in one block: pool them first.
    unique_x, first, counts = np.unique(xs, return_index=True, return_counts=True)
    sums = np.add.reduceat(ys, first)
    starts, ends, means = _weighted_pava(sums / counts, counts.astype(np.float64))
    centres = np.array(
        [np.average(unique_x[s:e], weights=counts[s:e]) for s, e in zip(starts, ends, strict=True)]
    )
    mapped = np.interp(np.asarray(x_new, dtype=np.float64), centres, means)
    return mapped + RANK_TIE_BREAK * np.asarray(x_new, dtype=np.float64)


@numba.njit(cache=True)
def _weighted_pava(
    y: np.ndarray, w: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pool-adjacent-violators on y (sorted by x) with weights w: block starts, ends, means."""
    n = y.size
    starts = np.empty(n, dtype=np.int64)
    ends = np.empty(n, dtype=np.int64)
    means = np.empty(n, dtype=np.float64)
    weights = np.empty(n, dtype=np.float64)
    blocks = 0
    for i in range(n):
        starts[blocks] = i
        ends[blocks] = i + 1
        means[blocks] = y[i]
        weights[blocks] = w[i]
        blocks += 1
        while blocks > 1 and means[blocks - 2] > means[blocks - 1]:
            total = weights[blocks - 2] + weights[blocks - 1]
            means[blocks - 2] = (
                means[blocks - 2] * weights[blocks - 2] + means[blocks - 1] * weights[blocks - 1]
            ) / total
            weights[blocks - 2] = total
            ends[blocks - 2] = ends[blocks - 1]
            blocks -= 1
    return starts[:blocks], ends[:blocks], means[:blocks]


@numba.njit(cache=True, parallel=True)
def _jbu_kernel(
    values: np.ndarray,
    known: np.ndarray,
    stride: int,
    offset_y: int,
    offset_x: int,
    guide: np.ndarray,
    disparity: np.ndarray,
    inv_2s2: float,
    inv_2c2: float,
    inv_2d2: float,
) -> np.ndarray:
    height, width, channels = guide.shape
    grid_rows, grid_cols = values.shape
    out = np.zeros((height, width), dtype=np.float64)
    for y in numba.prange(height):
        i0 = (y - offset_y) // stride
        for x in range(width):
            j0 = (x - offset_x) // stride
            total = 0.0
            weight_sum = 0.0
            plain = 0.0
            plain_sum = 0.0
            for i in range(i0 - 1, i0 + 3):
                if i < 0 or i >= grid_rows:
                    continue
                qy = offset_y + i * stride
                for j in range(j0 - 1, j0 + 3):
                    if j < 0 or j >= grid_cols or not known[i, j]:
                        continue
                    qx = offset_x + j * stride
                    spatial = math.exp(-((y - qy) ** 2 + (x - qx) ** 2) * inv_2s2)
                    colour = 0.0
                    for c in range(channels):
                        diff = guide[y, x, c] - guide[qy, qx, c]
                        colour += diff * diff
                    colour /= channels
                    ddiff = disparity[y, x] - disparity[qy, qx]
                    dterm = ddiff * ddiff * inv_2d2 if math.isfinite(ddiff) else 0.0
                    weight = spatial * math.exp(-colour * inv_2c2 - dterm)
                    total += weight * values[i, j]
                    weight_sum += weight
                    plain += spatial * values[i, j]
                    plain_sum += spatial
            if weight_sum > 1e-12:
                out[y, x] = total / weight_sum
            elif plain_sum > 0.0:
                # Every neighbour lies across an edge: fall back to spatial weights alone.
                out[y, x] = plain / plain_sum
    return out


def joint_bilateral_fill(
    values: np.ndarray,
    known: np.ndarray,
    stride: int,
    image: np.ndarray,
    disparity: np.ndarray,
    sigma_color: float = SIGMA_COLOR,
    sigma_disparity: float = SIGMA_DISPARITY,
) -> np.ndarray:
    """Joint-bilateral upsampling of samples on a stride grid to the full image.

    A pixel p gets Σ w·v / Σ w over the known samples q of the 4×4 grid cells around it, with
    w = exp(−|p − q|² / 2s²) · exp(−‖I_p − I_q‖² / 2σ_c²) · exp(−(d_p − d_q)² / 2σ_d²)
    (‖·‖² the mean squared channel difference; a non-finite disparity difference drops the
    disparity term). Where every neighbour's weight underflows (p lies across edges from all
    of them) the spatial weight alone is used; pixels without a known sample in reach get 0.
    Grid samples keep their values exactly.

    Args:
        values: (Hg, Wg) samples at rows/columns ``grid_offset(stride) + k·stride``.
        known: (Hg, Wg) bool, which samples are valid.
        stride: Grid spacing s ≥ 1.
        image: (H, W) or (H, W, 3) uint8 guide image.
        disparity: (H, W) float disparity guide, NaN allowed.
        sigma_color: σ_c, grey levels.
        sigma_disparity: σ_d, pixels.

    Returns:
        (H, W) float64 map.

    Raises:
        InputError: Grid shape that does not fit the image and stride, ``known`` not bool,
            a stride below 1, an empty image, or a guide that is not an (H, W) / (H, W, 3)
            uint8 image with an (H, W) disparity.
    """
    if not is_int(stride) or stride < 1:
        raise InputError(f'stride must be an integer >= 1; got {type(stride).__name__} {stride!r}')
    if not isinstance(image, np.ndarray) or image.ndim not in (2, 3):
        got = image.shape if isinstance(image, np.ndarray) else type(image).__name__
        raise InputError(f'image must be (H, W) or (H, W, 3); got {got}')
    height, width = image.shape[:2]
    if height == 0 or width == 0:
        # The stride grid of an empty axis started at -1 and asked for one sample.
        raise InputError(f'image must not be empty; got {image.shape}')
    _check_guides(image, disparity, (height, width))
    values, known = np.asarray(values), np.asarray(known)
    rows_g, cols_g = _grid_axis(height, stride), _grid_axis(width, stride)
    if values.shape != (rows_g.size, cols_g.size) or known.shape != values.shape:
        raise InputError(
            f'grid samples for a {height}×{width} image at stride {stride} must be '
            f'{(rows_g.size, cols_g.size)}; got values {values.shape}, known {known.shape}'
        )
    if known.dtype != np.bool_:
        # An integer 0/1 array would index rows below instead of masking.
        raise InputError(f'known must be a bool array; got dtype {known.dtype}')
    guide = image.astype(np.float32)
    if guide.ndim == 2:
        guide = guide[:, :, None]
    out = _jbu_kernel(
        np.ascontiguousarray(values, dtype=np.float64),
        np.ascontiguousarray(known, dtype=np.bool_),
        int(stride),
        int(rows_g[0]),
        int(cols_g[0]),
        np.ascontiguousarray(guide),
        np.ascontiguousarray(disparity, dtype=np.float32),
        1.0 / (2.0 * float(stride) ** 2),
        1.0 / (2.0 * sigma_color**2),
        1.0 / (2.0 * sigma_disparity**2),
    )
    sub = np.ix_(rows_g, cols_g)
    block = out[sub]
    block[known] = values[known]
    out[sub] = block
    return out

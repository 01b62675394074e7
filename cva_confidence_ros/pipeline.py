"""The processing pipeline shared by the node, the bag replay and the demo.

ROS-free: images in, disparity and confidence out. The node and the tools only translate
messages and parameters into :class:`PipelineConfig` and arrays.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field, fields
from functools import cached_property
import math
import os
import threading
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from cva_confidence_ros.checks import is_int, is_real
from cva_confidence_ros.errors import ConfigError, InputError, MemoryShortfallError

if TYPE_CHECKING:
    from cva_confidence_ros.confidence import ConfidenceInputs

__all__ = ['ROI_MARGIN', 'WARM_UP_MARGIN', 'WARM_UP_NETWORK_MACS', 'WARM_UP_ROWS',
           'PipelineConfig', 'PipelineResult', 'StereoPipeline', 'judged_region',
           'output_region']

_DEVICES = ('cpu', 'cuda', 'auto')
_MAX_SPECKLE_SIZE = 1_000_000
#: Rows processed above and below the region of interest and then dropped, so that the
#: windows of the matchers (census 5×5 and its 5×5 aggregation, MC-CNN's 9×9 patches) and of the
#: networks (13×13 extracts) inside the region see what they see on the whole image. Two
#: exceptions: SGM's vertical and diagonal paths start at the edge of this margin, and MC-CNN
#: standardises the image it gets (the rows processed) by its own mean and deviation.
ROI_MARGIN = 16
#: Rows of the synthetic pair of :meth:`StereoPipeline.warm_up` (processed resolution).
WARM_UP_ROWS = 16
#: Columns of that pair beyond max_disparity.
WARM_UP_MARGIN = 16
#: Most multiply-adds a confidence network may spend on the warm-up pair on a CPU; a heavier
#: one (CVA-Net: 35 M per pixel at D = 64) sees a window of it.
WARM_UP_NETWORK_MACS = 2e9
#: The methods the ``cva_*`` options (sparse paths, precision, backend) apply to.
COST_VOLUME_NETWORKS = ('cva_net', 'cva_net_lite', 'cva_net_fast')
# Taken around each frame when numba runs its parallel kernels on its ``workqueue`` threading
# layer (NUMBA_THREADING_LAYER=workqueue, or no OpenMP/TBB library): that layer is not
# thread-safe, and two pipelines used from two threads terminated the whole process.
_WORKQUEUE_LOCK = threading.Lock()


@dataclass(frozen=True)
class PipelineConfig:
    """Everything that decides what the pipeline computes.

    Attributes:
        matcher: Registered matcher name (``census_bm``, ``census_sgm``, ``mccnn_fast``).
        max_disparity: Cost-volume depth D at the processed resolution.
        confidence_method: Registered confidence method: ``cva_net_fast`` (default: the
            most accurate shipped network on the develop split and online on a CPU), ``cva_net``
            (the paper's network), ``cva_net_lite``, a learned baseline or a hand-crafted
            measure (``pkrn``, ...).
        model_path: Weights for learned methods; empty = the shipped weights for the matcher.
        device: ``cpu``, ``cuda`` or ``auto`` (CUDA when available).
        confidence_threshold: Pixels with confidence below it are invalid in the filtered output.
        downsample: 1, 2 or 4; images are shrunk by this factor before matching.
        lr_check: Also run a left–right consistency check and mark failing pixels invalid.
        subpixel: ``equiangular`` (default), ``parabola`` or ``none``: the curve through the
            costs around the winner-takes-all minimum that places the published disparity
            between the integers (``matching.refine_subpixel``); the confidence is that of the
            winner-takes-all disparity, which the refinement moves by at most 0.5 px.
        speckle_size: Kept pixels in a connected region of at most this many pixels (at the
            processed resolution) are dropped too (``matching.remove_speckles``, on the pixels
            the threshold keeps); 0 = off.
        speckle_range: Largest disparity step between neighbours of one region, in pixels.
        tile_budget_mb: Memory budget of one network tile at inference.
        cva_stride: 1, 2, 4 or 8: the network runs on every stride-th pixel of each axis, the
            rest is filled by joint-bilateral interpolation (1 = every pixel, exact).
        cva_cascade: ``none``, ``pkrn`` or ``lrd``: a cheap measure decides the pixels it is
            sure of; the network runs on the others (``lrd`` adds the right-view volume).
        cva_cascade_fraction: Share (0, 1] of the pixels the cascade hands to the network (the
            least confident by the cheap measure).
        cva_precision: ``fp32``, ``bf16`` or ``fp16`` (CUDA only) arithmetic of the network.
        cva_backend: ``torch``, or ``onnxruntime``: the learned cost-volume networks
            (``cva_net``, ``cva_net_lite``, ``cva_net_fast``) exported to ONNX once and run by
            ONNX Runtime on the CPU (float32, ``device`` must resolve to the CPU).
        roi_top: Share of the image height, from the top, that is not processed (sky, a
            ceiling beyond the range that matters); 0 = from the first row.
        roi_bottom: Share of the image height at which processing stops (the robot's own
            hood or bumper below it); 1 = to the last row. Only the rows between (plus
            :data:`ROI_MARGIN` rows of context) are matched and judged, so the time scales with
            ``roi_bottom − roi_top``; outside, the disparity is invalid and the confidence 0,
            and nothing there is kept.
        mask_path: An ignore mask (:mod:`cva_confidence_ros.mask`): an image of the input
            size, black where the camera sees the robot's own body (or anything else never to
            be judged); there, as outside the region of interest, nothing is published, and
            rows black from edge to edge at the top and bottom are not processed. ``''`` = none.

    Raises:
        ConfigError: An invalid value, named by its field (also in ``fields``: the node
            parameter of the same name).
    """

    matcher: str = 'census_bm'
    max_disparity: int = 64
    confidence_method: str = 'cva_net_fast'
    model_path: str = ''
    device: str = 'auto'
    confidence_threshold: float = 0.5
    downsample: int = 1
    lr_check: bool = False
    subpixel: str = 'equiangular'
    speckle_size: int = 100
    speckle_range: float = 1.0
    tile_budget_mb: float = 512.0
    cva_stride: int = 1
    cva_cascade: str = 'none'
    cva_cascade_fraction: float = 0.25
    cva_precision: str = 'fp32'
    cva_backend: str = 'torch'
    roi_top: float = 0.0
    roi_bottom: float = 1.0
    mask_path: str = ''

    def __post_init__(self) -> None:
        from cva_confidence_ros.confidence import CONFIDENCE_METHODS
        from cva_confidence_ros.matching import MATCHERS

        # Checked first: a list or another unhashable name fails the registry look-up with a
        # TypeError that names no option.
        for name, what in (('matcher', ''), ('confidence_method', ''),
                           ('model_path', ' (a file)'), ('mask_path', ' (a file)')):
            value = getattr(self, name)
            if not isinstance(value, str):
                hint = '; pass str(path)' if isinstance(value, os.PathLike) else ''
                raise ConfigError(f'{name} must be a string{what}; got {value!r}{hint}', name)
        # bool('false') is True: a flag given as a string would silently switch the check on.
        if not isinstance(self.lr_check, (bool, np.bool_)):
            raise ConfigError(f'lr_check must be True or False; got {self.lr_check!r}', 'lr_check')
        if self.matcher not in MATCHERS:
            raise ConfigError(
                f'unknown matcher {self.matcher!r}; expected one of {MATCHERS.names()}', 'matcher'
            )
        if self.confidence_method not in CONFIDENCE_METHODS:
            raise ConfigError(
                f'unknown confidence_method {self.confidence_method!r}; '
                f'expected one of {CONFIDENCE_METHODS.names()}', 'confidence_method',
            )
        if not is_int(self.max_disparity) or not 1 <= self.max_disparity <= 1024:
            raise ConfigError(
                f'max_disparity must be an integer in [1, 1024]; got {self.max_disparity!r}',
                'max_disparity',
            )
        if self.device not in _DEVICES:
            raise ConfigError(f'device must be one of {_DEVICES}; got {self.device!r}', 'device')
        if not is_real(self.confidence_threshold) or not 0 <= self.confidence_threshold <= 1:
            raise ConfigError(
                f'confidence_threshold must be a number in [0, 1]; '
                f'got {self.confidence_threshold!r}', 'confidence_threshold',
            )
        if not is_int(self.downsample) or self.downsample not in (1, 2, 4):
            raise ConfigError(
                f'downsample must be 1, 2 or 4; got {self.downsample!r}', 'downsample'
            )
        from cva_confidence_ros.matching import SUBPIXEL_METHODS

        if self.subpixel not in SUBPIXEL_METHODS:
            raise ConfigError(
                f'subpixel must be one of {SUBPIXEL_METHODS}; got {self.subpixel!r}', 'subpixel'
            )
        if not is_int(self.speckle_size) or not 0 <= self.speckle_size <= _MAX_SPECKLE_SIZE:
            raise ConfigError(
                f'speckle_size must be an integer in [0, {_MAX_SPECKLE_SIZE}]; '
                f'got {self.speckle_size!r}', 'speckle_size',
            )
        if not is_real(self.speckle_range) or not 0 <= self.speckle_range <= 1024:
            raise ConfigError(
                f'speckle_range must be a number in [0, 1024]; got {self.speckle_range!r}',
                'speckle_range',
            )
        if not is_real(self.tile_budget_mb) or not (
            math.isfinite(self.tile_budget_mb) and self.tile_budget_mb > 0
        ):
            raise ConfigError(
                f'tile_budget_mb must be a finite number > 0; got {self.tile_budget_mb!r}',
                'tile_budget_mb',
            )
        from cva_confidence_ros.model import SparseConfig

        # Raises ConfigError naming the cva_* field.
        SparseConfig(
            stride=self.cva_stride,
            cascade=self.cva_cascade,
            cascade_fraction=self.cva_cascade_fraction,
            precision=self.cva_precision,
        )
        from cva_confidence_ros.model.sparse import BACKENDS

        if self.cva_backend not in BACKENDS:
            raise ConfigError(
                f'cva_backend must be one of {BACKENDS}; got {self.cva_backend!r}', 'cva_backend'
            )
        for name in ('roi_top', 'roi_bottom'):
            value = getattr(self, name)
            if not is_real(value) or not 0 <= value <= 1:
                raise ConfigError(f'{name} must be a number in [0, 1]; got {value!r}', name)
        if self.roi_top >= self.roi_bottom:
            raise ConfigError(
                f'roi_top must be smaller than roi_bottom (the region of interest runs from '
                f'roi_top to roi_bottom of the image height); got roi_top = {self.roi_top!r}, '
                f'roi_bottom = {self.roi_bottom!r}', 'roi_top', 'roi_bottom',
            )
        # Numpy integers are taken but kept as Python ints: np.uint8(250) + 16 wraps to 10
        # (the warm-up pair's width), and 1 / np.int64(2) makes a numpy scale.
        for name in ('max_disparity', 'downsample', 'speckle_size', 'cva_stride'):
            object.__setattr__(self, name, int(getattr(self, name)))
        # Numpy floats and fractions likewise as Python floats: roi_rows rounds the share times
        # the height to 9 digits, which a float16 share (np.float16(0.25)) overflowed to NaN,
        # and every frame failed with "cannot convert float NaN to integer".
        for name in ('confidence_threshold', 'speckle_range', 'tile_budget_mb',
                     'cva_cascade_fraction', 'roi_top', 'roi_bottom'):
            object.__setattr__(self, name, float(getattr(self, name)))
        object.__setattr__(self, 'lr_check', bool(self.lr_check))

    def unused_options(self) -> list[str]:
        """The ``cva_*`` options set away from their defaults that change nothing here: those
        of the cost-volume networks under another method, and a cascade fraction without a
        cascade. They are accepted (one set of options serves every method) but a user tuning
        them saw no change and no word."""
        defaults = PipelineConfig()
        names = ['cva_stride', 'cva_cascade', 'cva_cascade_fraction', 'cva_precision',
                 'cva_backend']
        if self.confidence_method in COST_VOLUME_NETWORKS:
            names = ['cva_cascade_fraction'] if self.cva_cascade == 'none' else []
        return [f'{name} {getattr(self, name)!r}' for name in names
                if getattr(self, name) != getattr(defaults, name)]

    def roi_rows(self, height: int) -> tuple[int, int]:
        """Rows ``[y0, y1)`` of the region of interest in an image of ``height`` rows (the
        processed resolution); at least one row, the whole image by default."""
        if height <= 0:
            return 0, 0
        # Rounded first: 0.58 × 50 is 28.999999999999996 in floats (floor 28, not 29) and
        # 0.28 × 25 is 7.000000000000001 (ceil 8, not 7).
        y0 = min(height - 1, math.floor(round(self.roi_top * height, 9)))
        y1 = max(y0 + 1, min(height, math.ceil(round(self.roi_bottom * height, 9))))
        return y0, y1

    @property
    def disparity_step(self) -> float:
        """The disparity increment of the output (``DisparityImage.delta_d``): 1 for integer
        winner-takes-all disparities, 0 for sub-pixel ones (continuous values)."""
        return 1.0 if self.subpixel == 'none' else 0.0

    def replace(self, **changes: object) -> PipelineConfig:
        """Return a copy with ``changes`` applied (validated)."""
        names = {f.name for f in fields(self)}
        unknown = set(changes) - names
        if unknown:
            raise ConfigError(
                f'unknown pipeline options {sorted(unknown)}; expected {sorted(names)}'
            )
        values = {f.name: getattr(self, f.name) for f in fields(self)}
        values.update(changes)
        return PipelineConfig(**values)  # type: ignore[arg-type]


@dataclass
class PipelineResult:
    """What one stereo pair yields, at the processed (possibly downsampled) resolution.

    Attributes:
        disparity: (H, W) float32 disparity: winner-takes-all, refined to sub-pixel by
            ``PipelineConfig.subpixel``; NaN where the LR check failed.
        confidence: (H, W) float32 in [0, 1], higher = more trustworthy: the method's output
            through its fixed increasing map ``to_unit_interval`` (the identity for
            ``cva_net``), so the threshold means the same on every frame.
        raw_confidence: (H, W) float32, the method's own values (what the AUC is computed on;
            same order as ``confidence``, without the ties a squashing map can create).
        valid: (H, W) bool, True where the disparity is finite, confidence ≥ threshold and
            the pixel is not in a speckle of the pixels that pass (``speckle_size``).
        left: (H, W) or (H, W, 3) uint8 left image at the processed resolution.
        scale: 1 / downsample, the factor of pixel coordinates: each processed pixel is one
            downsample × downsample block of the input, and the bottom rows and right columns
            that fill no block are cropped (processed size = input size // downsample).
        timings_ms: Milliseconds per stage (``resize``, ``matching``, ``confidence``,
            ``subpixel`` when refined, ``speckle`` when filtered, ``total``).
        probabilistic: Whether ``confidence`` is meant as the probability that the disparity
            is correct (the networks; ``ConfidenceMethod.probabilistic``).
        speckle_fraction: Share of the pixels judged (:attr:`region`) that pass the
            threshold but lie in a speckle (dropped from :attr:`valid` by ``speckle_size``); 0
            with the filter off.
        rows: Rows ``[y0, y1)`` processed: those of the region of interest (``roi_top``,
            ``roi_bottom``), less the rows the mask ignores from edge to edge; the whole image
            by default. Outside them the disparity is NaN, the confidence 0, the raw
            confidence NaN and nothing is valid.
        mask: (H, W) bool, the ignore mask at the processed resolution (True = judged; the
            same holds where it is False), or None without one.
    """

    disparity: np.ndarray
    confidence: np.ndarray
    raw_confidence: np.ndarray
    valid: np.ndarray
    left: np.ndarray
    scale: float
    timings_ms: dict[str, float] = field(default_factory=dict)
    probabilistic: bool = False
    speckle_fraction: float = 0.0
    rows: tuple[int, int] | None = None
    mask: np.ndarray | None = None

    @cached_property
    def region(self) -> np.ndarray | None:
        """(H, W) bool, the pixels judged: the rows processed and the mask's pixels; None =
        every pixel. Made once per result (the node reads it for several statistics)."""
        return judged_region(self.valid.shape, self.rows, self.mask)

    def __repr__(self) -> str:
        # A notebook shows the repr of a cell's last value: the dataclass's own printed the
        # six maps in full, 48 lines of numbers for one 160×120 frame.
        height, width = np.shape(self.valid)[:2]
        parts = [f'{width}×{height} px', f'scale={self.scale:g}',
                 f'kept_fraction={self.kept_fraction:.3f}',
                 f'probabilistic={self.probabilistic}']
        if self.rows is not None and tuple(self.rows) != (0, height):
            parts.append(f'rows={tuple(self.rows)}')
        if self.mask is not None:
            parts.append(f'mask: {int(np.count_nonzero(self.mask))} px judged')
        if 'total' in self.timings_ms:
            parts.append(f"{self.timings_ms['total']:.1f} ms")
        return f'PipelineResult({", ".join(parts)})'

    @property
    def filtered_disparity(self) -> np.ndarray:
        """Disparity with NaN wherever :attr:`valid` is False."""
        return np.where(self.valid, self.disparity, np.float32(np.nan)).astype(np.float32)

    @property
    def kept_fraction(self) -> float:
        """Share of the pixels judged (:attr:`region`) in :attr:`valid` (0 for an empty
        map)."""
        region = self.region
        valid = self.valid if region is None else self.valid[region]
        return float(np.mean(valid)) if valid.size else 0.0

    @property
    def expected_kept_error(self) -> float | None:
        """The error rate the confidence predicts for the kept pixels: mean(1 − confidence)
        over :attr:`valid`, without ground truth (``calibration.expected_error``).

        None for a method whose confidence is no probability (the hand-crafted measures) or
        when no pixel is kept. On the develop split it is within a few points of the measured
        error (README, *What a confidence of 0.8 means*).
        """
        from cva_confidence_ros.calibration import expected_error

        if not self.probabilistic:
            return None
        return expected_error(self.confidence, self.valid)


class StereoPipeline:
    """Matcher + confidence method, configured once, applied to many pairs.

    Args:
        config: What to compute. Learned weights are loaded once here, not per frame.
        mask_option: What the caller calls ``config.mask_path``, for the messages about the
            mask (``'--mask'`` of the bag tools).

    Raises:
        ConfigError: ``config`` is no :class:`PipelineConfig`, the device is not available
            here, the method's options do not fit, or max_disparity is below the method's
            smallest depth (2 for ``pkrn``, ``lrd``).
        ModelError: Weights that cannot be loaded or do not fit the matcher and depth.
    """

    def __init__(self, config: PipelineConfig, mask_option: str = 'mask_path') -> None:
        from cva_confidence_ros.confidence import CONFIDENCE_METHODS
        from cva_confidence_ros.model import resolve_device

        _check_config(config)
        self.config = config
        # Checked here for every method, not on the first frame: a node that accepts
        # device=cuda on a machine without CUDA would then drop every frame.
        self.device = resolve_device(config.device)
        factory = CONFIDENCE_METHODS.get(config.confidence_method)
        self._method = factory(
            matcher=config.matcher,
            max_disparity=config.max_disparity,
            weights=config.model_path or None,
            device=config.device,
            tile_budget_mb=config.tile_budget_mb,
            cva_stride=config.cva_stride,
            cva_cascade=config.cva_cascade,
            cva_cascade_fraction=config.cva_cascade_fraction,
            cva_precision=config.cva_precision,
            cva_backend=config.cva_backend,
        )
        # Refused here, not on every frame (and in the warm-up's words) later.
        depth = getattr(self._method, 'min_depth', 1)
        if config.max_disparity < depth:
            raise ConfigError(
                f'confidence_method {config.confidence_method} compares the best cost with '
                f'the second best and needs max_disparity ≥ {depth}; got {config.max_disparity}'
            )
        from cva_confidence_ros.mask import load_mask

        self._mask_option = mask_option
        self._mask = load_mask(config.mask_path, mask_option) if config.mask_path else None
        self._reduced: tuple[tuple[int, int], np.ndarray] | None = None

    def __repr__(self) -> str:
        # The options set away from their defaults (the default object repr said nothing).
        defaults = PipelineConfig()
        shown = ('matcher', 'max_disparity', 'confidence_method')
        options = [f'{f.name}={getattr(self.config, f.name)!r}' for f in fields(self.config)
                   if f.name in shown or getattr(self.config, f.name) != getattr(defaults, f.name)]
        return f"StereoPipeline({', '.join(options)}; running on {self.device})"

    @property
    def probabilistic(self) -> bool:
        """Whether the method's confidence is meant as a probability of a correct disparity."""
        return bool(getattr(self._method, 'probabilistic', False))

    def _matcher_params(self) -> dict[str, Any]:
        # MC-CNN is the one matcher with a network; it runs where the confidence network runs.
        if self.config.matcher == 'mccnn_fast':
            return {'device': str(self.device)}
        return {}

    def check_input_size(self, width: int, height: int) -> None:
        """Whether images of ``width`` × ``height`` px can be processed with this configuration.

        Raises:
            InputError: Too small for ``downsample``, narrower than ``max_disparity`` + 1
                after downsampling, not the size of the mask, or with no pixel that both the
                region of interest and the mask leave.
            MemoryShortfallError: An InputError too: its matching needs more memory
                (:meth:`memory_needed`) than is available here (the need in GB and what
                lowers it).
        """
        cfg = self.config
        if min(width, height) < cfg.downsample:
            raise InputError(
                f'images of {width}×{height} px cannot be shrunk by downsample = {cfg.downsample}'
            )
        mask = self._processed_mask((height, width))
        if mask is not None:
            _judged_rows(cfg.roi_rows(mask.shape[0]), mask)
        shrunk = width // cfg.downsample
        if cfg.max_disparity >= shrunk:
            raise InputError(
                f'max_disparity must be smaller than the image width {shrunk}'
                + (f' ({width} px at downsample = {cfg.downsample})' if cfg.downsample > 1 else '')
                + f'; got {cfg.max_disparity}'
            )
        self._check_memory(width, height)

    def memory_needed(self, width: int, height: int) -> int:
        """Bytes that the matching of one ``width`` × ``height`` px pair allocates at least: the
        cost volume(s) (float32, D × rows processed × columns, the right view's too with
        ``lr_check`` or a method that needs it), SGM's work arrays (uint8 costs and uint16
        sums of the same size) and MC-CNN's features (64 float32 channels of both images).
        The confidence method's own memory comes on top: the networks' tiles, each padded on
        its own (about ``tile_budget_mb``; 1.5–1.8× that with glibc's fragmentation under
        the node's allocator setting)."""
        cfg = self.config
        rows = cfg.roi_rows(height // cfg.downsample)
        mask = self._processed_mask((height, width))
        if mask is not None:
            rows = _judged_rows(rows, mask)
        return self._matching_bytes(width // cfg.downsample, height // cfg.downsample, rows)

    def _matching_bytes(
        self, width: int, height: int, rows: tuple[int, int], depth: int | None = None
    ) -> int:
        """:meth:`memory_needed` at the processed size ``width`` × ``height``, ``rows`` judged
        (at cost-volume depth ``depth``; None = ``max_disparity``)."""
        cfg = self.config
        # Python ints: H·W·D of a 2448×2048 camera at D = 512 is 2.6e9, past int32.
        pixels = (min(height, rows[1] + ROI_MARGIN) - max(0, rows[0] - ROI_MARGIN)) * width
        voxels = pixels * (cfg.max_disparity if depth is None else depth)
        views = 2 if cfg.lr_check or getattr(self._method, 'needs_right', False) else 1
        from cva_confidence_ros.matching import MATCHERS

        matcher = MATCHERS.get(cfg.matcher)
        # MC-CNN's features live where its network runs: on a GPU they take no host memory.
        per_pixel = matcher.bytes_per_pixel if self.device.type == 'cpu' else 0
        # The second view's volume is new; its work arrays are the first one's.
        return (matcher.bytes_per_voxel + 4 * (views - 1)) * voxels + per_pixel * pixels

    def _check_memory(self, width: int, height: int) -> None:
        """InputError when the matching of such a pair cannot fit the memory left here
        (:func:`memory.available_memory`): refused up front, instead of swapping or the
        kernel's OOM killer ending the process (a node) without a word."""
        from cva_confidence_ros.memory import CHECK_SWITCH, shortfall

        need = self.memory_needed(width, height)
        available = shortfall(need)
        if available is None:
            return
        cfg = self.config
        gb = 1e9

        def need_at(factor: int, depth: int) -> int:
            return self._matching_bytes(
                width // factor, height // factor, cfg.roi_rows(height // factor), depth
            )

        depth = cfg.max_disparity
        # The largest halving of max_disparity that fits at the current downsample.
        smaller = next((d for d in (depth >> k for k in range(1, 8)) if d >= 8
                        and need_at(cfg.downsample, d) <= available), None)
        hints = [f'a smaller max_disparity (now {depth}' + (
            f'; {smaller}: {need_at(cfg.downsample, smaller) / gb:.2f} GB)' if smaller else ')')]
        for factor in (2, 4):
            if factor <= cfg.downsample:
                continue
            if depth < width // factor and need_at(factor, depth) <= available:
                hints.insert(0, f'downsample = {factor} ({need_at(factor, depth) / gb:.2f} GB)')
                break
            # The same depth range at a lower resolution takes a smaller max_disparity: with
            # neither downsample fitting alone, one param set at a time found no way out.
            fewer = max(1, depth * cfg.downsample // factor)
            if need_at(factor, fewer) <= available:
                hints.insert(0, f'downsample = {factor} with max_disparity = {fewer} (the same '
                                f'depth range, {need_at(factor, fewer) / gb:.2f} GB)')
                break
        hints.append('a narrower roi_top / roi_bottom')
        if cfg.lr_check:
            hints.append('lr_check off')
        raise MemoryShortfallError(
            f'a {width}×{height} px pair at max_disparity = {cfg.max_disparity}, downsample = '
            f'{cfg.downsample} with {cfg.matcher} needs at least {need / gb:.2f} GB for the '
            f'matching alone (cost volumes, work arrays), but {available / gb:.2f} GB of memory '
            f'are available; use '
            + ', '.join(hints) + f' ({CHECK_SWITCH}=0 in the environment turns this check off)'
        )

    def warm_up(self) -> None:
        """Run the whole pipeline once on a small synthetic pair, outside every statistic.

        Every numba kernel the configuration uses (matcher, winner-takes-all, left–right
        check, sub-pixel step, speckle filter, hand-crafted measures, the networks' own
        kernels) compiles or loads from its cache here, MC-CNN loads its weights and the
        confidence network makes its first torch call, so that none of it lands on the first
        real frame. The pair is :data:`WARM_UP_ROWS` rows by D + :data:`WARM_UP_MARGIN`
        columns at the processed resolution; a network whose work on it would exceed
        :data:`WARM_UP_NETWORK_MACS` multiply-adds (the paper's ``cva_net`` on a CPU) sees
        only a window of it (at least one pixel), so the warm-up stays well under a second.

        Nothing of the warm-up stays behind: the network evaluator's counters
        (``path_counts``, ``flops_done``), MC-CNN's last-pair features and SGM's work arrays
        are as they were, and the ignore mask is not used (its size is that of real images).
        """
        from cva_confidence_ros.matching.mccnn_fast import preserved_features
        from cva_confidence_ros.matching.sgm import preserved_scratch

        cfg = self.config
        factor = cfg.downsample
        height, width = WARM_UP_ROWS, cfg.max_disparity + WARM_UP_MARGIN
        # Random texture on a plane at disparity 2 (a few pixels keep to the left edge):
        # every stage sees ordinary values, with confident pixels for the speckle filter.
        rng = np.random.default_rng(0)
        texture = rng.integers(0, 256, (height * factor, (width + 2) * factor), dtype=np.uint8)
        # Left (x) matches right (x − 2); the pair was the other way round (disparity −2,
        # nothing confident, nothing kept).
        left = np.ascontiguousarray(texture[:, : width * factor])
        right = np.ascontiguousarray(texture[:, 2 * factor:])
        # Uncounted in this thread only: saving the counters and putting them back lost the
        # counts of frames that other threads processed during the warm-up (the node warms
        # up while its first frames arrive).
        uncounted = getattr(getattr(self._method, 'evaluator', None), 'uncounted', None)
        quiet = uncounted() if callable(uncounted) else contextlib.nullcontext()
        with _frame_guard(), preserved_features(), preserved_scratch(), quiet:
            self._run(left, right, None, self._warm_up_window(height, width))

    def _warm_up_window(self, height: int, width: int) -> tuple[int, int] | None:
        """(rows, columns) of the window the method sees in the warm-up, or None for all of
        the ``height`` × ``width`` pair: a window when the network is too heavy for it."""
        arch = getattr(self._method, 'arch', None)
        if not arch or self.device.type != 'cpu':
            return None
        from cva_confidence_ros.model.complexity import dense_macs

        depth = self.config.max_disparity
        try:
            if dense_macs(arch, depth, height, width) <= WARM_UP_NETWORK_MACS:
                return None
        except ConfigError:  # no count for it (the baselines, light networks): run it all
            return None
        # The largest square window (padded by the network's border, as counted) in budget.
        side = min(height, width)
        while side > 1 and dense_macs(arch, depth, side, side) > WARM_UP_NETWORK_MACS:
            side -= 1
        return side, side

    def process(self, left: np.ndarray, right: np.ndarray) -> PipelineResult:
        """Match one rectified pair and estimate per-pixel confidence.

        Args:
            left: (H, W) or (H, W, 3) rectified left image (RGB order if colour): uint8, or
                float with finite values in [0, 255], rounded to uint8
                (``matching.check_image_pair``).
            right: Same shape as ``left``, uint8 or float likewise.

        Returns:
            A :class:`PipelineResult` at 1/downsample of the input resolution.

        Raises:
            InputError: Shapes, dtypes or values that the matcher cannot use.
        """
        from cva_confidence_ros.matching import check_image_pair

        # Checked before resizing: OpenCV's resize has its own, less clear, view of bad arrays.
        given = left
        left, right = check_image_pair(left, right)
        self.check_input_size(left.shape[1], left.shape[0])
        with _frame_guard():
            result = self._run(left, right, self._processed_mask(left.shape[:2]))
        if np.may_share_memory(result.left, given):
            # At downsample = 1 it was the caller's own array: a camera driver that fills the
            # same buffer with the next frame changed the image of a result kept for later.
            result.left = result.left.copy()
        return result

    def _run(
        self,
        left: np.ndarray,
        right: np.ndarray,
        mask: np.ndarray | None,
        window: tuple[int, int] | None = None,
    ) -> PipelineResult:
        """:meth:`process` of a checked pair with the ignore ``mask`` at the processed
        resolution; ``window`` (warm-up only): the method sees only that many (rows, columns)
        of the region processed, its confidence elsewhere is NaN."""
        from cva_confidence_ros.confidence import ConfidenceInputs
        from cva_confidence_ros.datasets.resize import resize_image
        from cva_confidence_ros.matching import (
            compute_cost_volume,
            left_right_check,
            refine_subpixel,
            remove_speckles,
            wta_disparity,
        )

        cfg = self.config
        timings: dict[str, float] = {}
        start = time.perf_counter()
        # Crop to a multiple of the factor first, so that images and a ground truth shrunk with
        # datasets.resize_disparity stay pixel-aligned.
        left_s = resize_image(left, cfg.downsample)
        right_s = resize_image(right, cfg.downsample)
        timings['resize'] = (time.perf_counter() - start) * 1e3
        height = left_s.shape[0]
        rows = cfg.roi_rows(height)
        if mask is not None:
            rows = _judged_rows(rows, mask)
        # The region of interest with its margin of context: what is matched and judged.
        c0, c1 = max(0, rows[0] - ROI_MARGIN), min(height, rows[1] + ROI_MARGIN)
        left_c, right_c = left_s[c0:c1], right_s[c0:c1]

        tic = time.perf_counter()
        params = self._matcher_params()
        volume = compute_cost_volume(left_c, right_c, cfg.matcher, cfg.max_disparity, **params)
        disparity = wta_disparity(volume)
        volume_right = None
        disparity_right = None
        if cfg.lr_check or getattr(self._method, 'needs_right', False):
            volume_right = compute_cost_volume(
                left_c, right_c, cfg.matcher, cfg.max_disparity, view='right', **params
            )
            disparity_right = wta_disparity(volume_right)
        timings['matching'] = (time.perf_counter() - tic) * 1e3

        tic = time.perf_counter()
        inputs = ConfidenceInputs(
            cost_volume=volume,
            disparity=disparity,
            image=left_c,
            cost_volume_right=volume_right,
            disparity_right=disparity_right,
            matcher=cfg.matcher,
        )
        raw_confidence = self._confidence(inputs, window)
        confidence = self._method.to_unit_interval(raw_confidence)
        timings['confidence'] = (time.perf_counter() - tic) * 1e3

        if cfg.lr_check and disparity_right is not None:
            disparity = np.where(
                left_right_check(disparity, disparity_right), disparity, np.float32(np.nan)
            ).astype(np.float32)
        if cfg.subpixel != 'none':
            tic = time.perf_counter()
            disparity = refine_subpixel(volume, disparity, cfg.subpixel)
            timings['subpixel'] = (time.perf_counter() - tic) * 1e3
        if rows != (0, height):
            # Back to the whole image: the region's rows in place, nothing outside.
            inside = slice(rows[0] - c0, rows[1] - c0)
            disparity, confidence, raw_confidence = (
                _place(values[inside], height, rows, fill)
                for values, fill in ((disparity, np.nan), (confidence, 0.0),
                                     (raw_confidence, np.nan))
            )
        if mask is not None:
            # New arrays: the confidence may be the raw confidence itself (cva_net).
            disparity, confidence, raw_confidence = (
                np.where(mask, values, np.float32(fill)).astype(np.float32, copy=False)
                for values, fill in ((disparity, np.nan), (confidence, 0.0),
                                     (raw_confidence, np.nan))
            )
        # In float32, the confidence's own type, as a cloud filter downstream compares: a
        # float64 threshold 0.7 dropped the stored confidence float32(0.7).
        valid = np.isfinite(disparity) & (confidence >= np.float32(cfg.confidence_threshold))
        speckle_fraction = 0.0
        if cfg.speckle_size > 0:
            tic = time.perf_counter()
            confident = int(np.count_nonzero(valid))
            valid = remove_speckles(disparity, valid, cfg.speckle_size, cfg.speckle_range)
            region = judged_region(valid.shape, rows, mask)
            judged = valid.size if region is None else int(np.count_nonzero(region))
            speckle_fraction = (confident - int(np.count_nonzero(valid))) / max(judged, 1)
            timings['speckle'] = (time.perf_counter() - tic) * 1e3
        timings['total'] = (time.perf_counter() - start) * 1e3
        return PipelineResult(
            disparity=disparity,
            confidence=confidence,
            raw_confidence=raw_confidence,
            valid=valid,
            left=left_s,
            scale=1.0 / cfg.downsample,
            timings_ms=timings,
            probabilistic=self.probabilistic,
            speckle_fraction=speckle_fraction,
            rows=rows,
            mask=mask,
        )

    def _confidence(self, inputs: ConfidenceInputs, window: tuple[int, int] | None) -> np.ndarray:
        """The method's (H, W) float32 values of ``inputs``; with a ``window`` (rows,
        columns) only there (the right end of the top rows, where every disparity has a
        partner pixel), NaN elsewhere."""
        if window is None:
            return np.asarray(self._method(inputs), dtype=np.float32)
        from cva_confidence_ros.confidence import ConfidenceInputs

        height, width = inputs.shape
        rows = slice(0, min(window[0], height))
        columns = slice(max(0, width - window[1]), width)

        def crop(values: np.ndarray | None) -> np.ndarray | None:
            return None if values is None else values[..., rows, columns]

        part = ConfidenceInputs(
            cost_volume=inputs.cost_volume[:, rows, columns],
            disparity=inputs.disparity[rows, columns],
            image=inputs.image[rows, columns],
            cost_volume_right=crop(inputs.cost_volume_right),
            disparity_right=crop(inputs.disparity_right),
            matcher=inputs.matcher,
            first_column=columns.start,
        )
        out = np.full((height, width), np.nan, dtype=np.float32)
        out[rows, columns] = np.asarray(self._method(part), dtype=np.float32)
        return out

    def _processed_mask(self, shape: tuple[int, int]) -> np.ndarray | None:
        """The ignore mask at the processed resolution for input images of ``shape`` (checked
        against the mask's size; reduced once per input size)."""
        if self._mask is None:
            return None
        if self._reduced is None or self._reduced[0] != shape:
            from cva_confidence_ros.mask import check_mask_size, reduce_mask

            check_mask_size(self._mask, shape[1], shape[0],
                            f'{self._mask_option} {self.config.mask_path!r}')
            reduced = reduce_mask(self._mask, self.config.downsample)
            # Read-only: every result's ``mask`` is this array, and an in-place edit of one
            # result's mask (``result.mask[:10] = False``) changed the rows of every later frame.
            reduced.setflags(write=False)
            self._reduced = (shape, reduced)
        return self._reduced[1]


def _workqueue_layer() -> bool:
    """Whether numba's parallel kernels run on its ``workqueue`` threading layer (chosen once
    per process, and fixed from then on; started here keeping torch's thread count)."""
    from cva_confidence_ros.jit import start_numba_threads

    return start_numba_threads() == 'workqueue'


def _frame_guard() -> contextlib.AbstractContextManager[object]:
    """:data:`_WORKQUEUE_LOCK` when numba's threading layer is ``workqueue``, else a no-op."""
    return _WORKQUEUE_LOCK if _workqueue_layer() else contextlib.nullcontext()


def output_region(
    config: PipelineConfig,
    shape: tuple[int, int],
    mask: np.ndarray | None = None,
    option: str = 'mask_path',
) -> np.ndarray | None:
    """The pixels a pipeline of ``config`` judges in its outputs of ``shape`` (the processed
    resolution), from the outside: what :attr:`PipelineResult.region` is for a frame.

    Args:
        config: The pipeline's configuration (``roi_top``, ``roi_bottom``, ``downsample``).
        shape: (h, w) of the outputs.
        mask: The ignore mask at the input resolution (``mask.load_mask`` of
            ``config.mask_path``), or None.
        option: What the caller calls ``config.mask_path``, for the message (``'--mask'``).

    Raises:
        ConfigError: ``config`` is no :class:`PipelineConfig`.
        InputError: The mask, shrunk by ``downsample``, is not of ``shape`` (drawn for another
            resolution), or the region of interest and the mask have no pixel in common.
    """
    from cva_confidence_ros.mask import reduce_mask

    _check_config(config)
    rows = config.roi_rows(shape[0])
    reduced = None
    if mask is not None:
        reduced = reduce_mask(mask, config.downsample)
        # A mask of another camera resolution used to be cropped to the outputs (a larger
        # one: silently the wrong pixels) or failed numpy's broadcast (a smaller one).
        if reduced.shape != tuple(shape[:2]):
            at = ''
            if config.downsample > 1:
                at = (f' ({reduced.shape[1]}×{reduced.shape[0]} px at downsample = '
                      f'{config.downsample})')
            name = option + (f' {config.mask_path!r}' if config.mask_path else '')
            raise InputError(
                f'the mask ({name}) is {mask.shape[1]}×{mask.shape[0]} px{at} but the '
                f'outputs are {shape[1]}×{shape[0]} px; draw the mask on a frame of this camera '
                f'at the resolution it publishes'
            )
        rows = _judged_rows(rows, reduced)
    return judged_region(shape, rows, reduced)


def judged_region(
    shape: tuple[int, ...], rows: tuple[int, int] | None, mask: np.ndarray | None
) -> np.ndarray | None:
    """(H, W) bool of the pixels judged: ``rows`` ``[y0, y1)`` (None = all) and the mask's
    True pixels (None = all); None when that is every pixel."""
    height = shape[0]
    if mask is None and (rows is None or rows == (0, height)):
        return None
    region = np.zeros(shape[:2], dtype=bool)
    y0, y1 = (0, height) if rows is None else rows
    region[y0:y1] = True if mask is None else mask[y0:y1]
    return region


def _check_config(config: object) -> None:
    """Raise :class:`ConfigError` unless ``config`` is a :class:`PipelineConfig` (a dict of its
    fields or a matcher name failed with "'dict' object has no attribute 'device'")."""
    if not isinstance(config, PipelineConfig):
        raise ConfigError(
            f'config must be a PipelineConfig; got {type(config).__name__} {config!r:.80}'
            + ('; pass PipelineConfig(**fields)' if isinstance(config, dict) else '')
        )


def _judged_rows(rows: tuple[int, int], mask: np.ndarray) -> tuple[int, int]:
    """The region of interest's rows less those at its top and bottom that the mask ignores
    from edge to edge."""
    from cva_confidence_ros.mask import mask_rows

    # The mask's rows inside the region: a mask that judges rows above and below the region
    # but none in it used to pass, and every frame was processed with nothing judged.
    y0, y1 = mask_rows(mask[rows[0] : rows[1]])
    if y0 >= y1:
        m0, m1 = mask_rows(mask)
        judged = (f'judged pixels in rows {m0} to {m1} at the processed resolution' if m0 < m1
                  else 'no judged pixel at the processed resolution, where a pixel is judged '
                       'only when its whole downsample block is')
        raise InputError(
            f'the region of interest (rows {rows[0]} to {rows[1]}) and the mask ({judged}) '
            f'have no pixel in common'
        )
    return rows[0] + y0, rows[0] + y1


def _place(
    values: np.ndarray, height: int, rows: tuple[int, int], fill: float
) -> np.ndarray:
    """A (height, W) float32 map holding ``values`` in ``rows`` and ``fill`` elsewhere."""
    out = np.full((height, values.shape[1]), fill, dtype=np.float32)
    out[rows[0] : rows[1]] = values
    return out

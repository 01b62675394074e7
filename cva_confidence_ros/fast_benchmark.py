"""Speed and AUC cost of CVA-Net's fast paths (``cva-benchmark --suite fast``).

One record per configuration (:data:`FAST_CONFIGS`: exact, bf16, strides, cascades and their
combinations, plus whole-pipeline rows, for CVA-Net and, in the ``lite*`` rows, for CVA-Net-Lite:
:attr:`FastConfig.arch`), with the keys of
:data:`cva_confidence_ros.benchmark.RECORD_KEYS`:

* ``ms_per_frame``: the network part (cheap measure and filling included) on the cost volume of
  the Motorcycle pair fitted to ``--width``×``--height`` (census_bm, D = ``--max-disparity``),
  median of ``--repeat`` frames (``timed_calls``) after untimed ones (a warm-up frame, then
  the frame that gives ``peak_mem_mb``). The ``exact`` and ``bf16`` rows would take minutes a
  frame on a CPU: they are timed the same way on a ``--crop`` square (``bf16``: a quarter of
  it), after a warm-up on its 4×4 corner and the untimed call on the square, and extrapolated
  to the frame by floating-point operations (``extrapolated: true``); their ``peak_mem_mb`` is
  the crop's, not extrapolated.
  ``pipeline:*`` rows time :meth:`~cva_confidence_ros.pipeline.StereoPipeline.process` on the
  image pair: matching, WTA, cheap measure and network, what the node does per frame; they
  need shipped weights for D (the other rows fall back to a random network), else the run is
  refused before any row is measured.
* ``network_gflops``: operations the evaluator chose to run (counted per tile,
  :class:`~cva_confidence_ros.model.SparseEvaluator`) per second of the row's time;
  ``gemm_gflops``: a 2048² float32 matmul in the same process, the practical peak.
* ``peak_mem_mb``: peak resident memory during the untimed frame before the timed ones above
  the resident memory before it, freed heap handed back to the OS and VmHWM reset first. The
  command line keeps freed memory in the process as the node does
  (:func:`~cva_confidence_ros.memory.keep_freed_memory`), so the timed frames that follow run
  on a warm heap, as the node's frames do.
* ``threads`` / ``numba_threads``: torch's and numba's thread counts during the row
  (``--threads`` sets both, OpenCV's and the OpenMP/MKL variables for the run; ``python -m
  cva_confidence_ros.fast_benchmark`` runs on 1 unless ``--threads`` says otherwise).
* ``auc_rel``: mean AUC over the develop scenes of the configuration / that of the exact fp32
  network (the paper network at full resolution), when ``--data-root`` holds the develop split;
  None without it, and where it is undefined (windows without ground truth are skipped; an
  exact AUC of 0 has no ratio); Lite rows are relative to the same exact CVA-Net (so they
  can be < 1).
  Each scene is halved until its ground truth fits D, its census_bm cost volume computed, and
  a ``--auc-crop`` window (rows×columns, the one of nine candidate positions with the most
  ground truth) scored on its known pixels. A sparse configuration depends on the
  network only through its values at the pixels it evaluates, which equal the exact network's
  (tested to 1e-4), so the exact map of the crop is computed once and looked up for every
  configuration. ``bf16`` is the exception (other arithmetic): its AUC is measured on the
  central 10×10 pixels of every crop against the exact network's on the same pixels.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
import os
from pathlib import Path
import statistics
import sys
import time
from typing import Any, cast

import numpy as np

from cva_confidence_ros.benchmark import (
    EXIT_CODES,
    NETWORK_MATCHER,
    BenchSettings,
    _gemm_gflops,
    _network,
    _release_free_heap,
    _reset_peak,
    make_pairs,
    memory_kb,
    run_suite,
)
from cva_confidence_ros.errors import ConfigError

__all__ = ['FAST_CONFIGS', 'FastConfig', 'develop_crops', 'main', 'run_fast']


@dataclass(frozen=True)
class FastConfig:
    """One row: the ``cva_*`` options of the network and whether the whole pipeline is timed.

    Attributes:
        name: Row name.
        stride: ``cva_stride``.
        cascade: ``cva_cascade``.
        fraction: ``cva_cascade_fraction``.
        precision: ``cva_precision``.
        pipeline: Time :class:`~cva_confidence_ros.pipeline.StereoPipeline` on the image pair
            instead of the network on the cost volume.
        arch: Network: ``cvanet`` (the paper's, method ``cva_net``), ``cvanet_lite``
            (CVA-Net-Lite, method ``cva_net_lite``) or ``cvanet_fast`` (CVA-Net-Fast, method
            ``cva_net_fast``). ``auc_rel`` is relative to the exact ``cvanet`` either way.
    """

    name: str
    stride: int = 1
    cascade: str = 'none'
    fraction: float = 0.25
    precision: str = 'fp32'
    pipeline: bool = False
    arch: str = 'cvanet'

    def __post_init__(self) -> None:
        if self.arch not in _METHODS:
            raise ConfigError(f'arch must be one of {sorted(_METHODS)}; got {self.arch!r}')

    @property
    def method(self) -> str:
        """The confidence method that runs this row's network."""
        return _METHODS[self.arch]

    def sparse(self) -> Any:
        """The :class:`~cva_confidence_ros.model.SparseConfig` of this row."""
        from cva_confidence_ros.model import SparseConfig

        return SparseConfig(self.stride, self.cascade, self.fraction, self.precision)


#: Confidence method of each network architecture.
_METHODS = {'cvanet': 'cva_net', 'cvanet_lite': 'cva_net_lite', 'cvanet_fast': 'cva_net_fast'}
_LITE = 'cvanet_lite'
_FAST = 'cvanet_fast'
_TITLES = {'cvanet': 'CVA-Net', _LITE: 'CVA-Net-Lite', _FAST: 'CVA-Net-Fast'}

#: The rows of ``--suite fast``, in order.
FAST_CONFIGS: tuple[FastConfig, ...] = (
    FastConfig('exact'),
    FastConfig('bf16', precision='bf16'),
    FastConfig('stride2', stride=2),
    FastConfig('stride4', stride=4),
    FastConfig('stride8', stride=8),
    FastConfig('pkrn0.1', cascade='pkrn', fraction=0.1),
    FastConfig('pkrn0.25', cascade='pkrn', fraction=0.25),
    FastConfig('lrd0.1', cascade='lrd', fraction=0.1),
    FastConfig('lrd0.25', cascade='lrd', fraction=0.25),
    FastConfig('stride4+pkrn0.25', stride=4, cascade='pkrn', fraction=0.25),
    FastConfig('stride8+pkrn0.25', stride=8, cascade='pkrn', fraction=0.25),
    FastConfig('stride8+lrd0.25', stride=8, cascade='lrd', fraction=0.25),
    FastConfig('stride8+pkrn0.1', stride=8, cascade='pkrn', fraction=0.1),
    FastConfig('pipeline:stride8', stride=8, pipeline=True),
    FastConfig('pipeline:stride8+pkrn0.1', stride=8, cascade='pkrn', fraction=0.1, pipeline=True),
    FastConfig('lite', arch=_LITE),
    FastConfig('lite+stride2', stride=2, arch=_LITE),
    FastConfig('lite+stride4', stride=4, arch=_LITE),
    FastConfig('lite+stride8', stride=8, arch=_LITE),
    FastConfig('lite+stride4+pkrn0.25', stride=4, cascade='pkrn', fraction=0.25, arch=_LITE),
    FastConfig('lite+stride8+pkrn0.25', stride=8, cascade='pkrn', fraction=0.25, arch=_LITE),
    FastConfig('lite+stride8+pkrn0.1', stride=8, cascade='pkrn', fraction=0.1, arch=_LITE),
    FastConfig('pipeline:lite+stride2', stride=2, pipeline=True, arch=_LITE),
    FastConfig('pipeline:lite+stride4', stride=4, pipeline=True, arch=_LITE),
    FastConfig(
        'pipeline:lite+stride8+pkrn0.1', stride=8, cascade='pkrn', fraction=0.1, pipeline=True,
        arch=_LITE,
    ),
    FastConfig('fast', arch=_FAST),
    FastConfig('fast+stride2', stride=2, arch=_FAST),
    FastConfig('pipeline:fast', pipeline=True, arch=_FAST),
)
_EXTRAPOLATED = ('exact', 'bf16')
#: Environment variables of the thread pools that start after ``--threads`` is applied. Not
#: NUMBA_NUM_THREADS: numba reads it again at every compilation, and one that differs from the
#: pool it launched raised "Cannot set NUMBA_NUM_THREADS to a different value once the threads
#: have been launched" (a first run, whose kernels compile inside the block, crashed);
#: ``numba.set_num_threads`` limits the kernels instead.
_THREAD_ENV = ('OMP_NUM_THREADS', 'MKL_NUM_THREADS')
#: Develop window the AUC rows are scored on. 120×200 leaves a stride-8 grid 15×25 samples; on
#: the 48×96 windows used before (6×12 samples) most filled pixels lay in the grid's border
#: cells, which overstated the loss of the sparse rows (stride 8: 2.75 there, 1.45 here).
AUC_CROP = (120, 200)


@dataclass(frozen=True)
class _Timing:
    """Frames of one row: seconds and results of the timed ones, memory around the untimed one.

    Attributes:
        seconds: Wall time of each timed frame.
        results: What each timed frame returned.
        rss_kb: Resident memory before the untimed frame (None without ``/proc``).
        peak_kb: Peak resident memory during it (None where VmHWM cannot be reset).
    """

    seconds: list[float]
    results: list[dict[str, float]]
    rss_kb: int | None
    peak_kb: int | None


def _time_frames(frame: Callable[[], dict[str, float]], repeat: int) -> _Timing:
    """One untimed frame that gives the peak memory, then ``repeat`` timed frames.

    ``frame`` must have run once already (what a first call loads or compiles is no frame's).
    Freed heap is handed back to the OS before the untimed frame, so that the resident memory
    before it is what is live and its peak what a frame allocates. That frame pays the page
    faults of taking the memory back; the node keeps freed memory
    (:func:`~cva_confidence_ros.memory.keep_freed_memory`) and pays them on its first frame
    only, so the timed frames come after it, without a trim, as the node's later frames do.
    """
    _release_free_heap()
    rss, have_hwm = memory_kb('VmRSS'), _reset_peak()
    frame()
    peak = memory_kb('VmHWM') if have_hwm else None
    seconds, results = [], []
    for _ in range(repeat):
        start = time.perf_counter()
        results.append(frame())
        seconds.append(time.perf_counter() - start)
    return _Timing(seconds, results, rss, peak)


def _numba_threads() -> int:
    import numba

    return int(numba.get_num_threads())


@contextmanager
def _thread_limit(threads: int | None) -> Iterator[None]:
    """Run torch, numba and OpenCV on ``threads`` threads inside the block, and set the
    OpenMP/MKL/numba variables for pools started in it; all restored on exit. None: no change.

    numba can use at most the ``NUMBA_NUM_THREADS`` it was imported with; the records report
    what it really used (``numba_threads``).
    """
    if threads is None:
        yield
        return
    if threads < 1:
        raise ConfigError(f'threads must be ≥ 1; got {threads}')
    import cv2
    import numba
    import torch

    saved_env = {name: os.environ.get(name) for name in _THREAD_ENV}
    saved = numba.get_num_threads(), torch.get_num_threads(), cv2.getNumThreads()
    try:
        os.environ.update({name: str(threads) for name in _THREAD_ENV})
        # numba's OpenMP layer resets the OpenMP thread count that torch also uses: numba first.
        available = int(numba.config.NUMBA_NUM_THREADS)  # type: ignore[attr-defined]
        numba.set_num_threads(min(threads, available))
        torch.set_num_threads(threads)
        cv2.setNumThreads(threads)
        yield
    finally:
        numba.set_num_threads(saved[0])
        torch.set_num_threads(saved[1])
        cv2.setNumThreads(saved[2])
        for name, value in saved_env.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def _cheap(name: str, volume: np.ndarray, disparity: np.ndarray, image: np.ndarray,
           volume_right: np.ndarray | None, first_column: int = 0) -> np.ndarray | None:
    from cva_confidence_ros.confidence import CONFIDENCE_METHODS, ConfidenceInputs

    if name == 'none':
        return None
    inputs = ConfidenceInputs(volume, disparity, image, cost_volume_right=volume_right,
                              first_column=first_column)
    return CONFIDENCE_METHODS.get(name)()(inputs)


def develop_crops(
    root: Path, max_disparity: int, crop: tuple[int, int]
) -> list[dict[str, Any]]:
    """Cost-volume crops of the develop scenes with their error labels.

    Args:
        root: Data root holding the develop data sets.
        max_disparity: D.
        crop: (rows, columns) of the scored window.

    Returns:
        One dict per scene: ``name``, ``volume`` (D, h, w), ``volume_right``, ``disparity``,
        ``image``, ``wrong`` (h, w) bool, ``known`` (h, w) bool, ``x0`` (the image column of
        the window's column 0).
    """
    from cva_confidence_ros.datasets import DEVELOP_DATASETS, list_scenes, load_scene
    from cva_confidence_ros.datasets.resize import fit_disparity_range
    from cva_confidence_ros.matching import compute_cost_volume, wta_disparity
    from cva_confidence_ros.metrics import kitti_error

    crops = []
    for dataset in DEVELOP_DATASETS:
        for scene in list_scenes(dataset, root):
            sample, _ = fit_disparity_range(load_scene(dataset, root, scene), max_disparity)
            known = np.isfinite(sample.disparity)
            height, width = known.shape
            rows, columns = min(crop[0], height), min(crop[1], width)
            best, window = -1, (0, 0)
            for fy in (0.25, 0.5, 0.75):
                for fx in (0.25, 0.5, 0.75):
                    y0 = int(fy * (height - rows))
                    x0 = int(fx * (width - columns))
                    count = int(known[y0:y0 + rows, x0:x0 + columns].sum())
                    if count > best:
                        best, window = count, (y0, x0)
            y0, x0 = window
            box = (slice(y0, y0 + rows), slice(x0, x0 + columns))
            volume = compute_cost_volume(sample.left, sample.right, NETWORK_MATCHER, max_disparity)
            right = compute_cost_volume(
                sample.left, sample.right, NETWORK_MATCHER, max_disparity, view='right'
            )
            disparity = wta_disparity(volume)
            gt = sample.disparity[box]
            crops.append({
                'name': f'{dataset}/{scene}',
                'volume': np.ascontiguousarray(volume[:, box[0], box[1]]),
                'volume_right': np.ascontiguousarray(right[:, box[0], box[1]]),
                'disparity': np.ascontiguousarray(disparity[box]),
                'image': np.ascontiguousarray(sample.left[box]),
                'wrong': kitti_error(disparity[box], np.nan_to_num(gt)),
                'known': np.isfinite(gt),
                'x0': x0,
            })
            print(f'  develop crop {dataset}/{scene}: {rows}×{columns}, {best} known pixels',
                  file=sys.stderr, flush=True)
    return crops


def _auc_rel(configs: Sequence[FastConfig], crops: list[dict[str, Any]], net: Any,
             log: Callable[[str], None], others: dict[str, Any] | None = None
             ) -> dict[str, float]:
    """Mean develop AUC of each row / that of the exact CVA-Net (``net``); rows of another
    architecture look up the exact map of ``others[arch]`` instead, still relative to CVA-Net."""
    from cva_confidence_ros.metrics import roc_auc
    from cva_confidence_ros.model import SparseEvaluator, sparse_confidence

    evaluator = SparseEvaluator(net)
    bf16 = SparseEvaluator(net, precision='bf16')
    want_bf16 = any(c.name == 'bf16' for c in configs)
    others = others or {}
    light = {}
    for arch in sorted({c.arch for c in configs} - {'cvanet'}):
        if arch not in others:
            raise ConfigError(f'{_TITLES[arch]} rows need the {_TITLES[arch]} network')
        light[arch] = SparseEvaluator(others[arch])
    aucs: dict[str, list[float]] = {c.name: [] for c in configs}
    exact_aucs: list[float] = []
    bf16_pairs: list[tuple[float, float]] = []
    for item in crops:
        tic = time.perf_counter()
        known, wrong = item['known'], item['wrong']
        if not known.any():
            log(f'  AUC of {item["name"]}: skipped, no ground truth in its window')
            continue
        exact = evaluator(item['volume'])
        exact_auc = roc_auc(exact[known], wrong[known])
        exact_aucs.append(exact_auc)
        light_exact = {arch: light[arch](item['volume']) for arch in light}
        for config in configs:
            if config.name in _EXTRAPOLATED:
                continue
            cheap = _cheap(config.cascade, item['volume'], item['disparity'], item['image'],
                           item['volume_right'], item.get('x0', 0))
            values = light_exact.get(config.arch, exact)
            result = sparse_confidence(
                cast('Callable[[np.ndarray, np.ndarray], np.ndarray]',
                     lambda _v, _m, values=values: values),
                item['volume'], item['image'],
                item['disparity'], config.sparse(), cheap,
            )
            aucs[config.name].append(roc_auc(result.confidence[known], wrong[known]))
        rows, columns = known.shape
        centre = (slice(rows // 2 - 5, rows // 2 + 5), slice(columns // 2 - 5, columns // 2 + 5))
        sub_known, sub_wrong = known[centre], wrong[centre]
        if want_bf16 and sub_known.sum() > 1:
            low = bf16(np.ascontiguousarray(item['volume'][:, centre[0], centre[1]]))
            bf16_pairs.append((roc_auc(low[sub_known], sub_wrong[sub_known]),
                               roc_auc(exact[centre][sub_known], sub_wrong[sub_known])))
        log(f'  AUC of {item["name"]}: exact {exact_auc:.4f} '
            f'({time.perf_counter() - tic:.0f} s)')
    out: dict[str, float] = {}
    if bf16_pairs:
        low_mean, ref_mean = np.mean(bf16_pairs, axis=0)
        if ref_mean > 0:
            out['bf16'] = float(low_mean / ref_mean)
    mean_exact = float(np.mean(exact_aucs)) if exact_aucs else 0.0
    if mean_exact <= 0:
        # No scored pixel, or none wrong: the exact AUC is 0 and no ratio to it exists.
        log('  auc_rel undefined: the exact network scored no wrong pixel (AUC 0) on the '
            f'{len(exact_aucs)} window(s) with ground truth')
        return out
    out.update(
        {name: float(np.mean(values)) / mean_exact for name, values in aucs.items() if values}
    )
    out['exact'] = 1.0
    return out


def run_fast(
    settings: BenchSettings,
    configs: Sequence[FastConfig] = FAST_CONFIGS,
    crop: int = 48,
    data_root: Path | None = None,
    auc_crop: tuple[int, int] = AUC_CROP,
    log: Callable[[str], None] = lambda text: print(text, file=sys.stderr, flush=True),
    gemm_size: int = 2048,
    threads: int | None = None,
) -> list[dict[str, Any]]:
    """Measure the fast-path rows in this process (see the module docstring).

    Args:
        settings: Frame size, D and timed frames per row.
        configs: The rows.
        crop: Side of the crop the extrapolated rows are timed on.
        data_root: Root with the develop split, or None (``auc_rel`` None).
        auc_crop: (rows, columns) of the AUC window of each develop scene.
        log: Progress messages.
        gemm_size: Side of the float32 matmul that gives ``gemm_gflops``.
        threads: Threads of torch, numba and OpenCV for the run (restored after it); None
            leaves them as they are.

    Returns:
        One record per configuration with :data:`RECORD_KEYS` plus ``network_share`` (share of
        the pixels the network ran on), ``extrapolated``, ``timed_calls``, ``threads``,
        ``numba_threads`` and, for cascades, ``cheap_ms``.

    Raises:
        ConfigError: ``threads`` < 1, rows of a network that cannot be built, or pipeline
            rows without shipped weights for D (refused before any row is measured).
    """
    with _thread_limit(threads):
        return _measure_rows(settings, configs, crop, data_root, auc_crop, log, gemm_size)


def _measure_rows(
    settings: BenchSettings,
    configs: Sequence[FastConfig],
    crop: int,
    data_root: Path | None,
    auc_crop: tuple[int, int],
    log: Callable[[str], None],
    gemm_size: int,
) -> list[dict[str, Any]]:
    import torch

    from cva_confidence_ros.matching import compute_cost_volume, wta_disparity
    from cva_confidence_ros.model import SparseEvaluator, resolve_device
    from cva_confidence_ros.pipeline import PipelineConfig, StereoPipeline

    device = resolve_device('cpu')
    depth = settings.max_disparity
    _check_pipeline_weights(configs, depth)
    # CVA-Net is needed by its own rows and as the AUC reference; Lite and Fast rows alone
    # also run at a D below its minimum.
    needed = data_root is not None or any(c.arch == 'cvanet' for c in configs)
    net, note = _network(NETWORK_MATCHER, depth) if needed else (None, None)
    light = {
        arch: _light_network(depth, arch) for arch in {c.arch for c in configs} - {'cvanet'}
    }
    left, right = make_pairs(settings)['real']
    volume = compute_cost_volume(left, right, NETWORK_MATCHER, depth)
    volume_right = compute_cost_volume(left, right, NETWORK_MATCHER, depth, view='right')
    disparity = wta_disparity(volume)
    gemm = _gemm_gflops(device, gemm_size)
    auc_rel: dict[str, float] = {}
    if data_root is not None:
        log(f'develop-split AUC on {auc_crop[0]}×{auc_crop[1]} crops …')
        auc_rel = _auc_rel(
            configs, develop_crops(data_root, depth, auc_crop), net, log,
            {arch: pair[0] for arch, pair in light.items()},
        )
    records = []
    for config in configs:
        log(f'measuring {config.name} …')
        row_net, row_note = light.get(config.arch, (net, note))
        evaluator = SparseEvaluator(row_net, device, precision=config.precision)
        record: dict[str, Any] = {
            'config': config.name,
            'device': device.type,
            'width': settings.width,
            'height': settings.height,
            'max_disparity': depth,
            'gemm_gflops': gemm,
            'auc_rel': auc_rel.get(config.name),
            'threads': torch.get_num_threads(),
            'numba_threads': _numba_threads(),
            'timed_calls': settings.repeat,
            'extrapolated': config.name in _EXTRAPOLATED,
            'arch': config.arch,
        }
        if row_note is not None:
            record['note'] = row_note
        if config.name in _EXTRAPOLATED:
            side = crop if config.precision == 'fp32' else max(4, crop // 4)
            rows, columns = min(side, settings.height), min(side, settings.width)
            y0, x0 = (settings.height - rows) // 2, (settings.width - columns) // 2
            part = np.ascontiguousarray(volume[:, y0:y0 + rows, x0:x0 + columns])
            evaluator(part[:, :4, :4])  # loads what every call shares, at a fraction of the cost
            frame = evaluator._flops('tile', settings.height, settings.width)

            def crop_call(evaluator: Any = evaluator, part: np.ndarray = part
                          ) -> dict[str, float]:
                evaluator(part)
                return {}

            flops_before = evaluator.flops_done
            timing = _time_frames(crop_call, settings.repeat)
            # Every call on the crop runs the same operations: the untimed one included.
            done = (evaluator.flops_done - flops_before) / (settings.repeat + 1)
            seconds = statistics.median(timing.seconds)
            record.update(ms_per_frame=seconds * frame / done * 1e3,
                          network_gflops=done / seconds / 1e9, network_share=1.0,
                          crop=[rows, columns])
        else:
            sparse = config.sparse()
            frame_fn: Callable[[], dict[str, float]]
            if config.pipeline:
                pipeline = StereoPipeline(PipelineConfig(
                    matcher=NETWORK_MATCHER, max_disparity=depth, device='cpu',
                    confidence_method=config.method,
                    model_path=_weights_path(depth, config.arch), cva_stride=config.stride,
                    cva_cascade=config.cascade, cva_cascade_fraction=config.fraction,
                    cva_precision=config.precision,
                ))
                pipeline.warm_up()
                evaluator = pipeline._method.evaluator  # type: ignore[attr-defined]

                def pipeline_frame(pipeline: Any = pipeline) -> dict[str, float]:
                    return pipeline.process(left, right).timings_ms

                frame_fn = pipeline_frame
            else:
                def sparse_frame(
                    evaluator: Any = evaluator, sparse: Any = sparse
                ) -> dict[str, float]:
                    tic = time.perf_counter()
                    cheap = _cheap(sparse.cascade, volume, disparity, left,
                                   volume_right if sparse.cascade == 'lrd' else None)
                    cheap_ms = (time.perf_counter() - tic) * 1e3
                    result = evaluator.confidence(volume, left, disparity, sparse, cheap)
                    return {'cheap': cheap_ms, 'share': result.network_share}

                frame_fn = sparse_frame
            frame_fn()  # warm-up: first-call costs (kernels, caches) are no frame's
            flops_before = evaluator.flops_done
            timing = _time_frames(frame_fn, settings.repeat)
            extras = timing.results
            # The frames are the same: the untimed one ran the operations of a timed one.
            done = (evaluator.flops_done - flops_before) / (settings.repeat + 1)
            seconds = statistics.median(timing.seconds)
            record.update(ms_per_frame=seconds * 1e3, network_gflops=done / seconds / 1e9)
            if config.pipeline:
                record['stages_ms'] = {key: statistics.median(e[key] for e in extras)
                                       for key in extras[0]}
            else:
                record['network_share'] = extras[0]['share']
                record['cheap_ms'] = statistics.median(e['cheap'] for e in extras)
        peak, rss = timing.peak_kb, timing.rss_kb
        record['peak_mem_mb'] = (
            max(peak - rss, 0) / 1024.0 if peak is not None and rss is not None else None
        )
        log(f"  {config.name}: {record['ms_per_frame']:.0f} ms/frame, auc_rel "
            f"{record['auc_rel'] if record['auc_rel'] is None else round(record['auc_rel'], 4)}")
        records.append(record)
    return records


def _check_pipeline_weights(configs: Sequence[FastConfig], depth: int) -> None:
    """Refuse pipeline rows without shipped weights before anything is measured: the pipeline
    loads them (the other rows fall back to a random network), and it used to fail only when
    its row came, after every row before it had been measured."""
    from cva_confidence_ros.errors import ModelError
    from cva_confidence_ros.model import default_weights_path

    missing: dict[str, list[str]] = {}
    for config in configs:
        if config.pipeline:
            try:
                default_weights_path(NETWORK_MATCHER, depth, config.arch)
            except ModelError:
                missing.setdefault(config.arch, []).append(config.name)
    if missing:
        which = '; '.join(f'{_TITLES[arch]} for {names}' for arch, names in missing.items())
        raise ConfigError(
            f'pipeline rows need shipped {NETWORK_MATCHER} weights at D = {depth}, and there '
            f'are none: {which}; leave these rows out (--configs) or choose a D with shipped '
            'weights'
        )


def _weights_path(depth: int, arch: str = 'cvanet') -> str:
    from cva_confidence_ros.errors import ModelError
    from cva_confidence_ros.model import default_weights_path

    try:
        return str(default_weights_path(NETWORK_MATCHER, depth, arch))
    except ModelError:
        return ''


def _light_network(depth: int, arch: str) -> tuple[Any, str | None]:
    """Shipped CVA-Net-Lite or -Fast weights for (census_bm, D), else a seeded random network
    and why."""
    import torch

    from cva_confidence_ros.errors import ModelError
    from cva_confidence_ros.model import ARCHITECTURES, default_weights_path, load_weights

    try:
        path = default_weights_path(NETWORK_MATCHER, depth, arch)
    except ModelError:
        torch.manual_seed(0)
        return ARCHITECTURES.get(arch)({'max_disparity': depth}).eval(), (
            f'random init: no shipped {_TITLES[arch]} weights for {NETWORK_MATCHER}, '
            f'D = {depth} (speed does not depend on weight values; auc_rel is meaningless)'
        )
    net, _ = load_weights(path, matcher=NETWORK_MATCHER, max_disparity=depth, arch=arch)
    return net, None


def format_fast_table(records: Sequence[dict[str, Any]]) -> str:
    """Markdown table of the fast-path records."""
    first = records[0]
    threads = first.get('threads', '?')
    numba = first.get('numba_threads', threads)
    used = (f'{threads} thread(s)' if numba == threads
            else f'{threads} torch / {numba} numba threads')
    lines = [
        f"{first['width']}×{first['height']}, D = {first['max_disparity']}, {used}, "
        'census_bm cost volume of the Motorcycle pair',
        '',
        '| config | ms/frame | fps | network share | network GFLOP/s | GEMM GFLOP/s '
        '| peak MiB | auc_rel |',
        '|---|---:|---:|---:|---:|---:|---:|---:|',
    ]
    for r in records:
        auc = '—' if r.get('auc_rel') is None else f"{r['auc_rel']:.3f}"
        share = r.get('network_share')
        mark = ' *' if r.get('extrapolated') else ''
        peak = r.get('peak_mem_mb')
        lines.append(
            f"| {r['config']}{mark} | {r['ms_per_frame']:.0f} | {1e3 / r['ms_per_frame']:.3f} "
            f"| {'—' if share is None else f'{share:.1%}'} | {r['network_gflops']:.1f} "
            f"| {r['gemm_gflops']:.1f} | {'—' if peak is None else f'{peak:.0f}'} | {auc} |"
        )
    if any(r.get('extrapolated') for r in records):
        lines.append('* timed on a crop, extrapolated to the frame by FLOPs; peak MiB is the '
                     "crop's")
    return '\n'.join(lines)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='cva-benchmark --suite fast',
        description='CVA-Net fast paths (sparse grid, cascades, bf16): ms per frame, GFLOP/s, '
        'peak memory and develop-split AUC relative to the exact network.',
        epilog=EXIT_CODES,
    )
    parser.add_argument('--width', type=int, default=320)
    parser.add_argument('--height', type=int, default=240)
    parser.add_argument('--max-disparity', type=int, default=64)
    parser.add_argument('--repeat', type=int, default=1, help='timed frames per row')
    parser.add_argument('--configs', nargs='+', default=None, metavar='NAME',
                        help=f'rows to run (default all: {[c.name for c in FAST_CONFIGS]})')
    parser.add_argument('--crop', type=int, default=48, metavar='PIXELS',
                        help='side of the crop the exact row is timed on (bf16: a quarter)')
    parser.add_argument('--data-root', type=Path, default=None,
                        help='data root with the develop split (e.g. ../shared/data) for auc_rel')
    parser.add_argument('--auc-crop', default=f'{AUC_CROP[0]}x{AUC_CROP[1]}',
                        metavar='ROWSxCOLUMNS',
                        help='window of every develop scene that the AUC is computed on '
                        '(default %(default)s)')
    parser.add_argument('--threads', type=int, default=None, metavar='N',
                        help='torch, numba and OpenCV threads for the run, and the OpenMP/MKL '
                        'variables (default: as they are; python -m '
                        'cva_confidence_ros.fast_benchmark: 1)')
    parser.add_argument('--json', type=Path, default=None, metavar='PATH')
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``cva-benchmark --suite fast``; returns the exit code."""
    def measure(args: argparse.Namespace, settings: BenchSettings) -> list[dict[str, Any]]:
        by_name = {c.name: c for c in FAST_CONFIGS}
        names = args.configs or list(by_name)
        unknown = [n for n in names if n not in by_name]
        if unknown:
            raise ConfigError(f'unknown fast configs {unknown}; expected {list(by_name)}')
        try:
            rows, columns = (int(v) for v in args.auc_crop.lower().split('x'))
        except ValueError as exc:
            raise ConfigError(f'--auc-crop must be ROWSxCOLUMNS; got {args.auc_crop!r}') from exc
        if args.crop < 4:
            raise ConfigError(f'--crop must be ≥ 4 pixels; got {args.crop}')
        if rows < 16 or columns < 16:
            raise ConfigError(f'--auc-crop must be at least 16x16; got {args.auc_crop!r}')
        from cva_confidence_ros.memory import keep_freed_memory

        keep_freed_memory()  # as the node does, so that the timed frames see the node's heap
        return run_fast(settings, [by_name[n] for n in names], args.crop, args.data_root,
                        (rows, columns), threads=args.threads)

    extra = ('network_share', 'extrapolated', 'crop', 'timed_calls', 'threads', 'numba_threads',
             'cheap_ms', 'stages_ms', 'note', 'arch')
    return run_suite(_parser(), argv, measure, format_fast_table, extra)


if __name__ == '__main__':
    # One thread unless the command line asks for more (of two --threads the later counts).
    sys.exit(main(['--threads', '1', *sys.argv[1:]]))

"""Speed and memory of the matchers, side by side with OpenCV's StereoSGBM (``cva-benchmark``).

Every configuration runs in a fresh subprocess, so that its peak memory is its own and no
earlier configuration's caches or heap help it. Inside the subprocess:

1. the two pairs are built: the scikit-image Motorcycle pair (Middlebury 2014) resized and
   centre-cropped to the requested size, and a fixed synthetic pair (seeded random texture,
   horizontal bands of known disparity);
2. untimed frames: one on a small crop (numba loads or compiles its kernels, torch loads
   weights), then one per pair at full size;
3. the peak-RSS mark is reset (``/proc/self/clear_refs``), then ``--repeat`` rounds of one
   frame per pair are timed with ``time.perf_counter``; the peak is read after the first
   round. Each round of a matcher is followed by a round of OpenCV SGBM frames, the reference
   of its ratio: interleaving keeps the ratio fair on a machine whose load drifts (the SGBM
   row itself still comes from its own subprocess, for its memory).

A frame goes from the image pair to a disparity map: for a matcher the cost volume plus the
winner-takes-all disparity, for OpenCV ``StereoSGBM.compute`` (MODE_HH, 8 paths) on the gray
pair. ``ms_per_frame`` is the median over all timed frames. ``peak_mem_mb`` is the peak
resident memory during the first timed round minus the resident memory before the full-size
warm-up, taken after one frame on a small crop has loaded what all frames share (libraries,
JIT code, weights): it is what a frame needs, work buffers that a matcher keeps between
frames included. After the warm-up, freed heap is returned to the OS (``malloc_trim``) and
the peak mark reset, so that one-off costs do not count; the peak is VmHWM from
``/proc/self/status`` (``ru_maxrss`` where the mark cannot be reset, which then includes
the warm-up; None, a dash in the table, where the resident memory before cannot be read).

Configurations are entries of :data:`CASES`; the matchers of
:data:`cva_confidence_ros.matching.MATCHERS` and ``opencv_sgbm`` are registered here. A later
configuration registers a factory returning a :class:`Case` whose ``extras`` fill
``network_gflops``, ``gemm_gflops`` or ``auc_rel``.

The CVA-Net row ``cvanet_d<D>`` (``--network``, on by default) is measured apart, in a
subprocess of its own, by :func:`run_network`: the whole frame would take minutes on a CPU,
so :func:`cva_confidence_ros.model.predict_confidence` (batch normalisation folded, inference
mode) runs on a ``--network-crop`` square of the Motorcycle frame's cost volume, and the
frame's time is extrapolated by the ratio of floating-point operations (``extrapolated:
true``). ``network_gflops`` is the rate achieved on the crop, ``gemm_gflops`` the best rate of
a 2048×2048 float32 ``torch.matmul`` in the same process (same device and threads): the
practical peak. ``auc_rel`` is 1.0: this full-precision paper network is the reference that
faster variants report their AUC against.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
import ctypes
import ctypes.util
from dataclasses import dataclass, field
import json
import math
import os
from pathlib import Path
import platform
import resource
import statistics
import subprocess
import sys
import time
from typing import Any

import cv2
import numpy as np

from cva_confidence_ros import strict_json
from cva_confidence_ros.errors import (
    ConfigError,
    CVAError,
    ModelError,
    closed_stdout,
    from_interrupt,
    interrupted_exit,
    sigterm_as_interrupt,
    stdout_closed,
)
from cva_confidence_ros.outputs import check_output_file
from cva_confidence_ros.registry import Registry

__all__ = [
    'CASES',
    'NETWORK_MATCHER',
    'RECORD_KEYS',
    'BenchSettings',
    'Case',
    'host_summary',
    'main',
    'make_pairs',
    'run_case',
    'run_network',
    'run_suite',
    'write_records',
]

#: Keys of every record written by ``--json``.
RECORD_KEYS = (
    'config',
    'device',
    'width',
    'height',
    'max_disparity',
    'ms_per_frame',
    'peak_mem_mb',
    'network_gflops',
    'gemm_gflops',
    'auc_rel',
)
#: Matcher whose cost volume feeds the CVA-Net row (its shipped weights are used if present).
NETWORK_MATCHER = 'census_bm'
_BASELINE = 'opencv_sgbm'
_WORKER_FLAG = '--worker'
_NETWORK_WORKER_FLAG = '--network-worker'
_NETWORK_PREFIX = 'cvanet_d'
_GEMM_SIZE = 2048
_RECORD_PREFIX = 'BENCH-RECORD '
#: Keys of the ``cvanet_d<D>`` record that ``--json`` keeps beyond :data:`RECORD_KEYS` (the
#: README's network-row table quotes the crop and the threads).
_NETWORK_EXTRA_KEYS = ('extrapolated', 'crop', 'crop_ms', 'threads', 'note')
# What the matcher table's per-pair, volume and paired-SGBM columns (and its × SGBM ratio)
# are computed from: in the JSON too, so that it holds the table's numbers.
_MATCHER_EXTRA_KEYS = ('per_pair_ms', 'stages_ms', 'paired_sgbm_ms', *_NETWORK_EXTRA_KEYS)
_SUITES = ('matchers', 'node', 'fast', 'gpu', 'cloud')


@dataclass(frozen=True)
class BenchSettings:
    """What every configuration is measured on.

    Attributes:
        width: Image width in pixels (> max_disparity).
        height: Image height in pixels (≥ 8).
        max_disparity: Cost-volume depth D (≥ 1).
        repeat: Timed frames per pair (≥ 1).
    """

    width: int = 640
    height: int = 480
    max_disparity: int = 128
    repeat: int = 5

    def __post_init__(self) -> None:
        if self.height < 8 or self.width < 16:
            raise ConfigError(f'images must be at least 16×8; got {self.width}×{self.height}')
        if not 1 <= self.max_disparity < self.width:
            raise ConfigError(
                f'max_disparity must be in [1, width); got {self.max_disparity} for width '
                f'{self.width}'
            )
        if self.repeat < 1:
            raise ConfigError(f'repeat must be ≥ 1; got {self.repeat}')


@dataclass
class Case:
    """One benchmarked configuration, ready to run frames.

    Attributes:
        frame: Processes one (left, right) uint8 RGB pair; returns stage timings in ms (may be
            empty) — the frame itself is timed by the caller.
        device: Where it runs (``cpu``, ``cuda``…).
        extras: Values of ``network_gflops``, ``gemm_gflops``, ``auc_rel`` (None if absent).
    """

    frame: Callable[[np.ndarray, np.ndarray], dict[str, float]]
    device: str = 'cpu'
    extras: dict[str, float | None] = field(default_factory=dict)


#: Configuration name → factory ``(settings) -> Case``.
CASES: Registry[Callable[[BenchSettings], Case]] = Registry('benchmark configuration')


def _matcher_case(name: str) -> Callable[[BenchSettings], Case]:
    def factory(settings: BenchSettings) -> Case:
        from cva_confidence_ros.matching import compute_cost_volume, wta_disparity

        def frame(left: np.ndarray, right: np.ndarray) -> dict[str, float]:
            start = time.perf_counter()
            volume = compute_cost_volume(left, right, name, settings.max_disparity)
            middle = time.perf_counter()
            wta_disparity(volume)
            end = time.perf_counter()
            return {'volume': (middle - start) * 1e3, 'wta': (end - middle) * 1e3}

        return Case(frame=frame)

    return factory


_SGBM_BLOCK = 5


def _sgbm_disparities(max_disparity: int) -> int:
    """OpenCV's numDisparities for D: a multiple of 16."""
    return -(-max_disparity // 16) * 16


def _sgbm_min_width(max_disparity: int) -> int:
    """Narrowest image OpenCV's SGBM accepts for D (numDisparities + half a block + 1)."""
    return _sgbm_disparities(max_disparity) + _SGBM_BLOCK // 2 + 1


def _sgbm_case(settings: BenchSettings) -> Case:
    block = _SGBM_BLOCK
    disparities = _sgbm_disparities(settings.max_disparity)
    # OpenCV's stubs lack the StereoSGBM_create alias (kept for older OpenCV builds).
    sgbm = cv2.StereoSGBM_create(  # type: ignore[attr-defined]
        minDisparity=0,
        numDisparities=disparities,
        blockSize=block,
        P1=8 * block * block,
        P2=32 * block * block,
        mode=cv2.STEREO_SGBM_MODE_HH,
    )

    def frame(left: np.ndarray, right: np.ndarray) -> dict[str, float]:
        gray_left = cv2.cvtColor(left, cv2.COLOR_RGB2GRAY)
        gray_right = cv2.cvtColor(right, cv2.COLOR_RGB2GRAY)
        sgbm.compute(gray_left, gray_right)
        return {}

    return Case(frame=frame)


def _register_defaults() -> None:
    from cva_confidence_ros.matching import MATCHERS

    for name in MATCHERS.names():
        CASES.add(name, _matcher_case(name))
    CASES.add(_BASELINE, _sgbm_case)


_register_defaults()


def _fit(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """Resize so that the image covers width×height, then crop the centre."""
    rows, cols = image.shape[:2]
    scale = max(width / cols, height / rows)
    size = (max(width, round(cols * scale)), max(height, round(rows * scale)))
    interpolation = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
    resized = cv2.resize(image, size, interpolation=interpolation)
    top = (size[1] - height) // 2
    left = (size[0] - width) // 2
    return np.ascontiguousarray(resized[top:top + height, left:left + width])


def _synthetic_pair(width: int, height: int, max_disparity: int) -> tuple[np.ndarray, np.ndarray]:
    """Seeded smooth random texture in horizontal bands, each band at its own disparity."""
    rng = np.random.default_rng(2019)
    texture: np.ndarray = rng.integers(
        0, 256, (height, width + max_disparity, 3), dtype=np.uint8
    )
    texture = cv2.GaussianBlur(texture, (3, 3), 0.8)
    bands = 6
    left = np.ascontiguousarray(texture[:, :width])
    right = np.empty_like(left)
    for band in range(bands):
        rows = slice(band * height // bands, (band + 1) * height // bands)
        disparity = (band + 1) * (max_disparity - 1) // (bands + 1)
        # right(y, x) = left(y, x + d): the scene point of left x appears at x − d on the right
        right[rows] = texture[rows, disparity:disparity + width]
    return left, right


def make_pairs(settings: BenchSettings) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The benchmark pairs: ``real`` (Motorcycle, resized and cropped) and ``synthetic``.

    Returns:
        Name → (left, right) (H, W, 3) uint8 RGB images of the requested size.
    """
    from skimage import data

    left, right, _ = data.stereo_motorcycle()
    width, height = settings.width, settings.height
    return {
        'real': (_fit(left, width, height), _fit(right, width, height)),
        'synthetic': _synthetic_pair(width, height, settings.max_disparity),
    }


def memory_kb(field_name: str) -> int | None:
    """A ``/proc/self/status`` field in kB (e.g. ``VmRSS``, ``VmHWM``); None if unreadable."""
    try:
        with open('/proc/self/status', encoding='ascii', errors='replace') as status:
            for line in status:
                if line.startswith(field_name + ':'):
                    return int(line.split()[1])
    except OSError:
        return None
    return None


def _release_free_heap() -> None:
    """Hand freed heap pages back to the OS (glibc), so that the resident memory before the
    timed frames is what is live, and the peak shows what a frame really allocates."""
    try:
        ctypes.CDLL(ctypes.util.find_library('c') or 'libc.so.6').malloc_trim(0)
    except (OSError, AttributeError):
        pass  # not glibc: the peak can only be lower than the truth, never inflated


def _reset_peak() -> bool:
    try:
        with open('/proc/self/clear_refs', 'w', encoding='ascii') as clear:
            clear.write('5')  # resets VmHWM to the current RSS (Linux ≥ 4.0)
        return True
    except OSError:
        return False


def _max_rss_kb() -> int:
    """Peak resident size of this process so far, in kB (``ru_maxrss``: kB on Linux, bytes
    on macOS)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak // 1024 if sys.platform == 'darwin' else peak


def _timed(case: Case, left: np.ndarray, right: np.ndarray) -> tuple[float, dict[str, float]]:
    start = time.perf_counter()
    stage_times = case.frame(left, right)
    return (time.perf_counter() - start) * 1e3, stage_times


def run_case(name: str, settings: BenchSettings) -> dict[str, Any]:
    """Measure one configuration in this process.

    The first timed round also gives the peak memory (nothing else runs in it). For any
    configuration other than the baseline, every timed round is followed by a round of
    OpenCV SGBM frames on the same pairs, so that the ratio to SGBM compares frames run
    seconds, not minutes, apart on a machine whose load may drift.

    Returns:
        A record with :data:`RECORD_KEYS` plus ``per_pair_ms`` (median per pair),
        ``stages_ms`` (median of each stage the case reports) and ``paired_sgbm_ms`` (median
        of the interleaved SGBM frames, None for the baseline), used for the printed table.
    """
    case = CASES.get(name)(settings)
    baseline = CASES.get(_BASELINE)(settings) if name != _BASELINE else None
    pairs = make_pairs(settings)
    # A frame on a small crop loads what every frame shares (libraries imported lazily, JIT
    # code, weights), so that the memory measured below is the frames' own.
    wide = max(settings.max_disparity, _sgbm_disparities(settings.max_disparity)) + 16
    small = slice(0, 16), slice(0, min(settings.width, wide))
    for runner in (case, baseline):
        if runner is not None:
            left, right = pairs['synthetic']
            runner.frame(np.ascontiguousarray(left[small]), np.ascontiguousarray(right[small]))
    rss_before = memory_kb('VmRSS')  # None without /proc: no peak of the frames' own
    for left, right in pairs.values():
        case.frame(left, right)
        if baseline is not None:
            baseline.frame(left, right)
    _release_free_heap()
    have_hwm = _reset_peak()
    peak: int | None = None
    times: dict[str, list[float]] = {pair: [] for pair in pairs}
    stages: dict[str, list[float]] = {}
    paired: list[float] = []
    for round_index in range(settings.repeat):
        for pair, (left, right) in pairs.items():
            elapsed, stage_times = _timed(case, left, right)
            times[pair].append(elapsed)
            for stage, value in stage_times.items():
                stages.setdefault(stage, []).append(value)
        if round_index == 0:
            peak = memory_kb('VmHWM') if have_hwm else None
            if peak is None:
                peak = _max_rss_kb()  # it also covers the untimed warm-up frames
        if baseline is not None:
            for left, right in pairs.values():
                paired.append(_timed(baseline, left, right)[0])
    record: dict[str, Any] = {
        'config': name,
        'device': case.device,
        'width': settings.width,
        'height': settings.height,
        'max_disparity': settings.max_disparity,
        'ms_per_frame': statistics.median([t for pair in times.values() for t in pair]),
        'peak_mem_mb': (
            max(peak - rss_before, 0) / 1024.0
            if peak is not None and rss_before is not None
            else None
        ),
        'network_gflops': case.extras.get('network_gflops'),
        'gemm_gflops': case.extras.get('gemm_gflops'),
        'auc_rel': case.extras.get('auc_rel'),
        'per_pair_ms': {pair: statistics.median(values) for pair, values in times.items()},
        'stages_ms': {stage: statistics.median(values) for stage, values in stages.items()},
        'paired_sgbm_ms': statistics.median(paired) if paired else None,
    }
    return record


def _gemm_gflops(device: Any, size: int = _GEMM_SIZE, repeat: int = 3) -> float:
    """Best float32 ``torch.matmul`` rate of two size×size matrices on ``device``, GFLOP/s."""
    import torch

    generator = torch.Generator().manual_seed(0)
    a = torch.rand(size, size, generator=generator).to(device)
    b = torch.rand(size, size, generator=generator).to(device)
    best = float('inf')
    with torch.inference_mode():
        torch.matmul(a, b)  # untimed: loads the kernels, warms the caches
        for _ in range(repeat):
            if device.type == 'cuda':
                torch.cuda.synchronize(device)
            start = time.perf_counter()
            torch.matmul(a, b)
            if device.type == 'cuda':
                torch.cuda.synchronize(device)
            best = min(best, time.perf_counter() - start)
    return 2.0 * size**3 / best / 1e9


def _network(matcher: str, max_disparity: int) -> tuple[Any, str | None]:
    """Shipped CVA-Net weights for (matcher, D), else a seeded random one and why."""
    import torch

    from cva_confidence_ros.model import CVANet, default_weights_path, load_weights

    try:
        path = default_weights_path(matcher, max_disparity)
    except ModelError:
        torch.manual_seed(0)
        return CVANet(max_disparity).eval(), (
            f'random init: no shipped weights for {matcher}, D = {max_disparity} '
            '(speed does not depend on weight values)'
        )
    net, _ = load_weights(path, matcher=matcher, max_disparity=max_disparity)
    return net, None


def run_network(
    settings: BenchSettings, crop: int = 64, matcher: str = NETWORK_MATCHER
) -> dict[str, Any]:
    """Measure CVA-Net on a crop of the frame's cost volume (in this process).

    The matcher's volume is computed on a band of ``crop`` full-width rows in the middle of
    the Motorcycle pair (so that every crop column has all its disparities) and cut to the
    middle ``crop`` columns. After untimed runs on a 4×4 corner and on the crop itself, freed
    heap is handed back to the OS and the peak mark reset, then ``min(repeat, 3)`` calls
    of ``predict_confidence`` on the crop are timed; the median gives the crop's rate, and
    the frame's time is that median × FLOPs(frame) / FLOPs(crop), both counted by
    :func:`cva_confidence_ros.node_benchmark.network_flops` with the same tiling.

    Args:
        settings: Frame size and D.
        crop: Side of the square crop in pixels (≥ 1; clipped to the frame).
        matcher: Matcher of the cost volume and of the weights looked for.

    Returns:
        A record with :data:`RECORD_KEYS` (``config`` = ``cvanet_d<D>``, ``auc_rel`` = 1.0,
        ``peak_mem_mb`` = the crop's peak resident memory above what was resident before it)
        plus ``extrapolated`` (True), ``crop`` ([rows, columns]), ``crop_ms``, ``threads``
        and, for random weights, ``note``.

    Raises:
        ConfigError: ``crop`` < 1.
    """
    import torch

    from cva_confidence_ros.matching import compute_cost_volume
    from cva_confidence_ros.model import fold_batchnorm, predict_confidence, resolve_device
    from cva_confidence_ros.node_benchmark import network_flops

    if crop < 1:
        raise ConfigError(f'network crop must be ≥ 1 pixel; got {crop}')
    depth = settings.max_disparity
    rows, columns = min(crop, settings.height), min(crop, settings.width)
    left, right = make_pairs(settings)['real']
    top = (settings.height - rows) // 2
    band = slice(top, top + rows)
    volume = compute_cost_volume(
        np.ascontiguousarray(left[band]), np.ascontiguousarray(right[band]), matcher, depth
    )
    first = (settings.width - columns) // 2
    volume = np.ascontiguousarray(volume[:, :, first:first + columns], dtype=np.float32)
    device = resolve_device('cpu')
    net, note = _network(matcher, depth)
    # Folded once, as the confidence method does for a stream of frames.
    model = fold_batchnorm(net)
    predict_confidence(model, np.ascontiguousarray(volume[:, :4, :4]), device=device)
    # An untimed call on the crop itself, as run_case's full-size warm-up: the first call at a
    # shape pays one-off costs (kernel selection, buffers) that no later frame has.
    predict_confidence(model, volume, device=device)
    # Freed heap (the band's matching, the warm-ups) back to the OS first, as in run_case: a
    # crop that reuses it would otherwise not show it in its peak.
    _release_free_heap()
    rss_before = memory_kb('VmRSS')
    have_hwm = _reset_peak()
    times = []
    for _ in range(min(settings.repeat, 3)):
        start = time.perf_counter()
        predict_confidence(model, volume, device=device)
        times.append(time.perf_counter() - start)
    peak = memory_kb('VmHWM') if have_hwm else None
    seconds = statistics.median(times)
    crop_flops = network_flops(rows, columns, depth)
    frame_flops = network_flops(settings.height, settings.width, depth)
    record: dict[str, Any] = {
        'config': f'{_NETWORK_PREFIX}{depth}',
        'device': device.type,
        'width': settings.width,
        'height': settings.height,
        'max_disparity': depth,
        'ms_per_frame': seconds * frame_flops / crop_flops * 1e3,
        'peak_mem_mb': (
            max(peak - rss_before, 0) / 1024.0
            if peak is not None and rss_before is not None
            else None
        ),
        'network_gflops': crop_flops / seconds / 1e9,
        'gemm_gflops': _gemm_gflops(device),
        'auc_rel': 1.0,
        'extrapolated': True,
        'crop': [rows, columns],
        'crop_ms': seconds * 1e3,
        'threads': torch.get_num_threads(),
    }
    if note is not None:
        record['note'] = note
    return record


def _settings_args(settings: BenchSettings) -> list[str]:
    return [
        '--width', str(settings.width),
        '--height', str(settings.height),
        '--max-disparity', str(settings.max_disparity),
        '--repeat', str(settings.repeat),
    ]


def _run_in_subprocess(
    name: str, settings: BenchSettings, extra: Sequence[str] = ()
) -> dict[str, Any]:
    env = dict(os.environ)
    # The child must import this very package, also when it is run from a source checkout.
    package_root = str(Path(__file__).resolve().parents[1])
    env['PYTHONPATH'] = os.pathsep.join(
        [package_root] + ([env['PYTHONPATH']] if env.get('PYTHONPATH') else [])
    )
    flag = _NETWORK_WORKER_FLAG if name.startswith(_NETWORK_PREFIX) else _WORKER_FLAG
    command = [sys.executable, '-m', 'cva_confidence_ros.benchmark', flag, name]
    result = subprocess.run(
        command + _settings_args(settings) + list(extra),
        capture_output=True,
        text=True,
        env=env,
        check=False,
    )
    for line in reversed(result.stdout.splitlines()):
        if line.startswith(_RECORD_PREFIX):
            return json.loads(line[len(_RECORD_PREFIX):])
    raise ConfigError(
        f'benchmark of {name!r} failed (exit code {result.returncode}); expected a record, '
        f'got stderr:\n{result.stderr[-2000:]}'
    )


def _peak_cell(peak: float | None) -> str:
    """The peak-MB column: a dash where the peak could not be read (no ``/proc``)."""
    return f'{"—":>10}' if peak is None else f'{peak:>10.1f}'


def format_table(records: Sequence[dict[str, Any]], threads: int) -> str:
    """Human-readable table of the records with the ratio to OpenCV SGBM."""
    baseline = next((r['ms_per_frame'] for r in records if r['config'] == _BASELINE), None)
    networks = [r for r in records if r.get('network_gflops') is not None]
    first = records[0]
    nan = float('nan')
    lines = [
        f"{first['width']}×{first['height']}, D = {first['max_disparity']}, "
        f'{threads} CPU cores; frame = image pair → disparity; median ms per frame',
        f"{'config':<14}{'device':<8}{'ms/frame':>10}{'real':>9}{'synth':>9}{'volume':>9}"
        f"{'SGBM*':>9}{'× SGBM':>9}{'peak MiB':>10}",
    ]

    def cell(value: float | None, digits: int = 1) -> str:
        # A dash where the row has no such number (SGBM's own volume, the network's pairs);
        # a space before each number, which a wide one (a ratio of 1924) pushed out.
        return f'{"—":>9}' if value is None or math.isnan(value) else f' {value:>8.{digits}f}'

    for record in records:
        per_pair = record.get('per_pair_ms', {})
        volume = record.get('stages_ms', {}).get('volume')
        reference = record.get('paired_sgbm_ms') or baseline
        ratio = record['ms_per_frame'] / reference if reference else None
        lines.append(
            f"{record['config']:<14}{record['device']:<8}{record['ms_per_frame']:>10.1f}"
            f"{cell(per_pair.get('real'))}{cell(per_pair.get('synthetic'))}{cell(volume)}"
            f'{cell(reference or None)}{cell(ratio, 2)}{_peak_cell(record.get("peak_mem_mb"))}'
        )
    lines.append(
        'volume = cost-volume part of a matcher frame (the rest is WTA); real = Motorcycle, '
        'synth = banded synthetic pair;\nSGBM* = OpenCV SGBM frames interleaved with that '
        "row's frames in the same process (the ratio's reference); peak MiB = peak resident "
        'memory a frame needs (buffers kept between frames included)'
    )
    for record in networks:
        crop = record.get('crop') or ['?', '?']
        gemm = record.get('gemm_gflops')
        share = f" = {record['network_gflops'] / gemm:.0%} of" if gemm else ' of'
        lines.append(
            f"{record['config']}: {record['network_gflops']:.1f} GFLOP/s{share} a "
            f"{_GEMM_SIZE}² float32 matmul ({gemm or nan:.1f} GFLOP/s); measured on a "
            f'{crop[0]}×{crop[1]} crop, ms/frame extrapolated by FLOPs, peak MiB of the crop'
            + (f"; {record['note']}" if record.get('note') else '')
        )
    return '\n'.join(lines)


#: The --help epilog of every suite.
EXIT_CODES = ('Exit codes: 0 done, 2 bad input (one line on stderr), 130 stopped by Ctrl-C, 143 '
              "by SIGTERM (nothing is written then), 141 quietly when stdout's reader went "
              'away (| head). The table goes to stdout, progress to stderr.')


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='cva-benchmark',
        description='Milliseconds per frame and peak memory of the stereo matchers, next to '
        'OpenCV StereoSGBM (MODE_HH) on the same pairs.',
        epilog=EXIT_CODES,
    )
    defaults = BenchSettings()
    parser.add_argument('--width', type=int, default=defaults.width)
    parser.add_argument('--height', type=int, default=defaults.height)
    parser.add_argument('--max-disparity', type=int, default=defaults.max_disparity)
    parser.add_argument('--repeat', type=int, default=defaults.repeat,
                        help='timed frames per pair (after one untimed warm-up frame)')
    parser.add_argument('--matchers', nargs='+', default=None, metavar='NAME',
                        help=f'configurations to run (default: all of {CASES.names()}); '
                        f'{_BASELINE} is always added as the reference')
    parser.add_argument('--json', type=Path, default=None, metavar='PATH',
                        help='write the records as a JSON list to PATH')
    parser.add_argument('--suite', choices=_SUITES, default='matchers',
                        help='matchers (this table), node: end-to-end latency of cva-node '
                        'over DDS (see cva-benchmark --suite node --help), fast: CVA-Net '
                        'fast paths with their AUC cost (cva-benchmark --suite fast --help), '
                        'gpu: the networks per precision on a CUDA GPU '
                        '(cva-benchmark --suite gpu --help), or cloud: the point clouds in the '
                        'node and the cloud_filter node (cva-benchmark --suite cloud --help)')
    parser.add_argument('--network', action=argparse.BooleanOptionalAction, default=True,
                        help=f'add the CVA-Net row {_NETWORK_PREFIX}<D> (on a crop of the '
                        f'{NETWORK_MATCHER} cost volume, extrapolated to the frame by FLOPs)')
    parser.add_argument('--network-crop', type=int, default=64, metavar='PIXELS',
                        help='side of the square crop the network row is timed on')
    parser.add_argument(_WORKER_FLAG, default=None, help=argparse.SUPPRESS)
    parser.add_argument(_NETWORK_WORKER_FLAG, default=None, help=argparse.SUPPRESS)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``cva-benchmark`` (every suite); returns the process exit code: 0 done,
    2 bad input (one line on stderr), 130 / 143 stopped by Ctrl-C / SIGTERM (one line; nothing
    measured is printed or written), 141 without a word when stdout's reader went away
    (``| head -1``; the ``--json`` records are written before the table)."""
    # A Ctrl-C printed a KeyboardInterrupt traceback, a SIGTERM ended it without a word, and a
    # closed pipe printed a BrokenPipeError traceback and exited 1.
    with sigterm_as_interrupt() as terminated:
        try:
            return _main(argv)
        except BrokenPipeError:
            if not stdout_closed():  # a node suite's subprocess pipe, say: not our reader
                raise
            return closed_stdout()
        except (KeyboardInterrupt, SystemError) as exc:
            if not from_interrupt(exc):
                raise
            return interrupted_exit('cva-benchmark', terminated)


def _main(argv: Sequence[str] | None) -> int:
    suite = argparse.ArgumentParser(add_help=False)
    suite.add_argument('--suite', choices=_SUITES, default='matchers')
    chosen, rest = suite.parse_known_args(argv)
    if chosen.suite == 'node':
        from cva_confidence_ros.node_benchmark import main as node_main

        return node_main(rest)
    if chosen.suite == 'fast':
        from cva_confidence_ros.fast_benchmark import main as fast_main

        return fast_main(rest)
    if chosen.suite == 'gpu':
        from cva_confidence_ros.gpu_benchmark import main as gpu_main

        return gpu_main(rest)
    if chosen.suite == 'cloud':
        from cva_confidence_ros.cloud_benchmark import main as cloud_main

        return cloud_main(rest)
    parser = _parser()
    args = parser.parse_args(rest)
    try:
        settings = BenchSettings(args.width, args.height, args.max_disparity, args.repeat)
        if args.worker is not None:
            record = run_case(args.worker, settings)
            print(_RECORD_PREFIX + json.dumps(record), flush=True)
            return 0
        if args.network_worker is not None:
            record = run_network(settings, args.network_crop)
            print(_RECORD_PREFIX + json.dumps(record), flush=True)
            return 0
        if args.network_crop < 1:
            raise ConfigError(f'--network-crop must be ≥ 1 pixel; got {args.network_crop}')
        names = list(args.matchers) if args.matchers else CASES.names()
        for name in names:
            CASES.get(name)
        names = [name for name in names if name != _BASELINE] + [_BASELINE]
        if settings.width < _sgbm_min_width(settings.max_disparity):
            raise ConfigError(
                f'the OpenCV SGBM baseline needs images at least '
                f'{_sgbm_min_width(settings.max_disparity)} px wide at D = '
                f'{settings.max_disparity} (its disparity count is a multiple of 16); got '
                f'--width {settings.width}'
            )
        if args.json is not None:
            check_output_file(args.json, '--json')
        if args.network:
            from cva_confidence_ros.model.network import FUSION_LAYERS, MIN_DISPARITY

            if settings.max_disparity < MIN_DISPARITY:
                # Refused here: the network row runs last, after minutes of matcher rows.
                raise ConfigError(
                    f'the CVA-Net row {_NETWORK_PREFIX}{settings.max_disparity} needs '
                    f'--max-disparity ≥ {MIN_DISPARITY} (its fusion removes '
                    f'{2 * FUSION_LAYERS} disparities); got {settings.max_disparity}: raise it '
                    'or pass --no-network'
                )
        records = []
        for name in names:
            print(f'measuring {name} …', file=sys.stderr, flush=True)
            records.append(_run_in_subprocess(name, settings))
        if args.network:
            name = f'{_NETWORK_PREFIX}{settings.max_disparity}'
            print(f'measuring {name} …', file=sys.stderr, flush=True)
            crop = ['--network-crop', str(args.network_crop)]
            records.append(_run_in_subprocess(name, settings, crop))
    except CVAError as error:
        parser.exit(2, f'cva-benchmark: error: {error}\n')
    host = host_summary()
    # The records are saved before anything is printed: a table that fails to print (a closed
    # pipe) must not lose a run of minutes.
    if args.json is not None:
        write_records(args.json, records, _MATCHER_EXTRA_KEYS, host=host)
    print(format_table(records, os.cpu_count() or 1))
    print(f'host: {host}')
    return 0


def run_suite(
    parser: argparse.ArgumentParser,
    argv: Sequence[str] | None,
    measure: Callable[[argparse.Namespace, BenchSettings], list[dict[str, Any]]],
    table: Callable[[list[dict[str, Any]]], str],
    extra_keys: Sequence[str] = (),
) -> int:
    """Run one benchmark suite's command line: parse, measure, print the table, write the JSON.

    ``parser`` needs the ``--width``, ``--height``, ``--max-disparity``, ``--repeat`` and
    ``--json`` options; ``measure(args, settings)`` returns the records. A bad ``--json``
    path is refused before measuring; a :class:`CVAError` from either ends the process with
    code 2 and one line on stderr.
    """
    args = parser.parse_args(argv)
    try:
        settings = BenchSettings(args.width, args.height, args.max_disparity, args.repeat)
        if args.json is not None:
            check_output_file(args.json, '--json')
        records = measure(args, settings)
    except CVAError as error:
        parser.exit(2, f'cva-benchmark: error: {error}\n')
    host = host_summary()
    if args.json is not None:  # saved first, as in main
        write_records(args.json, records, extra_keys, host=host)
    print(table(records))
    print(f'host: {host}')
    return 0


def host_summary() -> str:
    """The machine the numbers belong to: CPU model, cores, and the vector ISA torch uses.

    Two hosts sold as the same 2-core VM ran CVA-Net-Fast 2.3× apart (oneDNN picks its
    convolution kernels by the vector ISA), so a table without this line cannot be compared.
    """
    model = platform.processor() or platform.machine() or 'unknown CPU'
    try:
        with open('/proc/cpuinfo', encoding='utf-8') as cpuinfo:
            for line in cpuinfo:
                if line.startswith('model name'):
                    model = line.split(':', 1)[1].strip()
                    break
    except OSError:
        pass
    try:
        import torch

        isa = torch.backends.cpu.get_cpu_capability()
    except (ImportError, AttributeError):
        isa = 'unknown'
    return f'{model}, {os.cpu_count() or 1} CPU cores, torch CPU kernels {isa}'


def write_records(
    path: Path,
    records: Sequence[dict[str, Any]],
    extra_keys: Sequence[str] = (),
    host: str | None = None,
) -> None:
    """Write the records as a JSON list: :data:`RECORD_KEYS`, ``extra_keys`` where set, ``host``.

    ``host`` is the same in every row: the machine they were taken on (None =
    :func:`host_summary`). The file is strict JSON: a NaN or infinite number is written as
    null.
    """
    keys = (*RECORD_KEYS, *extra_keys)
    host = host_summary() if host is None else host
    rows = [
        {**{key: record[key] for key in keys if key in record}, 'host': host}
        for record in records
    ]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(strict_json.dumps(rows, indent=2) + '\n', encoding='utf-8')
    print(f'wrote {path}', file=sys.stderr)


if __name__ == '__main__':
    sys.exit(main())

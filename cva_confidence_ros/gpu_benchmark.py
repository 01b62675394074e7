"""CVA-Net, -Lite and -Fast on a CUDA GPU per precision (``cva-benchmark --suite gpu``).

On a GPU the whole frame fits in one tile, so every row is the dense network on the full
frame. One record per (network, precision[, layout]) with the keys of
:data:`cva_confidence_ros.benchmark.RECORD_KEYS` plus:

* ``ms_per_frame``: what the node pays: the (D, H, W) float32 cost volume on the host in,
  the (H, W) confidence on the host out (padding, host→device copy, network, copy back);
  median of ``--repeat`` frames after untimed warm-up frames (cuDNN picks its kernels then).
* ``gpu_ms``: the network alone on a volume already on the device, timed with CUDA events;
  ``network_gflops`` is the network's floating-point operations (counted, 2 per multiply-add)
  over ``gpu_ms``. ``gemm_gflops`` is a float32 matmul (TF32 off) and ``gemm_bf16_gflops`` a
  bf16 matmul, both on the same device in the same run: the practical peaks.
* ``peak_mem_mb``: ``torch.cuda.max_memory_allocated`` during the timed frames (MiB), read
  before the network-only timing allocates its own device copy of the volume.
* ``auc_rel`` (with ``--data-root``): mean over the develop scenes (every scene halved until
  its ground truth fits D, census_bm, all known pixels of the full scene) of the row's AUC over
  that of the exact float32 CVA-Net on the same pixels; ``auc`` is the row's mean AUC itself.
  None where no weights are shipped for (census_bm, D) (speed does not depend on the weights).

``+cl`` rows keep the 3-D convolutions' tensors channels-last (NDHWC), the layout of cuDNN's
tensor-core kernels. ``--device cpu`` runs the same rows on the CPU (fp32 and bf16 only), as a
smoke test of the suite on a machine without a GPU.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
import statistics
import sys
import time
from typing import Any

import numpy as np

from cva_confidence_ros.benchmark import (
    EXIT_CODES,
    NETWORK_MATCHER,
    BenchSettings,
    _gemm_gflops,
    _network,
    make_pairs,
    run_suite,
)
from cva_confidence_ros.errors import ConfigError

__all__ = ['GPU_NETWORKS', 'PRECISIONS', 'format_gpu_table', 'main', 'run_gpu']

#: Row prefix → network architecture.
GPU_NETWORKS = {'exact': 'cvanet', 'lite': 'cvanet_lite', 'fast': 'cvanet_fast'}
PRECISIONS = ('fp32', 'fp16', 'bf16')
#: The row every ``auc_rel`` is relative to: the exact float32 CVA-Net.
_REFERENCE = 'exact:fp32'
_EXTRA_KEYS = ('gpu_ms', 'gemm_bf16_gflops', 'auc', 'arch', 'precision', 'channels_last',
               'note', 'gpu_name')


def _bf16_gemm_gflops(device: Any, size: int = 8192, repeat: int = 10) -> float:
    """Median bf16 ``torch.matmul`` rate of two size×size random matrices, GFLOP/s."""
    import torch

    generator = torch.Generator(device=device).manual_seed(0)
    a = torch.rand(size, size, generator=generator, device=device, dtype=torch.bfloat16)
    b = torch.rand(size, size, generator=generator, device=device, dtype=torch.bfloat16)
    timer = _Timer(device)
    with torch.inference_mode():
        for _ in range(3):
            torch.matmul(a, b)
        seconds = statistics.median(timer(lambda: torch.matmul(a, b)) for _ in range(repeat))
    return 2.0 * size**3 / seconds / 1e9


class _Timer:
    """Seconds of one call: CUDA events on a GPU, the host clock on a CPU."""

    def __init__(self, device: Any) -> None:
        self.device = device
        self.cuda = device.type == 'cuda'

    def __call__(self, fn: Callable[[], Any]) -> float:
        import torch

        if not self.cuda:
            start = time.perf_counter()
            fn()
            return time.perf_counter() - start
        begin, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        # On the stream of the device the work runs on: without one, the events go to the
        # current device's stream (cuda:0) and time nothing of the work on cuda:1.
        stream = torch.cuda.current_stream(self.device)
        begin.record(stream)
        fn()
        end.record(stream)
        end.synchronize()
        return begin.elapsed_time(end) / 1e3


@contextmanager
def _cudnn_autotuner(device: Any) -> Iterator[None]:
    """Switch cuDNN's autotuner (``torch.backends.cudnn.benchmark``) on inside the block on a
    CUDA ``device``, and put the flag back as it was on exit; other devices: no change."""
    import torch

    if device.type != 'cuda':
        yield
        return
    before = torch.backends.cudnn.benchmark
    torch.backends.cudnn.benchmark = True
    try:
        yield
    finally:
        torch.backends.cudnn.benchmark = before


def _develop_scenes(root: Path, depth: int, log: Callable[[str], None]) -> list[dict[str, Any]]:
    """census_bm cost volume, error labels and known mask of every develop scene fitted to D."""
    from cva_confidence_ros.datasets import DEVELOP_DATASETS, list_scenes, load_scene
    from cva_confidence_ros.datasets.resize import fit_disparity_range
    from cva_confidence_ros.matching import compute_cost_volume, wta_disparity
    from cva_confidence_ros.metrics import kitti_error

    scenes = []
    for dataset in DEVELOP_DATASETS:
        for scene in list_scenes(dataset, root):
            sample, factor = fit_disparity_range(load_scene(dataset, root, scene), depth)
            volume = compute_cost_volume(sample.left, sample.right, NETWORK_MATCHER, depth)
            known = np.isfinite(sample.disparity)
            wrong = kitti_error(wta_disparity(volume), np.nan_to_num(sample.disparity))
            scenes.append({'name': f'{dataset}/{scene}', 'volume': volume,
                           'wrong': wrong[known], 'known': known})
            log(f'  develop {dataset}/{scene}: {known.shape[0]}×{known.shape[1]} '
                f'(factor {factor}), {int(known.sum())} known pixels')
    return scenes


def _networks(depth: int, names: Sequence[str]) -> dict[str, tuple[Any, str | None]]:
    from cva_confidence_ros.fast_benchmark import _light_network

    nets = {}
    for name in names:
        arch = GPU_NETWORKS[name]
        nets[name] = _network(NETWORK_MATCHER, depth) if arch == 'cvanet' else _light_network(
            depth, arch)
    return nets


def run_gpu(
    settings: BenchSettings,
    networks: Sequence[str] = tuple(GPU_NETWORKS),
    precisions: Sequence[str] = PRECISIONS,
    device: str = 'cuda',
    data_root: Path | None = None,
    channels_last: bool = True,
    warmup: int = 3,
    log: Callable[[str], None] = lambda text: print(text, file=sys.stderr, flush=True),
) -> list[dict[str, Any]]:
    """Measure every (network, precision) row on ``device`` (see the module docstring).

    Args:
        settings: Frame size, D and timed frames per row.
        networks: Row prefixes, keys of :data:`GPU_NETWORKS`.
        precisions: ``fp32``, ``fp16`` (CUDA only), ``bf16``.
        device: ``cuda``, ``cuda:N`` or ``cpu``.
        data_root: Root with the develop split for ``auc_rel``, or None.
        channels_last: Add the ``+cl`` rows of the exact network (reduced precisions).
        warmup: Untimed frames before the timed ones.
        log: Progress messages.

    Returns:
        The records.

    Raises:
        ConfigError: Unknown network or precision, none of either, a device that is not
            there (CUDA on a machine without), fp16 on a CPU, or a negative warmup.
    """
    import torch

    from cva_confidence_ros.matching import compute_cost_volume
    from cva_confidence_ros.metrics import roc_auc
    from cva_confidence_ros.model import SparseEvaluator, pad_cost_volume
    from cva_confidence_ros.model.sparse import precision_context

    target = _check_rows(networks, precisions, device, warmup)
    # Fixed shapes: let cuDNN time its kernels; the flag is the process's, so it is put back.
    with _cudnn_autotuner(target):
        depth = settings.max_disparity
        timer = _Timer(target)
        gpu_name = torch.cuda.get_device_name(target) if target.type == 'cuda' else 'cpu'
        nets = _networks(depth, networks)
        left, right = make_pairs(settings)['real']
        volume = compute_cost_volume(left, right, NETWORK_MATCHER, depth)
        gemm = _gemm_gflops(target, 4096 if target.type == 'cuda' else 1024)
        gemm_bf16 = _bf16_gemm_gflops(target) if target.type == 'cuda' else None
        log(f'{gpu_name}: float32 matmul {gemm:.0f} GFLOP/s'
            + ('' if gemm_bf16 is None else f', bf16 matmul {gemm_bf16:.0f} GFLOP/s'))
        develop = _develop_scenes(data_root, depth, log) if data_root is not None else []
        rows: list[tuple[str, str, bool]] = []
        for name in networks:
            for precision in precisions:
                rows.append((name, precision, False))
                if (channels_last and name == 'exact' and precision != 'fp32'
                        and target.type == 'cuda'):
                    rows.append((name, precision, True))
        records = []
        for name, precision, layout in rows:
            net, note = nets[name]
            config = f'{name}:{precision}' + ('+cl' if layout else '')
            log(f'measuring {config} …')
            evaluator = SparseEvaluator(net, target, tile_budget_mb=1e9, precision=precision,
                                        path='tile')
            if layout:
                # torch's stubs of Module.to omit memory_format, which it accepts at run time.
                evaluator.net = evaluator.net.to(  # type: ignore[call-overload]
                    memory_format=torch.channels_last_3d
                )
            for _ in range(warmup):
                evaluator(volume)
            if target.type == 'cuda':
                torch.cuda.synchronize(target)
                torch.cuda.reset_peak_memory_stats(target)
            walls = []
            for _ in range(settings.repeat):
                start = time.perf_counter()
                evaluator(volume)
                walls.append(time.perf_counter() - start)
            # The peak of the timed frames alone: the network-only input below is a second
            # device copy of the padded volume (164 MB at 640×480, D = 128) that no frame has.
            peak = (torch.cuda.max_memory_allocated(target) / 2**20
                    if target.type == 'cuda' else None)
            padded = torch.from_numpy(pad_cost_volume(volume)).to(target)[None, None]
            if layout:
                padded = padded.contiguous(memory_format=torch.channels_last_3d)

            def network_only(padded: torch.Tensor = padded, evaluator: Any = evaluator,
                             precision: str = precision) -> None:
                with torch.inference_mode(), precision_context(target, precision):
                    evaluator.net(padded)

            for _ in range(warmup):
                network_only()
            gpu = statistics.median(timer(network_only) for _ in range(settings.repeat))
            flops = evaluator._flops('tile', settings.height, settings.width)
            auc = None
            if develop and note is None:
                aucs = []
                for scene in develop:
                    confidence = evaluator(scene['volume'])[scene['known']]
                    aucs.append(roc_auc(confidence, scene['wrong']))
                auc = float(np.mean(aucs))
            record: dict[str, Any] = {
                'config': config,
                'device': target.type,
                'gpu_name': gpu_name,
                'width': settings.width,
                'height': settings.height,
                'max_disparity': depth,
                'ms_per_frame': statistics.median(walls) * 1e3,
                'gpu_ms': gpu * 1e3,
                'network_gflops': flops / gpu / 1e9,
                'gemm_gflops': gemm,
                'gemm_bf16_gflops': gemm_bf16,
                'peak_mem_mb': peak,
                'auc': auc,
                'auc_rel': None,  # filled in below, once the reference row has been measured
                'arch': GPU_NETWORKS[name],
                'precision': precision,
                'channels_last': layout,
            }
            if note is not None:
                record['note'] = note
            log(f"  {config}: {record['ms_per_frame']:.1f} ms/frame, network {gpu * 1e3:.2f} ms "
                f"= {record['network_gflops'] / 1e3:.1f} TFLOP/s"
                + ('' if auc is None else f', AUC {auc:.4f}'))
            records.append(record)
            # network_only's defaults hold this row's evaluator and padded volume: without it in
            # the del, both stayed on the device through the next row's frames and its peak.
            del evaluator, padded, network_only
            if target.type == 'cuda':
                torch.cuda.empty_cache()
        if develop and not _fill_auc_rel(records):
            log(f'auc_rel left empty: it needs the {_REFERENCE} row (--networks exact '
                '--precisions fp32) with shipped weights')
        return records


def _check_rows(
    networks: Sequence[str], precisions: Sequence[str], device: str, warmup: int
) -> Any:
    """The device of :func:`run_gpu`'s rows (a :class:`torch.device`), once its arguments are
    checked; raises :class:`ConfigError` as :func:`run_gpu` says."""
    from cva_confidence_ros.devices import resolve_device

    if warmup < 0:
        raise ConfigError(f'warmup must be ≥ 0 untimed frames; got {warmup}')
    if not networks or not precisions:
        raise ConfigError(
            f'no rows to measure: networks {list(networks)}, precisions {list(precisions)}; '
            f'expected some of {list(GPU_NETWORKS)} and of {list(PRECISIONS)}'
        )
    unknown = [n for n in networks if n not in GPU_NETWORKS]
    if unknown:
        raise ConfigError(f'unknown networks {unknown}; expected some of {list(GPU_NETWORKS)}')
    bad = [p for p in precisions if p not in PRECISIONS]
    if bad:
        raise ConfigError(f'unknown precisions {bad}; expected some of {list(PRECISIONS)}')
    target = resolve_device(device)
    if target.type != 'cuda' and 'fp16' in precisions:
        raise ConfigError('fp16 needs a CUDA device; use --precisions fp32 bf16 on a CPU')
    return target


def _fill_auc_rel(records: Sequence[dict[str, Any]]) -> bool:
    """Set ``auc_rel`` = ``auc`` / that of the :data:`_REFERENCE` row in every record with an
    ``auc``, wherever that row stands; False (nothing set) without it or without its AUC."""
    reference = next((r.get('auc') for r in records if r['config'] == _REFERENCE), None)
    if not reference:
        return False
    for record in records:
        if record.get('auc') is not None:
            record['auc_rel'] = record['auc'] / reference
    return True


def format_gpu_table(records: Sequence[dict[str, Any]]) -> str:
    """Markdown table of the GPU records."""
    first = records[0]
    bf16 = first.get('gemm_bf16_gflops')
    lines = [
        f"{first['gpu_name']}, {first['width']}×{first['height']}, D = {first['max_disparity']}, "
        f"census_bm cost volume of the Motorcycle pair; float32 matmul "
        f"{first['gemm_gflops'] / 1e3:.1f} TFLOP/s"
        + ('' if bf16 is None else f', bf16 matmul {bf16 / 1e3:.0f} TFLOP/s'),
        '',
        '| config | ms/frame (host→host) | fps | network ms | network TFLOP/s | peak MiB '
        '| AUC | auc_rel |',
        '|---|---:|---:|---:|---:|---:|---:|---:|',
    ]
    for r in records:
        auc = '—' if r.get('auc') is None else f"{r['auc']:.4f}"
        rel = '—' if r.get('auc_rel') is None else f"{r['auc_rel']:.4f}"
        peak = r.get('peak_mem_mb')
        lines.append(
            f"| {r['config']} | {r['ms_per_frame']:.1f} | {1e3 / r['ms_per_frame']:.1f} "
            f"| {r['gpu_ms']:.2f} | {r['network_gflops'] / 1e3:.1f} "
            f"| {'—' if peak is None else f'{peak:.0f}'} | {auc} | {rel} |"
        )
    return '\n'.join(lines)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='cva-benchmark --suite gpu',
        description='CVA-Net, -Lite and -Fast on a CUDA GPU in fp32 / fp16 / bf16: ms per frame, '
        "network TFLOP/s against the same GPU's matmul, peak memory and develop-split AUC "
        'relative to the exact float32 network.',
        epilog=EXIT_CODES,
    )
    parser.add_argument('--device', default='cuda', help='cuda, cuda:N, or cpu (a smoke run)')
    parser.add_argument('--width', type=int, default=640)
    parser.add_argument('--height', type=int, default=480)
    parser.add_argument('--max-disparity', type=int, default=128)
    parser.add_argument('--repeat', type=int, default=10, help='timed frames per row')
    parser.add_argument('--warmup', type=int, default=3, help='untimed frames per row')
    parser.add_argument('--networks', nargs='+', default=list(GPU_NETWORKS),
                        choices=list(GPU_NETWORKS))
    parser.add_argument('--precisions', nargs='+', default=None, choices=list(PRECISIONS),
                        help='default: all on CUDA; fp32 and bf16 elsewhere (fp16 is CUDA only)')
    parser.add_argument('--no-channels-last', action='store_true',
                        help='leave out the channels-last (+cl) rows of the exact network')
    parser.add_argument('--data-root', type=Path, default=None,
                        help='data root with the develop split (e.g. ../shared/data) for auc_rel')
    parser.add_argument('--json', type=Path, default=None, metavar='PATH')
    return parser


def _precisions(args: argparse.Namespace) -> list[str]:
    """``--precisions``, or by default every one on CUDA and fp32, bf16 elsewhere (the CPU
    smoke run of the same rows: fp16 would only be refused there)."""
    if args.precisions is not None:
        return list(args.precisions)
    cuda = str(args.device).startswith('cuda')
    return [p for p in PRECISIONS if cuda or p != 'fp16']


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``cva-benchmark --suite gpu``; returns the exit code."""
    def measure(args: argparse.Namespace, settings: BenchSettings) -> list[dict[str, Any]]:
        return run_gpu(settings, args.networks, _precisions(args), args.device, args.data_root,
                       not args.no_channels_last, args.warmup)

    parser = _parser()
    args = parser.parse_args(argv)
    try:  # before run_suite makes the --json folder: no CUDA here leaves nothing behind
        _check_rows(args.networks, _precisions(args), args.device, args.warmup)
    except ConfigError as error:
        parser.exit(2, f'cva-benchmark: error: {error}\n')
    return run_suite(parser, argv, measure, format_gpu_table, _EXTRA_KEYS)


if __name__ == '__main__':
    sys.exit(main())

"""Export the cost-volume networks to ONNX, for ONNX Runtime, TensorRT or OpenVINO on a robot.

The exported graph is the folded network (batch normalisation merged into the convolutions)
behind the zero padding that :func:`~cva_confidence_ros.model.predict_confidence` applies, so
that it takes what a matcher gives and returns what the node publishes:

* input ``cost_volume``: (B, D, H, W) float32, costs normalised to [0, 1] as
  :func:`~cva_confidence_ros.matching.compute_cost_volume` returns them (one volume is
  ``volume[None]``); B, H and W are dynamic, D is the weights' depth;
* output ``confidence``: (B, H, W) float32 in (0, 1), one per pixel.

``cva-export`` writes the ``.onnx`` file, a ``.json`` beside it (matcher, D, architecture, the
weights it came from and their training facts) and, where ONNX Runtime is installed, checks the
exported graph against PyTorch on a random volume.
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator, Mapping, Sequence
import contextlib
import copy
import json
import os
from pathlib import Path
import sys
import tempfile
import time
from typing import Any
import warnings

import numpy as np
import torch
from torch import nn
import torch.nn.functional as F

from cva_confidence_ros import strict_json
from cva_confidence_ros.checks import is_int
from cva_confidence_ros.errors import (
    ConfigError,
    InputError,
    ModelError,
    reason,
)
from cva_confidence_ros.model.fast import FoldedCVANetFast
from cva_confidence_ros.model.inference import PAD, FoldedCVANet
from cva_confidence_ros.model.lite import FoldedCVANetLite, check_volume_tensor
from cva_confidence_ros.model.weights import (
    _unwrap,
    architecture_of,
    default_weights_path,
    load_weights,
)

__all__ = ['EXPORTABLE', 'CostVolumeModel', 'OnnxRuntimeNet', 'check_onnx', 'export_onnx', 'main']

PROG = 'cva-export'
#: Architectures whose input is the cost volume alone (the baselines need an image too).
EXPORTABLE = ('cvanet', 'cvanet_lite', 'cvanet_fast')
DEFAULT_OPSET = 17
# The folded (inference) forms of the three, exported as they are.
_FOLDED = {
    FoldedCVANet: 'cvanet',
    FoldedCVANetLite: 'cvanet_lite',
    FoldedCVANetFast: 'cvanet_fast',
}


class CostVolumeModel(nn.Module):
    """A cost-volume network as a deployable whole: (B, D, H, W) costs → (B, H, W) confidence.

    Args:
        net: CVA-Net, CVA-Net-Lite or CVA-Net-Fast (trained or folded), in eval mode.
    """

    def __init__(self, net: nn.Module) -> None:
        super().__init__()
        self.net = net

    def forward(self, cost_volume: torch.Tensor) -> torch.Tensor:
        """(B, D, H, W) costs → (B, H, W) confidence.

        Raises:
            InputError: ``cost_volume`` not a (B, D, H, W) tensor with H, W >= 1 (the network
                checks D and the dtype); named as given, not as the padded 5-D tensor the
                network sees.
        """
        if (
            not isinstance(cost_volume, torch.Tensor)
            or cost_volume.ndim != 4
            or cost_volume.shape[2] < 1
            or cost_volume.shape[3] < 1
        ):
            shape = getattr(cost_volume, 'shape', None)
            raise InputError(
                'expected a cost-volume tensor of shape (B, D, H, W), H and W >= 1 (one volume '
                f'is volume[None]); got {type(cost_volume).__name__}'
                + ('' if shape is None else f' of shape {tuple(shape)}')
            )
        padded = F.pad(cost_volume, (PAD, PAD, PAD, PAD))
        return self.net(padded.unsqueeze(1))


def _deployable(net: nn.Module) -> tuple[CostVolumeModel, str, int]:
    """The folded, float32 CPU copy of ``net`` behind the padding; ``net`` itself (its
    train/eval mode, device and dtype) is left as it was."""
    folded_arch = _FOLDED.get(type(_unwrap(net)))
    arch = folded_arch or architecture_of(net)
    if arch not in EXPORTABLE:
        raise ModelError(
            f'ONNX export covers the cost-volume networks {EXPORTABLE}; got {arch!r} (its '
            'input is a disparity map and an image)'
        )
    # A (Distributed)DataParallel wrapper, which architecture_of accepts, has no
    # fold_batchnorm and no max_disparity; torch.compile's wrapper cannot be traced ("FX to
    # torch.jit.trace a dynamo-optimized function"): the module inside either is exported.
    # Folding reads the BN running statistics whatever the mode, so the caller's network need
    # not be switched to eval mode.
    typed: Any = _unwrap(net)  # each of the three has max_disparity and folds itself
    if folded_arch:  # already folded (fold_batchnorm): a copy, the caller's is left as it is
        folded = copy.deepcopy(typed)
    else:
        folded = typed.fold_batchnorm()
    # The graph is float32 on the CPU as documented, whatever the network's device, its dtype
    # or torch's default dtype (the folded layers are built in the default dtype).
    folded = folded.to('cpu', torch.float32)
    return CostVolumeModel(folded).eval(), arch, int(typed.max_disparity)


def _check_size(size: object, name: str) -> tuple[int, int]:
    """``size`` as (H, W); ConfigError unless it is a pair of integers >= 1 (the volume's image
    size, before the padding the graph adds)."""
    pair = tuple(size) if isinstance(size, (tuple, list)) else None
    if pair is None or len(pair) != 2 or not all(is_int(v) and v >= 1 for v in pair):
        raise ConfigError(
            f"{name} must be (H, W), two integers >= 1 (the cost volume's image size); "
            f'got {size!r}'
        )
    return int(pair[0]), int(pair[1])


def _opset_range() -> tuple[int, int]:
    """The ONNX opsets this torch's exporter writes (7 to 23 for torch 2.13)."""
    try:
        from torch.onnx import _constants

        return int(_constants.ONNX_MIN_OPSET), int(_constants.ONNX_MAX_OPSET)
    except (ImportError, AttributeError):  # a private module: fall back to a safe range
        return 9, DEFAULT_OPSET


@contextlib.contextmanager
def _ir_dump_hidden() -> Iterator[None]:
    """Keep torch's exporter from printing the whole TorchScript graph on stdout when it fails
    (an operator the opset lacks: ~100 lines from C++, before the one-line ModelError that says
    why). File descriptor 1 goes to a file meanwhile; what else came there is passed on."""
    marker = b'Torch IR graph at exception:'
    flush = getattr(sys.stdout, 'flush', lambda: None)  # sys.stdout may be None (no console)
    flush()
    try:
        saved = os.dup(1)
    except OSError:  # no standard output to keep clean
        saved = -1
    if saved < 0:
        yield
        return
    with tempfile.TemporaryFile() as capture:
        os.dup2(capture.fileno(), 1)
        try:
            yield
        finally:
            flush()
            os.dup2(saved, 1)
            os.close(saved)
            capture.seek(0)
            passed_on = capture.read().split(marker, 1)[0]
            if passed_on:
                os.write(1, passed_on)


def _trace_to_onnx(
    module: nn.Module,
    example: torch.Tensor,
    path: Path,
    opset: int,
    input_name: str,
    input_axes: dict[int, str],
    metadata: dict[str, str] | None = None,
) -> None:
    """Trace ``module`` on ``example`` into an ONNX file with dynamic ``input_axes`` (the output
    ``confidence`` (B, H, W) dynamic throughout) and ``metadata`` as its metadata_props.

    The graph is written beside ``path`` and moved there once whole: a failed export (a full
    disk, an opset too old) leaves an older file at ``path`` as it was.

    Raises:
        ModelError: The ``onnx`` package (which the exporter writes with) is missing, the
            exporter cannot write the network at ``opset`` (out of the range this torch
            supports, or too old for an operator of the network), or ``path`` cannot be
            written.
    """
    low, high = _opset_range()
    if not is_int(opset) or not low <= opset <= high:
        raise ModelError(
            f'ONNX opset must be an integer in [{low}, {high}] (what this torch exports); '
            f'got {opset!r}'
        )
    partial = path.with_name(f'.{path.name}.partial')
    try:
        with warnings.catch_warnings(), torch.no_grad(), _ir_dump_hidden():
            # The traced shape checks and ONNX's constant folding notes are expected.
            warnings.simplefilter('ignore')
            torch.onnx.export(
                module,
                (example,),
                str(partial),
                dynamo=False,
                opset_version=int(opset),
                input_names=[input_name],
                output_names=['confidence'],
                dynamic_axes={
                    input_name: input_axes,
                    'confidence': {0: 'batch', 1: 'height', 2: 'width'},
                },
            )
        if metadata:
            import onnx

            graph = onnx.load(str(partial))
            onnx.helper.set_model_props(graph, metadata)
            onnx.save(graph, str(partial))
        with open(partial, 'rb') as handle:  # on the disk before it replaces an older graph
            os.fsync(handle.fileno())
        os.replace(partial, path)
    except ModuleNotFoundError as exc:
        raise ModelError(f'ONNX export needs the onnx package ({exc}): pip install onnx') from exc
    except OSError as exc:  # a full disk, no permission
        raise ModelError(f'cannot write the ONNX graph to {path}: {reason(exc)}') from exc
    except RuntimeError as exc:  # torch.onnx.OnnxExporterError is one too
        hint = '' if opset == DEFAULT_OPSET else f'; the default opset {DEFAULT_OPSET} works'
        raise ModelError(f'cannot export to ONNX at opset {opset} ({reason(exc)}){hint}') from exc
    finally:
        with contextlib.suppress(OSError):
            partial.unlink(missing_ok=True)


def export_onnx(
    net: nn.Module,
    path: str | os.PathLike[str],
    opset: int = DEFAULT_OPSET,
    example_size: tuple[int, int] = (32, 48),
    metadata: Mapping[str, object] | None = None,
) -> Path:
    """Write ``net`` as an ONNX graph with dynamic batch, height and width.

    The graph's metadata_props (ONNX Runtime: ``session.get_modelmeta().custom_metadata_map``)
    hold ``arch`` and ``max_disparity``, and ``metadata`` (e.g. ``matcher``, as ``cva-export``
    writes it from the weights' meta) as strings: the graph says what it is for without the
    ``.json`` beside it.

    Args:
        net: A CVA-Net, CVA-Net-Lite or CVA-Net-Fast (e.g. from :func:`load_weights`), or
            its folded form (``fold_batchnorm``); either may be under ``torch.compile``.
        path: The ``.onnx`` file to write.
        opset: ONNX opset version.
        example_size: (H, W) of the volume traced through the network (any size works later).
        metadata: More metadata_props (values written as ``str``; None values left out).

    Returns:
        ``path`` as a :class:`~pathlib.Path` (missing folders made, as :func:`save_weights`
        makes them).

    Raises:
        ModelError: Another architecture, the ``onnx`` package is missing, ``opset`` is
            one the exporter cannot write the network at, or ``path`` is a folder or in a
            place that cannot be written (an older file at ``path`` is then left as it was).
        ConfigError: ``example_size`` not two integers >= 1.
    """
    example_size = _check_size(example_size, 'example_size')
    model, arch, depth = _deployable(net)
    # A deployed graph travels without its card: a consumer can still check matcher and D.
    props = {key: str(value) for key, value in (metadata or {}).items() if value is not None}
    props.update(arch=arch, max_disparity=str(depth))
    path = Path(path)
    if path.is_dir():
        raise ModelError(f'cannot write the ONNX graph to {path}: it is a folder')
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ModelError(f'cannot write the ONNX graph to {path}: {reason(exc)}') from exc
    _trace_to_onnx(
        model, torch.rand(1, depth, *example_size, dtype=torch.float32), path, opset,
        'cost_volume',
        {0: 'batch', 2: 'height', 3: 'width'},
        props,
    )
    return path


def _cpu_session(onnxruntime: Any, graph: bytes, threads: int | None = None) -> Any:
    """An ONNX Runtime CPU session on ``graph`` with torch's thread count (ONNX Runtime's own
    default is the physical cores, one on many 2-vCPU machines) and no busy-waiting threads
    between runs (in the node the matcher, torch and DDS share the cores)."""
    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = threads or torch.get_num_threads()
    options.add_session_config_entry('session.intra_op.allow_spinning', '0')
    return onnxruntime.InferenceSession(graph, options, providers=['CPUExecutionProvider'])


def check_onnx(
    path: str | os.PathLike[str],
    net: nn.Module,
    size: tuple[int, int] = (48, 64),
    seed: int = 0,
    repeat: int = 3,
) -> dict[str, float]:
    """Run the exported graph with ONNX Runtime beside PyTorch on one random volume.

    Returns:
        ``max_abs_diff`` between the two confidences, and the median ``onnxruntime_ms`` and
        ``torch_ms`` of ``repeat`` runs (this machine's threads).

    Raises:
        ModelError: ONNX Runtime is not installed, or the graph does not load, does not run
            on a (1, D, H, W) volume of ``net``'s depth, or gives another shape than ``net``.
        ConfigError: ``size`` not two integers >= 1.
    """
    size = _check_size(size, 'size')
    try:
        import onnxruntime
    except ImportError as exc:
        raise ModelError('checking an export needs onnxruntime: pip install onnxruntime') from exc
    model, _, depth = _deployable(net)
    volume = np.random.default_rng(seed).random((1, depth, *size), dtype=np.float32)
    try:
        session = _cpu_session(onnxruntime, Path(path).read_bytes())
    except Exception as exc:  # onnxruntime raises its own types for a bad graph
        raise ModelError(f'ONNX Runtime cannot load {path}: {exc}') from exc

    def timed(run: Any) -> tuple[np.ndarray, float]:
        times, out = [], None
        for _ in range(max(1, repeat)):
            tic = time.perf_counter()
            out = run()
            times.append((time.perf_counter() - tic) * 1e3)
        return np.asarray(out), float(np.median(times))

    try:
        ort_out, ort_ms = timed(lambda: session.run(None, {'cost_volume': volume})[0])
    except Exception as exc:  # onnxruntime's own types: another D, input name or dtype
        raise ModelError(
            f'ONNX Runtime cannot run {path} on a float32 cost volume of shape {volume.shape}, '
            f'what the network takes ({reason(exc)})'
        ) from exc
    with torch.inference_mode():
        torch_out, torch_ms = timed(lambda: model(torch.from_numpy(volume)).numpy())
    if ort_out.shape != torch_out.shape:
        raise ModelError(
            f'{path} gives confidence of shape {ort_out.shape}; the network {torch_out.shape}'
        )
    return {
        'max_abs_diff': float(np.abs(ort_out - torch_out).max()),
        'onnxruntime_ms': ort_ms,
        'torch_ms': torch_ms,
    }


class OnnxRuntimeNet:
    """A folded cost-volume network run by ONNX Runtime on the CPU, called like the network.

    The network is exported once (in memory) with dynamic batch, height and width, so it takes
    what the torch network takes, (B, 1, D, h + 12, w + 12) padded tiles or 13×13 extracts, and
    gives (B, h, w). :class:`~cva_confidence_ros.model.SparseEvaluator` runs it with
    ``backend='onnxruntime'``.

    Args:
        net: A folded CVA-Net, CVA-Net-Lite or CVA-Net-Fast (``fold_batchnorm``); a float32
            CPU copy of it is exported (``net`` itself is left as it is).
        threads: ONNX Runtime's intra-op threads; None (or 0) = torch's current thread count.

    Raises:
        ModelError: ``onnx`` or ``onnxruntime`` is not installed, or the export fails.
        ConfigError: ``threads`` neither None nor an integer >= 0.
    """

    def __init__(self, net: nn.Module, threads: int | None = None) -> None:
        if threads is not None and not (is_int(threads) and threads >= 0):
            raise ConfigError(
                "threads must be None or an integer >= 0 (ONNX Runtime's intra-op threads; "
                f"None or 0: torch's thread count); got {type(threads).__name__} {threads!r}"
            )
        try:
            import onnxruntime
        except ImportError as exc:
            raise ModelError(
                "cva_backend 'onnxruntime' needs onnxruntime: pip install onnx onnxruntime"
            ) from exc
        # The module inside torch.compile's wrapper: the tracer refuses a compiled one.
        net = _unwrap(net)
        typed: Any = net
        depth = int(typed.max_disparity)
        self.max_disparity = depth
        # The graph runs float32 on the CPU: a float64 (or CUDA) network, or layers built under
        # a float64 default dtype, would be traced into a graph that the float32 feed of
        # __call__ cannot run (or that ONNX Runtime cannot load).
        model = copy.deepcopy(net).to('cpu', torch.float32).eval()
        example = torch.rand(1, 1, depth, 2 * PAD + 8, 2 * PAD + 8, dtype=torch.float32)
        with tempfile.TemporaryDirectory() as folder:
            path = Path(folder) / 'net.onnx'
            _trace_to_onnx(
                model, example, path, DEFAULT_OPSET, 'padded',
                {0: 'batch', 3: 'rows', 4: 'columns'},
            )
            graph = path.read_bytes()
        self.session = _cpu_session(onnxruntime, graph, threads)

    def __call__(self, padded: torch.Tensor) -> torch.Tensor:
        """(B, 1, D, h + 12, w + 12) float32 CPU tensor → (B, h, w) confidence tensor.

        Raises:
            InputError: ``padded`` not a floating-point (B, 1, D, ≥13, ≥13) tensor with the
                network's D (as the network itself; an integer volume is not cast silently).
        """
        check_volume_tensor(padded, self.max_disparity)
        feed = np.ascontiguousarray(padded.detach().numpy(), dtype=np.float32)
        (out,) = self.session.run(None, {'padded': feed})
        return torch.from_numpy(out)


def _size(text: str) -> tuple[int, int]:
    height, _, width = text.partition('x')
    if not (height.isdigit() and width.isdigit() and int(height) > 0 and int(width) > 0):
        raise argparse.ArgumentTypeError(f'expected HxW, e.g. 240x320; got {text!r}')
    return int(height), int(width)


def _build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=PROG,
        description='Export CVA-Net, CVA-Net-Lite or CVA-Net-Fast weights to ONNX: input '
        'cost_volume (B, D, H, W) float32 in [0, 1], output confidence (B, H, W).',
        epilog='Exit codes: 0 written, 2 bad input or a graph or card that cannot be written '
        '(one line on stderr; a graph and card from before stay as they were), 1 the checked '
        'graph cannot be moved in place, 130 stopped by Ctrl-C, 143 by SIGTERM.',
    )
    parser.add_argument('weights', nargs='?', default=None,
                        help='weights file (.pt); default: the shipped file for --arch, '
                        '--matcher and --max-disparity')
    # None: not given. Without WEIGHTS they pick the shipped file (defaults cvanet_fast,
    # census_bm, 64); with WEIGHTS, those given must be what the file holds.
    parser.add_argument('--arch', default=None, choices=EXPORTABLE,
                        help='architecture of the shipped weights to export (default '
                        'cvanet_fast); with WEIGHTS: checked against the file')
    parser.add_argument('--matcher', default=None,
                        help='matcher of the shipped weights (default census_bm); with '
                        'WEIGHTS: checked against the file')
    parser.add_argument('--max-disparity', type=int, default=None,
                        help='depth D of the shipped weights (default 64); with WEIGHTS: '
                        'checked against the file')
    parser.add_argument('--out', type=Path, required=True,
                        help='the .onnx file to write (its card: the .json beside it); a '
                        'graph and card from before are replaced once the new graph is checked')
    parser.add_argument('--overwrite', action='store_true',
                        help='also replace a .json beside --out that is not a card of '
                        'cva-export (refused otherwise)')
    parser.add_argument('--opset', type=int, default=DEFAULT_OPSET, help='ONNX opset version')
    parser.add_argument('--check-size', type=_size, default=None, metavar='HxW',
                        help='volume size of the ONNX Runtime check (default 240x320 for '
                        'CVA-Net-Fast, 60x80 for the 3-D networks: seconds a frame on a CPU)')
    parser.add_argument('--no-check', action='store_true', help='skip the ONNX Runtime check')
    return parser


def _not_a_card(card: Path) -> str:
    """Why the file at ``card`` (the .json beside ``--out``) is not the card of an earlier
    export that ``cva-export`` may replace; '' when it is, or when there is none."""
    try:
        held = json.loads(card.read_text(encoding='utf-8'))
    except FileNotFoundError:
        return ''
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        return f'{card} exists and is not a card of cva-export ({reason(exc)})'
    if not (
        isinstance(held, dict)
        and held.get('arch') in EXPORTABLE
        and isinstance(held.get('input'), dict)
        and held['input'].get('name') == 'cost_volume'
    ):
        return f'{card} exists and is not a card of cva-export (no arch and cost_volume input)'
    return ''


def run(args: argparse.Namespace) -> int:
    """Export for parsed arguments; raises ``CVAError`` on bad input."""
    from cva_confidence_ros.outputs import check_output_file, write_text_atomic

    if Path(args.out).suffix != '.onnx':
        raise ModelError(f'--out must name a .onnx file; got {args.out}')
    out = check_output_file(args.out, '--out')
    # The card beside the graph: refused up front, as --out is, rather than after the graph.
    card = check_output_file(out.with_suffix('.json'), 'the card beside --out:')
    # An earlier graph and card are replaced, as the README promises (the graph stays until
    # the new one is checked); another .json is not: a cva-evaluate --json named like the
    # graph was replaced by the card without a word.
    foreign = '' if getattr(args, 'overwrite', False) else _not_a_card(card)
    if foreign:
        raise ConfigError(f'the card beside --out {out}: {foreign}; --overwrite to replace it, '
                          'or another --out')
    if args.weights:
        # Checked, not ignored (--max-disparity 32 exported a D = 64 file without a word).
        weights = Path(args.weights)
        net, meta = load_weights(weights, args.matcher, args.max_disparity, arch=args.arch)
    else:
        weights = default_weights_path(
            args.matcher or 'census_bm',
            64 if args.max_disparity is None else args.max_disparity,
            args.arch or 'cvanet_fast',
        )
        net, meta = load_weights(weights, arch=None)
    arch = architecture_of(net)
    depth = int(meta.get('max_disparity') or net.max_disparity)
    # Written beside --out and moved there once checked: a graph that fails the check is not
    # left where a deploy script looks (nor put over a good one from before).
    staging = out.with_name(f'.{out.stem}.unchecked.onnx')
    try:
        tic = time.perf_counter()
        export_onnx(net, staging, opset=args.opset,
                    metadata={'matcher': meta.get('matcher'), 'weights': weights.name})
        seconds = time.perf_counter() - tic
        record: dict[str, Any] = {
            'arch': arch,
            'matcher': meta.get('matcher'),
            'max_disparity': depth,
            'weights': str(weights),
            'weights_facts': {
                k: meta[k] for k in ('samples_seen', 'command', 'date') if k in meta
            },
            'opset': args.opset,
            'input': {'name': 'cost_volume', 'shape': ['batch', depth, 'height', 'width'],
                      'dtype': 'float32', 'range': [0.0, 1.0]},
            'output': {'name': 'confidence', 'shape': ['batch', 'height', 'width'],
                       'dtype': 'float32', 'range': [0.0, 1.0]},
        }
        if not args.no_check:
            size = args.check_size or ((240, 320) if arch == 'cvanet_fast' else (60, 80))
            check = check_onnx(staging, net, size)
            height, width = size
            record['check'] = {'size': [height, width], **check}
            print(f'{PROG}: ONNX Runtime vs PyTorch at {height}x{width} (HxW, as --check-size): '
                  'max |difference| '
                  f'{check["max_abs_diff"]:.2e}; {check["onnxruntime_ms"]:.1f} ms against '
                  f'{check["torch_ms"]:.1f} ms (median of 3, {torch.get_num_threads()} torch '
                  'threads)', file=sys.stderr)
            if not check['max_abs_diff'] < 1e-4:
                raise ModelError(
                    f'the exported graph differs from PyTorch by {check["max_abs_diff"]:.2e} '
                    f'(more than 1e-4); {out} not written'
                )
        # The card first, whole or not at all: written after the graph, a card that could not
        # be written left the new graph beside the card of the one before (its matcher, D).
        write_text_atomic(card, strict_json.dumps(record, indent=2) + '\n')
        os.replace(staging, out)
    finally:
        staging.unlink(missing_ok=True)
    print(f'{PROG}: wrote {out} and {card.name} ({arch}, {meta.get("matcher")}, D = {depth}, '
          f'opset {args.opset}, {out.stat().st_size / 1e6:.2f} MB; exported in '
          f'{seconds:.1f} s)', file=sys.stderr)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``cva-export`` (``ros2 run cva_confidence_ros export``).

    Returns:
        0 when written (and checked); 2 on bad input or a graph or card that cannot be
        written (one line on stderr; a graph and card from before are left as they were); 1 if
        the checked graph cannot be moved in place; 130 / 143 stopped by Ctrl-C / SIGTERM.
    """
    from cva_confidence_ros.evaluation.cli import exit_code

    args = _build_parser().parse_args(argv)
    # exit_code tells SIGTERM ('terminated', 143) from Ctrl-C ('interrupted', 130).
    return exit_code(PROG, lambda: run(args))


if __name__ == '__main__':
    sys.exit(main())


"""Saving, loading and finding network weights (CVA-Net and every other learned method).

A weights file is a ``torch.save`` dict ``{'state_dict': ..., 'meta': {...}}``; ``meta`` holds at
least ``arch`` (a name of :data:`ARCHITECTURES`, e.g. ``'cvanet'``), ``matcher`` and
``max_disparity`` plus a training summary. Shipped weights are named
``<arch>_<matcher>_d<D>.pt``.

A network class takes part by having a class attribute ``arch`` (its registered name), an
attribute ``max_disparity``, and a builder registered in :data:`ARCHITECTURES` that rebuilds an
untrained instance from ``meta``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
import contextlib
import json
import os
from pathlib import Path
import sys
from typing import Any

import numpy as np
import torch
from torch import nn

from cva_confidence_ros.checks import is_int
from cva_confidence_ros.errors import ConfigError, ModelError, reason
from cva_confidence_ros.model.fast import CVANetFast
from cva_confidence_ros.model.inference import resolve_device
from cva_confidence_ros.model.lite import CVANetLite
from cva_confidence_ros.model.network import CVANet
from cva_confidence_ros.outputs import torch_save_atomic
from cva_confidence_ros.registry import Registry

__all__ = [
    'ARCH',
    'ARCHITECTURES',
    'PACKAGE',
    'default_weights_path',
    'load_weights',
    'save_weights',
    'weights_file_name',
    'weights_search_dirs',
]

#: The architecture name of CVA-Net itself (the default everywhere).
ARCH = 'cvanet'
PACKAGE = 'cva_confidence_ros'

#: arch name → builder ``(meta) -> nn.Module`` of an untrained network of that architecture.
ARCHITECTURES: Registry[Callable[[Mapping[str, Any]], nn.Module]] = Registry(
    'network architecture'
)
ARCHITECTURES.add(ARCH, lambda meta: CVANet(int(meta['max_disparity'])))
ARCHITECTURES.add(CVANetLite.arch, lambda meta: CVANetLite(int(meta['max_disparity'])))
ARCHITECTURES.add(CVANetFast.arch, lambda meta: CVANetFast(int(meta['max_disparity'])))


def weights_file_name(matcher: str, max_disparity: int, arch: str = ARCH) -> str:
    """Shipped-weights file name, e.g. ``cvanet_census_bm_d64.pt`` or ``ccnn_census_bm_d64.pt``."""
    return f'{arch}_{matcher}_d{int(max_disparity)}.pt'


def _unwrap(net: nn.Module) -> nn.Module:
    # torch.compile's wrapper: save_weights refused a compiled network ("got OptimizedModule").
    compiled = getattr(net, '_orig_mod', None)
    net = compiled if isinstance(compiled, nn.Module) else net
    inner = getattr(net, 'module', None)  # DistributedDataParallel
    return inner if isinstance(inner, nn.Module) else net


def architecture_of(net: nn.Module) -> str:
    """The registered architecture name of ``net`` (its class attribute ``arch``).

    Raises:
        ModelError: ``net`` belongs to no registered architecture.
    """
    model = _unwrap(net)
    arch = getattr(type(model), 'arch', None)
    if not isinstance(arch, str) or arch not in ARCHITECTURES:
        raise ModelError(
            f'expected a network of a registered architecture {ARCHITECTURES.names()}; '
            f'got {type(model).__name__}'
        )
    return arch


def _weights_path(path: object) -> Path:
    """``path`` as a :class:`Path`; ConfigError unless it is a str or an ``os.PathLike``."""
    if not isinstance(path, (str, os.PathLike)):
        raise ConfigError(
            f'weights path must be a str or os.PathLike; got {type(path).__name__} {path!r}'
        )
    return Path(path)


def _plain(value: object) -> object:
    """JSON stand-in of ``value``: a numpy scalar's Python number, else its string."""
    return value.item() if isinstance(value, np.generic) else str(value)


def save_weights(net: nn.Module, path: str | os.PathLike[str], meta: Mapping[str, Any]) -> Path:
    """Write ``net``'s weights and ``meta`` to ``path`` (parent folders are created).

    Args:
        net: A network of a registered architecture (or a DistributedDataParallel wrapper).
        path: Target ``.pt`` file; written to a temporary name first, then renamed.
        meta: At least ``matcher``; ``max_disparity`` and ``arch`` are filled in from ``net``.
            Stored as JSON-like plain values (tuples become lists, numpy scalars numbers,
            other objects strings); ``max_disparity`` always as an int.

    Returns:
        The written path.

    Raises:
        ModelError: ``net`` of no registered architecture; ``meta`` not a mapping, lacking
            ``matcher`` or contradicting the network's depth; ``path`` a directory or not
            writable (no temporary file is left behind).
        ConfigError: ``path`` neither a str nor an ``os.PathLike``.
    """
    arch = architecture_of(net)
    model = _unwrap(net)
    path = _weights_path(path)
    if not isinstance(meta, Mapping):
        raise ModelError(
            f'meta must be a mapping with at least matcher; got {type(meta).__name__} {meta!r}'
        )
    meta = dict(meta)
    if not meta.get('matcher'):
        raise ModelError(
            f'meta must name the matcher the weights are for; got keys {sorted(meta)}'
        )
    if meta.setdefault('max_disparity', model.max_disparity) != model.max_disparity:
        raise ModelError(
            f"meta['max_disparity'] = {meta['max_disparity']!r} contradicts the network's "
            f'D = {model.max_disparity} (an integer)'
        )
    # load_weights wants an int: 16.0 or np.int64(16) pass the check above but would not load.
    meta['max_disparity'] = int(meta['max_disparity'])
    meta['arch'] = arch
    # Only plain values load back with torch.load(weights_only=True); a JSON round trip turns
    # tuples into lists, numpy scalars into numbers and anything exotic (versions, paths) into
    # strings.
    try:
        meta = json.loads(json.dumps(meta, default=_plain))
    except (TypeError, ValueError) as exc:  # keys that are not text, circular values
        raise ModelError(f'meta must hold plain values under text keys ({reason(exc)})') from exc
    state = {k: v.detach().cpu() for k, v in model.state_dict().items()}
    if path.is_dir():
        raise ModelError(f'weights file {path} is a directory; expected a .pt file path')
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        # Not torch.save(path): it reported a full disk as 'unexpected pos …', not ENOSPC.
        torch_save_atomic(path, {'state_dict': state, 'meta': meta})
    except (OSError, RuntimeError) as exc:
        kept = '; the one there was left as it was' if path.is_file() else ''
        raise ModelError(f'cannot write weights file {path} ({reason(exc)}){kept}') from exc
    return path


def _check_stored_tensors(stored: Any, own: Mapping[str, torch.Tensor]) -> None:
    """Refuse stored tensors of another shape or kind than the network's: ``load_state_dict``
    would cast a complex tensor to real (dropping its imaginary part) or real values to
    integers (batch-norm counters) without a word.

    Raises:
        TypeError: Naming the tensor (turned into a ModelError by the caller).
    """
    if not isinstance(stored, Mapping):
        return  # load_state_dict names it
    for name, tensor in own.items():
        value = stored.get(name)
        if not isinstance(value, torch.Tensor):
            continue
        if value.is_complex() or value.is_floating_point() != tensor.is_floating_point():
            raise TypeError(f'{name} is {value.dtype}, the network holds {tensor.dtype}')
        if value.shape != tensor.shape:
            raise ValueError(
                f'{name} has shape {tuple(value.shape)}, the network holds {tuple(tensor.shape)}'
            )


def _class_name(arch: str, meta: Mapping[str, Any]) -> str:
    """The class the weights of ``arch`` load into (``'CVANetFast'``), for messages; '' for
    an architecture that is not registered or a ``meta`` it cannot be built from."""
    try:
        with torch.device('meta'):  # shapes only: nothing is allocated
            return type(ARCHITECTURES.get(arch)(meta)).__name__
    except (ConfigError, KeyError, TypeError, ValueError):
        return ''


def load_weights(
    path: str | os.PathLike[str],
    matcher: str | None = None,
    max_disparity: int | None = None,
    device: str | torch.device = 'cpu',
    arch: str | None = ARCH,
) -> tuple[Any, dict[str, Any]]:
    """Load a network in eval mode from a weights file and check what it is for.

    Args:
        path: A file written by :func:`save_weights`.
        matcher: If given, the matcher the weights must have been trained for.
        max_disparity: If given, the cost-volume depth D the weights must have.
        device: Where to put the network (``'cpu'``, ``'cuda'``, ``'auto'``).
        arch: The architecture the weights must be of (default CVA-Net); None = any
            registered architecture.

    Returns:
        ``(net, meta)``; ``net`` is a :class:`CVANet` unless ``arch`` says otherwise, in
        float32 whatever the stored precision (weights stored as float16 load as float32).

    Raises:
        ModelError: Missing, empty or corrupt file (or a cva-train checkpoint); a stored
            ``meta`` that is not a dict or whose ``arch`` or ``max_disparity`` has the wrong
            type; weights of another architecture; or weights for another matcher or depth
            than asked.
        ConfigError: ``path`` not a str or ``os.PathLike``, ``max_disparity`` not an integer,
            ``arch`` neither None nor a str, or a bad ``device`` (CUDA asked for where there
            is none); checked before the file is read.
    """
    path = _weights_path(path)
    torch_device = resolve_device(device)
    if max_disparity is not None and not is_int(max_disparity):
        raise ConfigError(
            f'max_disparity must be an integer or None; '
            f'got {type(max_disparity).__name__} {max_disparity!r}'
        )
    if arch is not None and not isinstance(arch, str):
        raise ConfigError(
            f'arch must be an architecture name or None; got {type(arch).__name__} {arch!r}'
        )
    if path.is_dir():
        raise ModelError(f'weights file {path} is a directory; expected a .pt file')
    if not path.exists():
        raise ModelError(f'weights file {path} does not exist')
    if not path.is_file():
        raise ModelError(f'weights file {path} is not a regular file; expected a .pt file')
    if path.stat().st_size == 0:
        raise ModelError(f'weights file {path} is empty')
    try:
        blob = torch.load(path, map_location='cpu', weights_only=True)
    except Exception as exc:  # torch raises many unrelated types for a damaged file
        if path.suffix.lower() == '.onnx':  # cva-export's graph given as model_path / weights
            raise ModelError(
                f'{path} is an ONNX graph, not a weights file: give the .pt weights it was '
                "exported from (cva_backend 'onnxruntime' exports them itself at start; an "
                'ONNX graph is run with ONNX Runtime, TensorRT or OpenVINO directly)'
            ) from exc
        raise ModelError(
            f'cannot read weights file {path} ({reason(exc)}); '
            'expected a torch.save dict with state_dict and meta'
        ) from exc
    if isinstance(blob, dict) and 'model' in blob and 'optimizer' in blob:
        raise ModelError(
            f'{path} is a cva-train checkpoint, not a weights file; the weights file is the '
            'one a finished run writes to --weights-out (continue this run with --resume)'
        )
    if not isinstance(blob, dict) or 'state_dict' not in blob or 'meta' not in blob:
        keys = sorted(blob) if isinstance(blob, dict) else type(blob).__name__
        raise ModelError(
            f'{path} is not a CVA-Net weights file: expected state_dict and meta; got {keys}'
        )
    if not isinstance(blob['meta'], dict):
        raise ModelError(
            f'{path} is not a CVA-Net weights file: expected meta to be a dict; '
            f"got {type(blob['meta']).__name__}"
        )
    meta = dict(blob['meta'])
    stored = meta.get('arch')
    if not isinstance(stored, str):
        raise ModelError(
            f"{path}: meta['arch'] must be an architecture name (str); "
            f'got {type(stored).__name__} {stored!r}'
        )
    if arch is not None and stored != arch:
        # Named with the class they load into and how: 'expected cvanet' alone left a user
        # of load_weights(path) with a CVA-Net-Fast file to guess the class and the argument.
        owner = _class_name(stored, meta)
        hint = (
            f' (they are {owner} weights: load them with arch={stored!r}, or arch=None for '
            'any architecture)'
            if owner
            else ''  # an unregistered arch: no class would load them
        )
        raise ModelError(f'{path} holds weights of arch {stored!r}; expected {arch!r}{hint}')
    if stored not in ARCHITECTURES:
        raise ModelError(
            f'{path} holds weights of arch {stored!r}; expected one of {ARCHITECTURES.names()}'
        )
    depth = meta.get('max_disparity')
    if isinstance(depth, bool) or not isinstance(depth, int):
        raise ModelError(
            f"{path}: meta['max_disparity'] must be an integer; "
            f'got {type(depth).__name__} {depth!r}'
        )
    for_what = f'matcher {meta.get("matcher")!r} and D = {meta.get("max_disparity")}'
    if matcher is not None and meta.get('matcher') != matcher:
        raise ModelError(
            f'{path} holds weights for {for_what}; asked for matcher {matcher!r}. '
            f'Train weights for it with: cva-train --matcher {matcher} ...'
        )
    if max_disparity is not None and meta.get('max_disparity') != int(max_disparity):
        raise ModelError(
            f'{path} holds weights for {for_what}; asked for D = {max_disparity}. '
            f'Train weights for it with: cva-train --max-disparity {max_disparity} ...'
        )
    try:
        # A shape-only build first: a corrupt depth (D = 10**12) is refused by the stored
        # tensors' shapes before any memory is allocated for it.
        with torch.device('meta'):
            skeleton = ARCHITECTURES.get(stored)(meta)
        _check_stored_tensors(blob['state_dict'], skeleton.state_dict())
        net = ARCHITECTURES.get(stored)(meta)
        net.load_state_dict(blob['state_dict'])
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        raise ModelError(
            f'{path}: the stored tensors do not fit arch {stored!r} ({reason(exc)})'
        ) from exc
    broken = [
        name
        for name, tensor in net.state_dict().items()
        if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all())
    ]
    if broken:
        raise ModelError(
            f'{path} holds NaN or infinite values in {len(broken)} tensors '
            f'(first: {broken[0]}); the training that wrote it diverged'
        )
    net.to(torch_device).eval()
    return net, meta


def weights_search_dirs() -> list[Path]:
    """Folders searched for shipped weights, in order: those of the running install first.

    1. ``models/`` of the source tree (editable installs and checkouts);
    2. ``share/cva_confidence_ros/models`` beside the installed package: in the folder of a
       ``pip install --target DIR`` and in the prefix of a ``<prefix>/lib/pythonX.Y/
       site-packages`` install (a venv's ``pip install``, ``--user``, ``--prefix``, a colcon
       install tree) used through ``PYTHONPATH``, where ``sys.prefix`` is another one;
    3. ``<sys.prefix>/share/cva_confidence_ros/models`` (pip install);
    4. the ament index share directory of the package (colcon install), when
       ``ament_index_python`` is importable and knows the package.
    """
    here = Path(__file__).resolve().parents  # model, cva_confidence_ros, site-packages, ...
    # sys.prefix came second: a colcon install tree or a --target install run with a venv's
    # Python loaded the weights of the (older) copy pip-installed into that venv.
    prefix = here[5] if len(here) > 5 and here[2].name in ('site-packages', 'dist-packages') \
        else None
    dirs = [here[2] / 'models']
    for base in (here[2], prefix, Path(sys.prefix)):
        folder = base / 'share' / PACKAGE / 'models' if base is not None else None
        if folder is not None and folder not in dirs:
            dirs.append(folder)
    try:
        from ament_index_python.packages import (
            PackageNotFoundError,
            get_package_share_directory,
        )
    except ImportError:
        return dirs
    try:
        dirs.append(Path(get_package_share_directory(PACKAGE)) / 'models')
    except (PackageNotFoundError, ValueError, KeyError, OSError):
        pass
    return dirs


def _shipped(arch: str, dirs: list[Path]) -> str:
    """What ``dirs`` hold for ``arch``, e.g. ``census_bm D = 64, 256; census_sgm D = 64``
    (a D or matcher that is not shipped was refused with a training command alone, although
    the weights asked for were often shipped for another D)."""
    # The longest registered name that prefixes a file is its architecture: cvanet_fast_*.pt
    # is no cvanet file for matcher 'fast_...'.
    names = sorted(ARCHITECTURES.names(), key=len, reverse=True)
    depths: dict[str, set[int]] = {}
    for folder in dirs:
        with contextlib.suppress(OSError):
            for file in folder.glob(f'{arch}_*_d*.pt'):
                owner = next((n for n in names if file.name.startswith(f'{n}_')), None)
                matcher, _, depth = file.stem[len(arch) + 1:].rpartition('_d')
                if owner == arch and matcher and depth.isdigit():
                    depths.setdefault(matcher, set()).add(int(depth))
    return '; '.join(
        f'{m} D = {", ".join(str(d) for d in sorted(ds))}' for m, ds in sorted(depths.items())
    ) or 'none'


def default_weights_path(matcher: str, max_disparity: int, arch: str = ARCH) -> Path:
    """Path of the shipped weights ``<arch>_<matcher>_d<D>.pt``.

    Raises:
        ModelError: No such file in any of :func:`weights_search_dirs`; the message lists the
            folders and says how to train the weights (or, for a D the architecture cannot
            take, says so instead of naming a training command that would fail).
    """
    name = weights_file_name(matcher, max_disparity, arch)
    dirs = weights_search_dirs()
    for folder in dirs:
        candidate = folder / name
        if candidate.is_file():
            return candidate
    looked = ', '.join(str(d) for d in dirs)
    if arch in ARCHITECTURES:
        try:  # a D the architecture cannot take: no command would train such weights
            with torch.device('meta'):
                ARCHITECTURES.get(arch)({'max_disparity': max_disparity})
        except ConfigError as error:
            raise ModelError(f'no {arch} network for D = {max_disparity}: {error}') from None
    raise ModelError(
        f'no shipped {arch} weights {name} for matcher {matcher!r} and D = {max_disparity}; '
        f'looked in: {looked}; {arch} weights there: {_shipped(arch, dirs)}. '
        f'Train them with: cva-train --arch {arch} --matcher {matcher} '
        f'--max-disparity {max_disparity} --data-root DATA --datasets kitti2012 '
        f'--weights-out models/{name}'
    )

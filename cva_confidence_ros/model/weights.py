"""Saving, loading and finding CVA-Net weights.

A weights file is a ``torch.save`` dict ``{'state_dict': ..., 'meta': {...}}``; ``meta`` holds at
least ``arch = 'cvanet'``, ``matcher`` and ``max_disparity`` plus a training summary.
Shipped weights are named ``cvanet_<matcher>_d<D>.pt``.
"""

from __future__ import annotations

from collections.abc import Mapping
import json
import os
from pathlib import Path
import sys
from typing import Any

import torch
from torch import nn

from cva_confidence_ros.errors import ModelError
from cva_confidence_ros.model.inference import resolve_device
from cva_confidence_ros.model.network import CVANet

__all__ = [
    'ARCH',
    'PACKAGE',
    'default_weights_path',
    'load_weights',
    'save_weights',
    'weights_file_name',
    'weights_search_dirs',
]

ARCH = 'cvanet'
PACKAGE = 'cva_confidence_ros'


def weights_file_name(matcher: str, max_disparity: int) -> str:
    """Shipped-weights file name for a matcher and depth, e.g. ``cvanet_census_bm_d64.pt``."""
    return f'{ARCH}_{matcher}_d{int(max_disparity)}.pt'


def save_weights(net: nn.Module, path: str | os.PathLike[str], meta: Mapping[str, Any]) -> Path:
    """Write ``net``'s weights and ``meta`` to ``path`` (parent folders are created).

    Args:
        net: A :class:`CVANet` (or a DistributedDataParallel wrapper of one).
        path: Target ``.pt`` file; written to a temporary name first, then renamed.
        meta: At least ``matcher``; ``max_disparity`` and ``arch`` are filled in from ``net``.
            Stored as JSON-like plain values (tuples become lists, other objects strings).

    Returns:
        The written path.

    Raises:
        ModelError: ``meta`` lacks ``matcher`` or contradicts the network's depth.
    """
    model = net.module if isinstance(getattr(net, 'module', None), CVANet) else net
    if not isinstance(model, CVANet):
        raise ModelError(f'expected a CVANet to save; got {type(model).__name__}')
    meta = dict(meta)
    if not meta.get('matcher'):
        raise ModelError(
            f'meta must name the matcher the weights are for; got keys {sorted(meta)}'
        )
    if meta.setdefault('max_disparity', model.max_disparity) != model.max_disparity:
        raise ModelError(
            f"meta['max_disparity'] = {meta['max_disparity']} contradicts the network's "
            f'D = {model.max_disparity}'
        )
    meta['arch'] = ARCH
    # Only plain values load back with torch.load(weights_only=True); a JSON round trip turns
    # tuples into lists and anything exotic (versions, paths) into strings.
    meta = json.loads(json.dumps(meta, default=str))
    state = {k: v.detach().cpu() for k, v in model.state_dict().items()}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + '.tmp')
    torch.save({'state_dict': state, 'meta': meta}, tmp)
    os.replace(tmp, path)
    return path


def load_weights(
    path: str | os.PathLike[str],
    matcher: str | None = None,
    max_disparity: int | None = None,
    device: str | torch.device = 'cpu',
) -> tuple[CVANet, dict[str, Any]]:
    """Load a :class:`CVANet` in eval mode from a weights file and check what it is for.

    Args:
        path: A file written by :func:`save_weights`.
        matcher: If given, the matcher the weights must have been trained for.
        max_disparity: If given, the cost-volume depth D the weights must have.
        device: Where to put the network (``'cpu'``, ``'cuda'``, ``'auto'``).

    Returns:
        ``(net, meta)``.

    Raises:
        ModelError: Missing, empty or corrupt file; not CVA-Net weights; or weights for another
            matcher or depth than asked.
    """
    path = Path(path)
    if not path.is_file():
        raise ModelError(f'weights file {path} does not exist')
    if path.stat().st_size == 0:
        raise ModelError(f'weights file {path} is empty')
    try:
        blob = torch.load(path, map_location='cpu', weights_only=True)
    except Exception as exc:  # torch raises many unrelated types for a damaged file
        raise ModelError(
            f'cannot read weights file {path} ({type(exc).__name__}: {exc}); '
            'expected a torch.save dict with state_dict and meta'
        ) from exc
    if not isinstance(blob, dict) or 'state_dict' not in blob or 'meta' not in blob:
        keys = sorted(blob) if isinstance(blob, dict) else type(blob).__name__
        raise ModelError(
            f'{path} is not a CVA-Net weights file: expected state_dict and meta; got {keys}'
        )
    meta = dict(blob['meta'])
    if meta.get('arch') != ARCH:
        raise ModelError(f'{path} holds weights of arch {meta.get("arch")!r}; expected {ARCH!r}')
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
        net = CVANet(int(meta['max_disparity']))
        net.load_state_dict(blob['state_dict'])
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        raise ModelError(f'{path}: the stored tensors do not fit CVA-Net ({exc})') from exc
    net.to(resolve_device(device)).eval()
    return net, meta


def weights_search_dirs() -> list[Path]:
    """Folders searched for shipped weights, in order.

    1. ``models/`` of the source tree (editable installs and checkouts);
    2. ``<sys.prefix>/share/cva_confidence_ros/models`` (pip install);
    3. the ament index share directory of the package (colcon install), when
       ``ament_index_python`` is importable and knows the package.
    """
    dirs = [
        Path(__file__).resolve().parents[2] / 'models',
        Path(sys.prefix) / 'share' / PACKAGE / 'models',
    ]
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


def default_weights_path(matcher: str, max_disparity: int) -> Path:
    """Path of the shipped weights ``cvanet_<matcher>_d<D>.pt``.

    Raises:
        ModelError: No such file in any of :func:`weights_search_dirs`; the message lists the
            folders and says how to train the weights.
    """
    name = weights_file_name(matcher, max_disparity)
    dirs = weights_search_dirs()
    for folder in dirs:
        candidate = folder / name
        if candidate.is_file():
            return candidate
    looked = ', '.join(str(d) for d in dirs)
    raise ModelError(
        f'no shipped CVA-Net weights {name} for matcher {matcher!r} and D = {max_disparity}; '
        f'looked in: {looked}. Train them with: cva-train --matcher {matcher} '
        f'--max-disparity {max_disparity} --data-root DATA --datasets kitti2012 '
        f'--weights-out models/{name}'
    )

"""Where tensors go: one reading of the ``device`` option for the network and MC-CNN."""

from __future__ import annotations

import torch

from cva_confidence_ros.errors import ConfigError

_NAMES = "'cpu', 'cuda', 'cuda:N' or 'auto'"


def resolve_device(device: str | torch.device) -> torch.device:
    """Turn ``'cpu'``, ``'cuda'``, ``'cuda:N'`` or ``'auto'`` (CUDA if available) into a
    :class:`torch.device`.

    Raises:
        ConfigError: An unknown name, CUDA asked for but not available, or a GPU index this
            machine does not have (torch takes any index; moving a network there fails with
            a CUDA error).
    """
    if isinstance(device, torch.device):
        resolved = device
    elif device == 'auto':
        return torch.device('cuda' if torch.cuda.is_available() else 'cpu')
    elif not isinstance(device, str) or device not in ('cpu', 'cuda') and not (
        device.startswith('cuda:') and device[5:].isdecimal()
    ):
        raise ConfigError(f'device must be {_NAMES}; got {device!r}')
    else:
        try:
            resolved = torch.device(device)
        except RuntimeError:  # an index torch cannot read: 'cuda:01', 'cuda:٣', 20 digits
            raise ConfigError(f'device must be {_NAMES}; got {device!r}') from None
    if resolved.type not in ('cpu', 'cuda'):
        raise ConfigError(f'device must be {_NAMES}; got {device!r}')
    if resolved.type == 'cuda':
        if not torch.cuda.is_available():
            raise ConfigError(f'device {str(device)!r} asked for, but CUDA is not available here')
        count = torch.cuda.device_count()
        if resolved.index is not None and resolved.index >= count:
            raise ConfigError(
                f'device {str(device)!r} asked for, but this machine has {count} CUDA device(s)'
            )
    return resolved

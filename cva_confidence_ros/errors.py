"""One exception tree for the whole package.

Every message says what was expected and what came, e.g.
``InputError("left and right must have the same shape; got (480, 640) and (480, 639)")``.
"""

from __future__ import annotations

import os
import re
import sys
from typing import NoReturn

__all__ = [
    'BagError',
    'CVAError',
    'ConfigError',
    'DataError',
    'end_process',
    'InputError',
    'MemoryShortfallError',
    'ModelError',
    'from_interrupt',
    'reason',
]


class CVAError(Exception):
    """Base class of every error raised on purpose by cva_confidence_ros."""


class ConfigError(CVAError, ValueError):
    """A configuration value (matcher name, parameter, option) is invalid.

    Args:
        message: What was expected and what came; ``str(error)`` is this message.
        *fields: Names of the values at fault as the raising class knows them — a dataclass
            field or node parameter — so that a front end that set them under other names,
            e.g. command-line options, can name those.

    Attributes:
        fields: Those names, in the order given; empty when not known.
    """

    def __init__(self, message: str, *fields: str) -> None:
        # Only the message in args: str() and pickling stay as they were (pickle restores
        # fields from the instance's __dict__).
        super().__init__(message)
        self.fields: tuple[str, ...] = fields


class InputError(CVAError, ValueError):
    """An input array or message has the wrong shape, dtype, encoding or values."""


class MemoryShortfallError(InputError):
    """An input whose processing needs more memory than is left here
    (``memory.available_memory``): refused before anything is allocated, the need in GB and
    what lowers it in the message."""


class DataError(CVAError):
    """A data set, file or folder cannot be read as expected."""


class ModelError(CVAError):
    """Weights are missing, corrupt, or do not fit the matcher or cost-volume depth."""


class BagError(CVAError):
    """A rosbag2 cannot be read or written as expected."""


def reason(exc: BaseException, limit: int = 200) -> str:
    """``'Type: first sentence of the message'``, at most ``limit`` characters of message.

    For wrapping a third-party exception into one of ours: torch's loader, for one, explains a
    damaged file over a dozen lines and suggests ``weights_only=False``, which is not advice to
    pass on for a file that is simply broken.
    """
    lines = str(exc).strip().splitlines()
    first = lines[0].strip() if lines else ''
    if first.endswith(':') and len(lines) > 1:  # a heading, e.g. torch's load_state_dict
        first = f'{first} {lines[1].strip()}'
    sentences = first.split('. ')
    first = sentences.pop(0)
    # A first 'sentence' that is only a bracketed tag says nothing (torch's writer: '[enforce
    # fail at inline_container.cc:747] . open file failed …'): the next one goes with it.
    while sentences and not re.sub(r'\[[^\]]*\]', '', first).strip(' .'):
        first = f'{first}. {sentences.pop(0)}'
    if len(first) > limit:
        first = first[: limit - 1] + '…'
    return f'{type(exc).__name__}: {first}' if first else type(exc).__name__


def from_interrupt(exc: BaseException) -> bool:
    """Whether ``exc`` is a Ctrl-C: a :class:`KeyboardInterrupt`, or an error it caused.

    Python raises the interrupt wherever it runs next, which can be a callback from C: inside
    a numba kernel's hand-over of its result it comes out as ``SystemError: CPUDispatcher(...)
    returned a result with an exception set``, the interrupt at the end of its chain.
    """
    seen: set[int] = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        if isinstance(current, KeyboardInterrupt):
            return True
        seen.add(id(current))
        current = current.__cause__ or current.__context__
    return False


def end_process(code: int) -> NoReturn:
    """End the process with ``code`` at once: output flushed, no interpreter finalisation.

    For exits with C++ threads still running (a worker inside torch, gloo's threads of a
    process group): finalising the interpreter under them can end one in ``std::terminate``
    (SIGABRT, after everything else went right).
    """
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    os._exit(code)

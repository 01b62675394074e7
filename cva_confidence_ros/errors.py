"""One exception tree for the whole package.

Every message says what was expected and what came, e.g.
``InputError("left and right must have the same shape; got (480, 640) and (480, 639)")``.
"""

from __future__ import annotations

from collections.abc import Iterator
import contextlib
import os
import re
import signal
import sys
import threading
from typing import NoReturn

__all__ = [
    'BagError',
    'CVAError',
    'ConfigError',
    'DataError',
    'EXIT_CLOSED_STDOUT',
    'closed_stdout',
    'end_process',
    'InputError',
    'MemoryShortfallError',
    'ModelError',
    'from_interrupt',
    'interrupted_exit',
    'reason',
    'sigterm_as_interrupt',
    'stdout_closed',
]

#: Exit status of a tool whose stdout reader went away (``cva-benchmark … | head -1``):
#: 128 + SIGPIPE, as a shell reports ``cat`` that the closed pipe ended.
EXIT_CLOSED_STDOUT = 128 + signal.SIGPIPE


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


@contextlib.contextmanager
def sigterm_as_interrupt() -> Iterator[list[int]]:
    """Treat SIGTERM (a batch system's time limit, ``timeout``, ``kill``) as Ctrl-C meanwhile:
    its default action ends the process at once, without a word and without its ``finally``
    blocks. Yields a list that holds the signal once it came (the tool then exits 143 instead
    of 130). Only in the main thread, only over the default action."""
    came: list[int] = []
    if threading.current_thread() is not threading.main_thread() or (
        signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL
    ):
        yield came
        return

    def interrupt(signum: int, _frame: object) -> None:
        came.append(signum)
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, interrupt)
    try:
        yield came
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


def stdout_closed() -> bool:
    """Whether stdout is a pipe whose reader went away (poll says POLLERR): a BrokenPipeError
    of another pipe (a subprocess, a socket) is no reader that wanted no more."""
    import select

    try:
        poller = select.poll()
        poller.register(sys.stdout.fileno(), select.POLLOUT)
        return any(events & select.POLLERR for _, events in poller.poll(0))
    except (AttributeError, OSError, ValueError):  # no poll (Windows), no file descriptor
        return False


def interrupted_exit(prog: str, terminated: list[int], detail: str = '') -> int:
    """Say in one line on stderr how ``prog`` was stopped (``terminated`` by SIGTERM, as
    :func:`sigterm_as_interrupt` yields it, else ``interrupted``: a batch system's SIGTERM is
    no Ctrl-C that anyone pressed), ``detail`` after it; return 143 or 130, as a shell reports
    a process that the signal ended."""
    print(f'{prog}: {"terminated" if terminated else "interrupted"}{detail}', file=sys.stderr)
    return 143 if terminated else 130


def closed_stdout() -> int:
    """For a :class:`BrokenPipeError` on stdout, whose reader went away (``| head -1``): point
    stdout at ``/dev/null``, so that the interpreter's last flush raises nothing either, and
    return :data:`EXIT_CLOSED_STDOUT`. Nothing is said: the reader wanted no more, as ``cat``
    ends quietly there (a tool said ``error: [Errno 32] Broken pipe`` and exited 1, another
    printed a traceback)."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):  # no file descriptor (a replaced sys.stdout)
        pass
    return EXIT_CLOSED_STDOUT

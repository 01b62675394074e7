"""Ctrl-C as a request to stop, noted rather than raised: how the package's nodes take SIGINT.

Python's own SIGINT handler raises ``KeyboardInterrupt`` at the next bytecode, wherever that is.
During a node's start that is often inside a C extension calling back into Python: torch's and
rclpy's C++ (where the exception cannot propagate and the process aborts with ``terminate called
after throwing … error_already_set … KeyboardInterrupt``), or a callback whose exception is only
printed, or library code that swallows it (the start then carries on and the node spins on,
deaf to the Ctrl-C that was meant to stop it). So a node notes the signal (:func:`install`) and
stops at points of its own: after its imports, once it is built, and, while it spins, through
rclpy, whose handler (installed by ``rclpy.init`` in front of this one, which it still calls)
shuts the context down on the same signal and so ends the executor's spin.

The handler replaces an inherited "ignore SIGINT" too (a background job of a script), as
``rclpy.init`` does with its own: a node takes SIGINT as a request to stop from its first line,
not only once rclpy is up. No rclpy here: this is installed before anything heavy is imported.

Once the stop has begun, SIGTERM means "stop now" (:func:`hurry`): ``ros2 launch`` sends it 5 s
after its SIGINT and SIGKILL 5 s later, so a stop that waits for a long frame must not wait on.
"""

from __future__ import annotations

import signal
import threading
from types import FrameType

__all__ = ['hurried', 'hurry', 'install', 'requested', 'restore']

_requested = threading.Event()
_hurried = threading.Event()
_previous: list[object] = []


def _note(signum: int, frame: FrameType | None) -> None:
    _requested.set()


def install() -> bool:
    """Note SIGINT from now on instead of raising ``KeyboardInterrupt``.

    Returns:
        False, and nothing changes, outside the main thread (where Python cannot set handlers).
    """
    if threading.current_thread() is not threading.main_thread():
        return False
    _requested.clear()
    _hurried.clear()
    _previous.append(signal.signal(signal.SIGINT, _note))
    return True


def restore() -> None:
    """Put back the handler :func:`install` replaced (the last one, when installed twice)."""
    if _previous and threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, _previous.pop())  # type: ignore[arg-type]


def requested() -> bool:
    """Whether a SIGINT came since :func:`install`."""
    return _requested.is_set()


def hurry(signum: int | None = None, frame: FrameType | None = None) -> None:
    """Ask a stop in progress not to wait for the frame being processed any longer (a signal
    handler: SIGTERM once the stop has begun)."""
    _hurried.set()


def hurried() -> bool:
    """Whether :func:`hurry` was called since :func:`install`."""
    return _hurried.is_set()

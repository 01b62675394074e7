"""Progress lines on stderr (frames done, frames per second, time left) and Ctrl-C handling."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
import signal
import sys
import threading
import time
from types import FrameType
from typing import TextIO

__all__ = ['GracefulInterrupt', 'Progress']


class Progress:
    """Prints ``<prefix> done/total frames, X fps, ~Y s left`` to a stream.

    On a terminal the line is rewritten in place; otherwise (logs, pipes) a new line is
    written at most every ``interval`` seconds, plus one at the end.

    Args:
        total: Expected number of frames (0 if unknown).
        prefix: Text in front of each line.
        stream: Where to write; stderr by default.
        interval: Least seconds between two lines when not on a terminal.
        clock: Time source (seconds), replaceable in tests.
    """

    def __init__(
        self,
        total: int,
        prefix: str = '',
        stream: TextIO | None = None,
        interval: float = 1.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.total = max(int(total), 0)
        self.prefix = prefix
        self.stream = stream if stream is not None else sys.stderr
        self.interval = interval
        self.clock = clock
        self.done = 0
        self._start = clock()
        self._last = -float('inf')
        self._printed = -1
        self._tty = bool(getattr(self.stream, 'isatty', lambda: False)())

    def line(self) -> str:
        """The current progress text."""
        elapsed = max(self.clock() - self._start, 1e-9)
        rate = self.done / elapsed
        text = f'{self.prefix}{self.done}/{self.total or "?"} frames, {rate:.2f} fps'
        if self.total and self.done and self.done < self.total:
            text += f', ~{(self.total - self.done) / rate:.0f} s left'
        return text

    def update(self, done: int | None = None, force: bool = False) -> None:
        """Record progress (one more frame, or ``done`` frames) and print if it is time."""
        self.done = self.done + 1 if done is None else int(done)
        now = self.clock()
        if self._tty:
            self.stream.write('\r' + self.line() + '\x1b[K')
            self.stream.flush()
        elif force or now - self._last >= self.interval:
            self._last = now
            self._printed = self.done
            self.stream.write(self.line() + '\n')
            self.stream.flush()

    def finish(self) -> None:
        """Print the final line (unless the last line printed says the same)."""
        if self._tty:
            self.stream.write('\r' + self.line() + '\x1b[K\n')
        elif self._printed != self.done:
            self.stream.write(self.line() + '\n')
        self.stream.flush()


class GracefulInterrupt:
    """Turns SIGINT/SIGTERM into :class:`KeyboardInterrupt`, but never inside a critical section.

    Writing a message into a bag must not be cut in half, or the storage file could not be
    finalised. Inside :meth:`critical` a signal is only noted; it is raised when the section
    ends. Outside, it is raised at once, which aborts a long computation (the frame being
    processed is lost, the frames already written are kept).

    Use as a context manager around the whole run; the previous handlers come back on exit.
    Signal handlers can only be set from the main thread; elsewhere this does nothing.
    """

    def __init__(self) -> None:
        self.requested = False
        self._depth = 0
        self._closing = False
        self._previous: dict[int, object] = {}

    def _handler(self, signum: int, frame: FrameType | None) -> None:
        self.requested = True
        if self._depth == 0 and not self._closing:
            raise KeyboardInterrupt

    def __enter__(self) -> GracefulInterrupt:
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous[sig] = signal.signal(sig, self._handler)
        return self

    def __exit__(self, *exc: object) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)  # type: ignore[arg-type]
        self._previous.clear()

    @contextmanager
    def critical(self) -> Iterator[None]:
        """A section that a signal does not interrupt (it is raised after the section)."""
        self._depth += 1
        try:
            yield
        finally:
            self._depth -= 1
        if self._depth == 0 and self.requested and not self._closing:
            raise KeyboardInterrupt

    def closing(self) -> None:
        """From now on only note signals: the outputs are being finalised and must not break."""
        self._closing = True

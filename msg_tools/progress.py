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

__all__ = ['GracefulInterrupt', 'Progress', 'print_above']

# The progress line being rewritten in place on a terminal (no newline after it yet): a log
# line printed to its stream goes above it (print_above), not onto its end.
_open_line: Progress | None = None


def print_above(message: str, stream: TextIO | None = None) -> None:
    """Print ``message`` as a line of ``stream`` (stderr by default); where a progress line
    is being rewritten there on a terminal, above it (the line is cleared, the message
    printed, the progress drawn again), not glued to its end."""
    stream = stream if stream is not None else sys.stderr
    line = _open_line
    if line is not None and line.stream is stream:
        stream.write('\r\x1b[K' + message + '\n' + line.line() + '\x1b[K')
    else:
        stream.write(message + '\n')
    stream.flush()


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
        text = f'{self.prefix}{self.done}/{self.total or "?"} frames'
        elapsed = self.clock() - self._start
        if elapsed <= 0:
            # No time measured yet (a coarse clock): no rate to tell, nor a time left from it.
            return f'{text}, ? fps'
        rate = self.done / elapsed
        text += f', {rate:.2f} fps'
        if self.total and self.done and self.done < self.total:
            text += f', ~{(self.total - self.done) / rate:.0f} s left'
        return text

    def update(self, done: int | None = None, force: bool = False) -> None:
        """Record progress (one more frame, or ``done`` frames) and print if it is time."""
        self.done = self.done + 1 if done is None else int(done)
        now = self.clock()
        if self._tty:
            global _open_line
            _open_line = self
            self.stream.write('\r' + self.line() + '\x1b[K')
            self.stream.flush()
        elif force or now - self._last >= self.interval:
            self._last = now
            self._printed = self.done
            self.stream.write(self.line() + '\n')
            self.stream.flush()

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc: object) -> None:
        # Also on an error or Ctrl-C: the line ends, so what is printed next starts a line.
        self.finish()

    def finish(self) -> None:
        """Print the final line (unless the last line printed says the same)."""
        global _open_line
        if _open_line is self:
            _open_line = None
        if self._tty:
            self.stream.write('\r' + self.line() + '\x1b[K\n')
        elif self._printed != self.done:
            self.stream.write(self.line() + '\n')
        self.stream.flush()


class GracefulInterrupt:
    """SIGINT/SIGTERM as a request to stop, raised as :class:`KeyboardInterrupt` where it is safe.

    The first signal is only noted (and a line on stderr says so, when ``notice`` is given); the
    run raises it at its next :meth:`check` (between frames, in its waits). Raised from the
    handler itself, it could land wherever Python happens to run next: inside numba's or
    torch's C code calling back into Python, where it becomes a ``SystemError`` or aborts the
    process. A second signal outside a critical section is raised at once, for a step that
    takes long. Inside :meth:`critical` (writing a
    message into a bag, which must not be cut in half) and after :meth:`closing` (the outputs
    are being finalised) signals are only noted (the first with its line inside a critical
    section, with none after :meth:`closing`).

    Use as a context manager around the run; it may be entered again inside (the handlers are
    set by the outermost ``with`` and put back when it ends). Signal handlers can only be set
    from the main thread; elsewhere this does nothing.

    Args:
        notice: Written to stderr on the first signal, e.g. ``stopping after this frame``.
    """

    def __init__(self, notice: str = '') -> None:
        self.notice = notice
        self._signals = 0
        self.signum = 0
        self._depth = 0
        self._closing = False
        self._entered = 0
        self._previous: dict[int, object] = {}

    @property
    def requested(self) -> bool:
        """Whether a signal came."""
        return self._signals > 0

    @property
    def exit_code(self) -> int:
        """The status of a run the signals stopped: 128 + the first one's number, as a shell
        reports a process it ended (130 Ctrl-C, 143 SIGTERM, as ``cva-evaluate`` and
        ``cva-param``); 130 when none came (a Ctrl-C outside the handlers)."""
        return 128 + (self.signum or signal.SIGINT)

    def _handler(self, signum: int, frame: FrameType | None) -> None:
        self._signals += 1
        self.signum = self.signum or signum
        if self._closing:
            return
        if self._signals > 1:
            if not self._depth:
                raise KeyboardInterrupt
            return
        # Said inside a critical section too (its next check stops the run all the same): a
        # first Ctrl-C there went without a word, and a user pressed again, unanswered.
        if self.notice:
            notice, again = self.notice, 'Ctrl-C again'
            if signum == signal.SIGTERM:
                # A batch system's time limit or `kill` is no Ctrl-C that anyone pressed.
                notice, again = notice.replace('Ctrl-C:', 'SIGTERM:'), 'a second signal'
            print_above(f'{notice} ({again} to stop at once)')

    def __enter__(self) -> GracefulInterrupt:
        self._entered += 1
        if self._entered == 1 and threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous[sig] = signal.signal(sig, self._handler)
        return self

    def __exit__(self, *exc: object) -> None:
        self._entered -= 1
        if self._entered:
            return
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)  # type: ignore[arg-type]
        self._previous.clear()

    def check(self) -> None:
        """Raise :class:`KeyboardInterrupt` if a signal came (outside critical sections and
        before :meth:`closing`)."""
        if self.requested and not self._depth and not self._closing:
            raise KeyboardInterrupt

    @contextmanager
    def critical(self) -> Iterator[None]:
        """A section that no signal interrupts, not even a second one (the next :meth:`check`
        raises it)."""
        self._depth += 1
        try:
            yield
        finally:
            self._depth -= 1

    def closing(self) -> None:
        """From now on only note signals: the outputs are being finalised and must not break."""
        self._closing = True

"""``errors.reason``: a third-party exception as one short clause for our messages;
``errors.from_interrupt``: a Ctrl-C, also when it surfaced as another error."""

from __future__ import annotations

import pytest

from cva_confidence_ros.errors import from_interrupt, reason


def test_reason_keeps_type_and_first_sentence_only():
    exc = RuntimeError('Weights only load failed. Re-run with weights_only=False.\nMore lines.')
    assert reason(exc) == 'RuntimeError: Weights only load failed'
    assert reason(ValueError('no sentence end')) == 'ValueError: no sentence end'
    assert reason(KeyError()) == 'KeyError'
    text = 'Error(s) in loading state_dict for Net:\n\tsize mismatch for w: 2 vs 3.'
    heading = RuntimeError(text)
    assert reason(heading) == 'RuntimeError: Error(s) in loading state_dict for Net: size ' \
        'mismatch for w: 2 vs 3.'
    long = reason(OSError('x' * 500), limit=50)
    assert long.startswith('OSError: ') and long.endswith('…')
    assert len(long) == len('OSError: ') + 50


def _interrupted_kernel() -> SystemError:
    """What a Ctrl-C raised by Python's handler during a numba kernel turns into."""
    import os
    import signal
    import threading

    import numpy as np

    from cva_confidence_ros.confidence.handcrafted import two_smallest

    def handler(signum: int, frame: object) -> None:
        raise KeyboardInterrupt

    volume = np.random.default_rng(0).random((600, 800, 64), dtype=np.float32)
    two_smallest(volume[:8, :8])  # compiled before the signal
    previous = signal.signal(signal.SIGINT, handler)
    timer = threading.Timer(0.05, os.kill, (os.getpid(), signal.SIGINT))
    try:
        timer.start()
        while True:
            two_smallest(volume)
    except SystemError as exc:
        return exc
    finally:
        timer.join()
        signal.signal(signal.SIGINT, previous)


def test_from_interrupt_follows_the_chain_to_a_ctrl_c():
    assert from_interrupt(KeyboardInterrupt())
    assert not from_interrupt(SystemError('a real fault'))
    try:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as inner:
            raise RuntimeError('while handling it') from inner
    except RuntimeError as outer:
        assert from_interrupt(outer)
    looped = ValueError('a')
    looped.__context__ = ValueError('b')
    looped.__context__.__context__ = looped
    assert not from_interrupt(looped)
    # The real thing: numba's callback into Python got the interrupt.
    exc = _interrupted_kernel()
    assert 'returned a result with an exception set' in str(exc)
    assert from_interrupt(exc)


def test_the_evaluation_tools_exit_130_on_ctrl_c(capsys):
    from cva_confidence_ros.evaluation.cli import exit_code

    def interrupted() -> int:
        raise _interrupted_kernel()

    def keyboard() -> int:
        raise KeyboardInterrupt

    def fault() -> int:
        raise SystemError('a real fault')

    assert exit_code('cva-evaluate', interrupted) == 130
    assert exit_code('cva-evaluate', keyboard) == 130
    assert capsys.readouterr().err.splitlines() == ['cva-evaluate: interrupted'] * 2
    with pytest.raises(SystemError, match='a real fault'):
        exit_code('cva-evaluate', fault)

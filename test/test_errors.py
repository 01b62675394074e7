"""``errors.reason``: a third-party exception as one short clause for our messages."""

from __future__ import annotations

from cva_confidence_ros.errors import reason


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

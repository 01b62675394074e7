"""``errors.reason``: a message whose first sentence is only a tag keeps the one after it."""

from __future__ import annotations

from cva_confidence_ros.errors import reason


def test_a_bracketed_tag_alone_is_no_first_sentence() -> None:
    # torch's writer: the cut at the first '. ' left only the tag, not the cause.
    exc = RuntimeError('[enforce fail at inline_container.cc:747] . open file failed because '
                       'of errno 21 on fopen: Is a directory, file path: out/c.pt. More text.')
    assert reason(exc) == ('RuntimeError: [enforce fail at inline_container.cc:747] . open file '
                           'failed because of errno 21 on fopen: Is a directory, file path: '
                           'out/c.pt')
    # An ordinary message still ends at its first sentence.
    assert reason(ValueError('bad header. See the docs.')) == 'ValueError: bad header'
    assert reason(OSError('[Errno 28] No space left on device')) == (
        'OSError: [Errno 28] No space left on device')

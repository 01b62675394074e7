"""A camera driver that leaves its header stamps at zero is named as such, not taken for a bag
on a loop (every frame after the first paired as 'the same frame again')."""

from __future__ import annotations

import time

from node_test_utils import (
    SMALL_MLM,
    LogRecorder,
    feed_frame,
    first_stamp,
    localhost_context,
    spare_domain_id,
    textured_pair,
)
import pytest

from cva_confidence_ros.node import ConfidenceNode

pytestmark = pytest.mark.timeout(120)


def _frames(stamps: list[int]) -> list[tuple[str, str]]:
    with localhost_context(spare_domain_id()) as context:
        node = ConfidenceNode(context=context, parameter_overrides=list(SMALL_MLM))
        recorder = LogRecorder()
        node.get_logger = lambda: recorder  # type: ignore[method-assign]
        try:
            left, right = textured_pair()
            for stamp in stamps:
                feed_frame(node, left, right, stamp)
                time.sleep(0.3)  # one frame at a time, as a camera sends them
            return recorder.lines
        finally:
            node.destroy_node()


def test_header_stamps_of_zero_are_named_as_the_drivers_fault() -> None:
    lines = _frames([0, 0, 0])
    warnings = [line for level, line in lines if level == 'warning']
    assert any('left/camera_info has header stamp 0: its driver does not stamp' in line
               for line in warnings), warnings
    # Before: 'input stamps repeat: the frame 0.000000000 came again (a bag played again or on
    # a loop?)', the only line.
    assert not any('bag played again' in line for line in warnings), warnings


def test_real_stamps_say_nothing_of_it() -> None:
    start = first_stamp()
    lines = _frames([start, start + 100_000_000])
    assert not any('header stamp 0' in line for _, line in lines)

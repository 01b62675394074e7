"""Review 33 of the managed node as a lifecycle manager drives it, cycle after cycle: a frame
taken by the worker at the moment of a deactivate, or half published when it came, went out
after a quick activate, an old frame after pairing started afresh (regression tests of faults
found in the review)."""

from __future__ import annotations

from collections.abc import Iterator
import threading
from typing import Any

from node_test_utils import (
    SMALL_MLM,
    feed_frame,
    first_stamp,
    localhost_context,
    spare_domain_id,
    textured_pair,
    wait_until,
)
import pytest

from cva_confidence_ros.node import ManagedConfidenceNode

pytestmark = pytest.mark.timeout(120)


@pytest.fixture
def node() -> Iterator[ManagedConfidenceNode]:
    with localhost_context(spare_domain_id()) as context:
        managed = ManagedConfidenceNode(context=context, parameter_overrides=list(SMALL_MLM))
        try:
            managed.trigger_configure()
            managed.trigger_activate()
            yield managed
        finally:
            managed.destroy_node()


def _state(node: ManagedConfidenceNode) -> str:
    return str(node._state_machine.current_state[1])


def _published_stamps(node: ManagedConfidenceNode) -> list[int]:
    """Spy on the frames the worker publishes: the list fills with their stamps."""
    stamps: list[int] = []
    publish = node._publish

    def spy(result: Any, header: Any, *args: Any) -> None:
        stamps.append(header.stamp.sec * 1_000_000_000 + header.stamp.nanosec)
        publish(result, header, *args)

    node._publish = spy  # type: ignore[method-assign]
    return stamps


def test_a_frame_taken_as_the_deactivate_comes_is_not_published_after_activate(
    node: ManagedConfidenceNode,
) -> None:
    # The worker noted the frame's activation only after taking it from the mailbox: a
    # deactivate in between (the executor thread) made the frame count as the next
    # activation's, and after a quick activate it went out, an old frame.
    mailbox = node._mailbox
    take = mailbox.take
    waiting, taken, go_on = threading.Event(), threading.Event(), threading.Event()

    def slow_take() -> Any:
        waiting.set()
        item = take()
        if item is not None and not taken.is_set():
            taken.set()
            go_on.wait(10.0)
        return item

    mailbox.take = slow_take  # type: ignore[method-assign]
    mailbox.poke()  # the worker waits in the take of before: on to this one
    assert waiting.wait(10.0)
    stamps = _published_stamps(node)
    left, right = textured_pair()
    old, new = first_stamp(), first_stamp() + 100_000_000
    feed_frame(node, left, right, old)
    assert taken.wait(10.0)
    node.trigger_deactivate()
    node.trigger_activate()
    assert _state(node) == 'active'
    go_on.set()
    feed_frame(node, left, right, new)
    assert wait_until(lambda: new in stamps, timeout=10.0)
    assert old not in stamps


def test_a_frame_half_published_at_a_deactivate_does_not_finish_after_activate(
    node: ManagedConfidenceNode,
) -> None:
    # The deactivate only disabled the lifecycle publishers: the worker, between two outputs
    # of a frame, went on with the next ones once a quick activate enabled them again.
    publisher = node._pub_disparity
    in_publish, go_on, deactivated = threading.Event(), threading.Event(), threading.Event()
    sent: list[bool] = []  # for each disparity published: whether the deactivate was done

    def slow_count() -> int:
        if not in_publish.is_set():
            in_publish.set()
            go_on.wait(10.0)
        return 1

    publish = publisher.publish

    def spy(msg: Any) -> None:
        sent.append(deactivated.is_set())
        publish(msg)

    publisher.get_subscription_count = slow_count  # type: ignore[method-assign]
    publisher.publish = spy  # type: ignore[method-assign]
    stamps = _published_stamps(node)
    left, right = textured_pair()
    old, new = first_stamp(), first_stamp() + 100_000_000
    feed_frame(node, left, right, old)
    assert in_publish.wait(10.0)

    def cycle() -> None:
        node.trigger_deactivate()
        deactivated.set()
        node.trigger_activate()

    manager = threading.Thread(target=cycle)
    manager.start()
    manager.join(0.3)  # a deactivate that waits for the frame's outputs is still at it here
    go_on.set()
    manager.join(10.0)
    assert not manager.is_alive()
    assert _state(node) == 'active'
    feed_frame(node, left, right, new)
    assert wait_until(lambda: new in stamps and len(sent) == 2, timeout=10.0)
    # The old frame's disparity went out before the deactivate ended (which waited for it);
    # the new frame's after it.
    assert sent == [False, True]

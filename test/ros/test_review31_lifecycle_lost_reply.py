"""Review 31 of cva-lifecycle: a transition whose reply is lost is judged by the node's state
only where that state changed; a node already in the goal state refused it."""

from __future__ import annotations

import time
from typing import Any

from lifecycle_msgs.msg import State, Transition
from lifecycle_msgs.srv import ChangeState, GetState
from node_test_utils import localhost_context, spare_domain_id
import pytest
from rclpy.node import Node
from rclpy.task import Future

from cva_confidence_ros.ros import lifecycle_cli

pytestmark = pytest.mark.timeout(60)


class LostReply:
    """A change_state client whose request goes out and whose reply never comes."""

    def __init__(self) -> None:
        self.sent = 0

    def call_async(self, request: Any) -> Future:
        self.sent += 1
        return Future()


class States:
    """A get_state client answering the labels given, one per call (the last one again)."""

    def __init__(self, *labels: str) -> None:
        self.labels = list(labels)

    def call_async(self, request: Any) -> Future:
        label = self.labels.pop(0) if len(self.labels) > 1 else self.labels[0]
        future = Future()
        future.set_result(GetState.Response(current_state=State(label=label)))
        return future


@pytest.mark.parametrize(('states', 'success'), [
    # Before: the poll found 'inactive' and said "Transitioning successful" for a configure
    # that the inactive node had refused.
    (('inactive',), None),
    (('unconfigured', 'inactive'), True),  # a lost reply of a configure that was taken
])
def test_a_lost_reply_counts_as_success_only_where_the_state_changed(
    monkeypatch: pytest.MonkeyPatch, states: tuple[str, ...], success: bool | None
) -> None:
    monkeypatch.setattr(lifecycle_cli, 'ATTEMPT_S', 0.1)
    with localhost_context(spare_domain_id()) as context:
        node = Node('review31_lifecycle', context=context)
        try:
            change = LostReply()
            request = ChangeState.Request(transition=Transition(label='configure'))
            answer = lifecycle_cli._change_state(
                node, change, States(*states), request, 'inactive', time.monotonic() + 1.0
            )
        finally:
            node.destroy_node()
    assert change.sent == 1  # a transition is never sent twice
    if success is None:
        assert answer is None  # no answer: exit 2, "no answer from …"
    else:
        assert answer is not None and answer.success is success

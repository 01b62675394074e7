"""Review 32 of the managed node and ``cva-lifecycle``: a ``change_state`` request by id alone
that the state does not have, an empty transition label, and a node that is there but busy
(each a regression test of a fault found in the review)."""

from __future__ import annotations

from collections.abc import Iterator
import os
import subprocess
import sys
import threading
from typing import Any

from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState
from node_test_utils import SMALL_MLM, Spinner, localhost_context, spare_domain_id
import pytest

from cva_confidence_ros.node import ManagedConfidenceNode
from cva_confidence_ros.ros import lifecycle_cli

pytestmark = pytest.mark.timeout(120)


@pytest.fixture
def context_and_domain() -> Iterator[tuple[Any, int]]:
    domain = spare_domain_id()
    with localhost_context(domain) as context:
        yield context, domain


def _state(node: ManagedConfidenceNode) -> str:
    return str(node._state_machine.current_state[1])


def _change_state_service(node: ManagedConfidenceNode) -> Any:
    (service,) = [srv for srv in node.services if srv.srv_name.endswith('/change_state')]
    return service


def _by_id(node: ManagedConfidenceNode, transition_id: int) -> bool:
    """Answer a ``change_state`` request carrying an id and no label as the executor would (as
    ``ros2 service call …/change_state lifecycle_msgs/srv/ChangeState '{transition: {id: 3}}'``
    sends it)."""
    request = ChangeState.Request(transition=Transition(id=transition_id))
    return bool(_change_state_service(node).callback(request, ChangeState.Response()).success)


def test_a_transition_by_an_id_the_state_does_not_have_is_refused_not_raised(
    context_and_domain: tuple[Any, int],
) -> None:
    # rclpy raised RCLError ('Transition is not registered') out of the service callback, which
    # ended the executor's spin: an 'activate' by id to an unconfigured node (or the id 0 an
    # empty label means) stopped the node for good instead of being refused.
    context, _ = context_and_domain
    node = ManagedConfidenceNode(context=context, parameter_overrides=list(SMALL_MLM))
    try:
        for transition_id in (Transition.TRANSITION_ACTIVATE, 0, 99):
            assert _by_id(node, transition_id) is False
            assert _state(node) == 'unconfigured'
        # A transition by id that the state has goes through as ever.
        assert _by_id(node, Transition.TRANSITION_CONFIGURE) is True
        assert _state(node) == 'inactive'
        assert _by_id(node, Transition.TRANSITION_CONFIGURE) is False
        assert _by_id(node, Transition.TRANSITION_ACTIVATE) is True
        assert _state(node) == 'active'
        by_label = ChangeState.Request(transition=Transition(label='deactivate'))
        assert _change_state_service(node).callback(by_label, ChangeState.Response()).success
        assert _state(node) == 'inactive'
    finally:
        node.destroy_node()


def test_cva_lifecycle_refuses_an_empty_transition_label(
    capsys: pytest.CaptureFixture[str],
) -> None:
    # Sent as is, '' asked for transition id 0, which ended the node (see above); the tool
    # then waited its whole --timeout and said the node was perhaps not running.
    assert lifecycle_cli.main(['--timeout', '0.5', 'set', '/cva_confidence', '']) == 2
    err = capsys.readouterr().err
    assert "TRANSITION must be a transition's label (configure, activate" in err, err
    assert "got ''" in err
    assert lifecycle_cli.main(['--timeout', '0.5', 'set', '/cva_confidence', ' ']) == 2
    assert "got ' '" in capsys.readouterr().err


def test_cva_lifecycle_tells_a_busy_node_from_one_that_is_not_there(
    context_and_domain: tuple[Any, int],
) -> None:
    # A node in a long transition (a configure that loads a network) was reported as "is
    # /cva_confidence running, a managed node, and in this ROS_DOMAIN_ID?" although its service
    # had been found and the transition went on.
    context, domain = context_and_domain
    node = ManagedConfidenceNode(context=context, parameter_overrides=list(SMALL_MLM))
    service = _change_state_service(node)
    answer = service.callback
    release = threading.Event()

    def busy(request: Any, response: Any) -> Any:
        release.wait(30.0)
        return answer(request, response)

    service.callback = busy
    spinner = Spinner(context, node)
    try:
        env = dict(os.environ, ROS_DOMAIN_ID=str(domain),
                   ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
        done = subprocess.run(
            [sys.executable, '-m', 'cva_confidence_ros.ros.lifecycle_cli', '--timeout', '3',
             'set', '/cva_confidence', 'configure'],
            capture_output=True, text=True, timeout=60, env=env,
        )  # fmt: skip
        release.set()
        assert done.returncode == 2, done
        assert '/cva_confidence/change_state is there but did not answer within 3 s ' \
            '(the transition may still be going on' in done.stderr, done.stderr
        assert 'is /cva_confidence running' not in done.stderr
    finally:
        release.set()
        spinner.stop()
        node.destroy_node()


def test_an_activate_that_raises_unexpectedly_says_why(
    context_and_domain: tuple[Any, int], monkeypatch: pytest.MonkeyPatch
) -> None:
    # rclpy turns an exception of on_activate into ERROR without a word: the node ended
    # unconfigured and its log did not say why.
    context, _ = context_and_domain
    node = ManagedConfidenceNode(context=context, parameter_overrides=list(SMALL_MLM))
    errors: list[str] = []
    logger = node.get_logger()

    class Recording:
        def __getattr__(self, name: str) -> Any:
            return getattr(logger, name)

        def error(self, message: str, **kwargs: Any) -> None:
            errors.append(message)

    def broken() -> None:
        raise RuntimeError('a subscription could not be made')

    try:
        assert _by_id(node, Transition.TRANSITION_CONFIGURE) is True
        monkeypatch.setattr(node, 'get_logger', lambda: Recording())
        monkeypatch.setattr(node, '_activate', broken)
        assert _by_id(node, Transition.TRANSITION_ACTIVATE) is False
        assert _state(node) == 'unconfigured'  # on_error cleaned up: configure again
        assert 'activate raised RuntimeError: a subscription could not be made' in errors
    finally:
        node.destroy_node()

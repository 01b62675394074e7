"""Review 27 of the managed node: its public views in every lifecycle state, and a configure that
raises half way (each a regression test of a fault found in the review)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

from diagnostic_msgs.msg import DiagnosticStatus
from node_test_utils import localhost_context, spare_domain_id
import pytest
from rclpy.lifecycle import TransitionCallbackReturn
from rclpy.parameter import Parameter

from cva_confidence_ros.errors import CVAError
from cva_confidence_ros.node import ManagedConfidenceNode
from cva_confidence_ros.ros.lifecycle_node import NotConfiguredError

pytestmark = pytest.mark.timeout(120)

OVERRIDES = [
    Parameter('matcher', value='census_bm'),
    Parameter('max_disparity', value=16),
    Parameter('confidence_method', value='mlm'),
]
COUNTERS = {
    'messages_received', 'frames_received', 'frames_processed', 'frames_dropped',
    'frames_throttled', 'messages_unmatched', 'frames_invalid', 'frames_failed', 'stamp_jumps',
}


@pytest.fixture
def node() -> Iterator[ManagedConfidenceNode]:
    """A managed node, unconfigured, in a localhost context of its own (not spun: the tests
    trigger its transitions in this thread)."""
    with localhost_context(spare_domain_id()) as context:
        made = ManagedConfidenceNode(context=context, parameter_overrides=list(OVERRIDES))
        try:
            yield made
        finally:
            made.destroy_node()


def _state(node: ManagedConfidenceNode) -> str:
    return str(node._state_machine.current_state[1])


def _assert_not_configured(node: ManagedConfidenceNode, state: str) -> None:
    """What a node that is not configured answers: zero-or-kept counters, a stale status that
    names the state, and a clear error for the configurations."""
    assert set(node.stats()) == COUNTERS
    status = node.diagnostics()
    assert status.level == DiagnosticStatus.STALE
    assert status.message.startswith(f'{state}: not processing'), status.message
    values = {kv.key: kv.value for kv in status.values}
    assert values['lifecycle_state'] == state
    assert {key: int(values[key]) for key in COUNTERS} == node.stats()
    for name in ('pipeline_config', 'node_config'):
        with pytest.raises(NotConfiguredError, match=f'{name} exists only while the node is '
                           rf'configured \(inactive or active\); it is {state}'):
            getattr(node, name)


def test_an_unconfigured_node_answers_stats_diagnostics_and_its_configs(
    node: ManagedConfidenceNode,
) -> None:
    # stats(), diagnostics(), pipeline_config and node_config raised AttributeError ('no
    # attribute _stats' / '_pipeline_config') until the first configure.
    assert _state(node) == 'unconfigured'
    assert node.stats() == dict.fromkeys(COUNTERS, 0)
    _assert_not_configured(node, 'unconfigured')
    assert issubclass(NotConfiguredError, CVAError)
    assert 'configure, then activate' in node.diagnostics().message

    assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
    assert node.pipeline_config.matcher == 'census_bm'
    assert node.node_config.queue_size >= 1
    assert node.diagnostics().level == DiagnosticStatus.OK
    assert node.trigger_activate() == TransitionCallbackReturn.SUCCESS
    assert node.pipeline_config.max_disparity == 16

    # Cleaned up, the configurations of the released pipeline are no longer answered (they
    # were, stale, and diagnostics() said 'processing at 0.0 Hz', OK).
    assert node.trigger_deactivate() == TransitionCallbackReturn.SUCCESS
    assert node.trigger_cleanup() == TransitionCallbackReturn.SUCCESS
    _assert_not_configured(node, 'unconfigured')

    assert node.trigger_shutdown() == TransitionCallbackReturn.SUCCESS
    assert _state(node) == 'finalized'
    _assert_not_configured(node, 'finalized')
    assert 'destroy the node' in node.diagnostics().message


def test_the_summary_says_what_each_state_allows(node: ManagedConfidenceNode) -> None:
    # Finalized, the summary still said 'lifecycle transitions: configure, then activate'.
    computes = 'matcher=census_bm max_disparity=16 confidence_method=mlm'
    assert node.summary() == 'unconfigured; lifecycle transitions: configure, then activate'
    node.trigger_configure()
    assert node.summary().startswith(f'inactive; {computes}'), node.summary()
    node.trigger_activate()
    assert node.summary().startswith(f'active; {computes}'), node.summary()
    node.trigger_deactivate()
    node.trigger_cleanup()
    assert node.summary() == 'unconfigured; lifecycle transitions: configure, then activate'
    node.trigger_shutdown()
    assert node.summary() == (
        'finalized; shut down, no lifecycle transition left: destroy the node'
    )


def _fail_on_call(original: Callable[..., Any], count: int) -> Callable[..., Any]:
    """A stand-in for a node's create method ``original`` that raises on its ``count``-th call
    and passes the others on."""
    calls: list[tuple[Any, ...]] = []

    def create(*args: Any, **kwargs: Any) -> Any:
        calls.append(args)
        if len(calls) == count:
            raise RuntimeError('injected: cannot create')
        return original(*args, **kwargs)

    return create


@pytest.mark.parametrize(
    ('method', 'count'),
    [('create_timer', 1), ('create_lifecycle_publisher', 3)],
    ids=['timer', 'third-output-publisher'],
)
def test_a_configure_that_raises_half_way_leaves_no_publisher_or_timer_behind(
    node: ManagedConfidenceNode, monkeypatch: pytest.MonkeyPatch, method: str, count: int,
) -> None:
    # The core lists what it made (_owned) only once the timer is made: a configure that
    # raised before (create_timer failing here) left the eleven publishers (the ten outputs
    # and /diagnostics) alive, the outputs among the lifecycle node's managed entities.
    publishers, timers = list(node.publishers), list(node.timers)
    monkeypatch.setattr(node, method, _fail_on_call(getattr(node, method), count))

    assert node.trigger_configure() == TransitionCallbackReturn.ERROR
    assert _state(node) == 'unconfigured'
    assert not node.configured
    assert list(node.publishers) == publishers
    assert list(node.timers) == timers
    assert not node._managed_entities
    assert not node._owned

    # Without the fault, it configures as ever.
    monkeypatch.undo()
    assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
    assert len(list(node.publishers)) == len(publishers) + 11
    assert len(list(node.timers)) == len(timers) + 1
    node.trigger_cleanup()
    assert list(node.publishers) == publishers
    assert list(node.timers) == timers


def test_an_inactive_node_says_so_in_its_diagnostics(node: ManagedConfidenceNode) -> None:
    # Configured but not subscribed, /diagnostics said 'processing at 0.0 Hz' (OK), which reads
    # as a camera that went quiet; the state was in no value.
    node.trigger_configure()
    status = node.diagnostics()
    values = {kv.key: kv.value for kv in status.values}
    assert status.level == DiagnosticStatus.OK
    assert status.message == (
        'inactive: configured, not subscribed to the stereo inputs (activate to process)'
    )
    assert values['lifecycle_state'] == 'inactive'
    assert values['matcher'] == 'census_bm' and values['processing_rate_hz'] == '0.000'
    node.trigger_activate()
    status = node.diagnostics()
    assert status.message.startswith('processing at ')
    assert {kv.key: kv.value for kv in status.values}['lifecycle_state'] == 'active'
    node.trigger_deactivate()
    assert node.diagnostics().message.startswith('inactive: configured')

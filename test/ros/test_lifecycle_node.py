"""The managed (lifecycle) node: driven through the standard lifecycle services over real DDS,
in this process and as the installed ``cva-lifecycle-node``."""

from __future__ import annotations

from collections.abc import Iterator
import gc
import os
from pathlib import Path
import signal
import subprocess
import sys
import time
from typing import Any

from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
from node_test_utils import (
    NodeProcess,
    Spinner,
    StereoClient,
    first_stamp,
    held_pipeline,
    image_msg,
    info_msgs,
    localhost_context,
    spare_domain_id,
    textured_pair,
)
import numpy as np
import pytest
from rcl_interfaces.msg import Log
from rclpy.context import Context
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile

from cva_confidence_ros.node import ManagedConfidenceNode
from cva_confidence_ros.ros.convert import disparity_from_message, float_image_to_array

pytestmark = pytest.mark.timeout(240)

MAX_DISPARITY = 16
# CVA-Net-Fast has no shipped weights for D = 16: a configuration the node must refuse.
REFUSED = [
    Parameter('matcher', value='census_bm'),
    Parameter('max_disparity', value=MAX_DISPARITY),
    Parameter('confidence_method', value='cva_net_fast'),
]
SERVICE_TIMEOUT_S = 60.0


class _Managed:
    """A managed node and a client node in one localhost context, spun in the background."""

    def __init__(self, context: Context, overrides: list[Parameter]) -> None:
        self.node = ManagedConfidenceNode(context=context, parameter_overrides=overrides)
        self.client = StereoClient(context)
        self.client.subscribe('/rosout', Log, QoSProfile(depth=200))
        self.spinner = Spinner(context, self.node, self.client.node)
        self.stamp = first_stamp()

    def next_stamp(self) -> int:
        self.stamp += 10_000_000_000
        return self.stamp

    def call(self, srv_type: Any, name: str, request: Any) -> Any:
        """Call one of the node's services over DDS, as ``ros2 lifecycle`` / ``ros2 param`` do."""
        client = self.client.node.create_client(srv_type, name)
        try:
            assert client.wait_for_service(timeout_sec=20.0), f'no service {name}'
            future = client.call_async(request)
            deadline = time.monotonic() + SERVICE_TIMEOUT_S
            while not future.done() and time.monotonic() < deadline:
                time.sleep(0.02)
            assert future.done(), f'no answer from {name}'
            return future.result()
        finally:
            self.client.node.destroy_client(client)

    def transition(self, label: str) -> bool:
        request = ChangeState.Request(transition=Transition(label=label))
        return bool(self.call(ChangeState, '/cva_confidence/change_state', request).success)

    def state(self) -> str:
        return str(self.call(GetState, '/cva_confidence/get_state', GetState.Request())
                   .current_state.label)

    def inputs_subscribed(self) -> int:
        """How many of the four input topics the node subscribes to (seen from the client)."""
        return sum(pub.get_subscription_count() > 0 for pub in self.client.pubs.values())

    def wait_inputs(self, count: int, timeout: float = 20.0) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.inputs_subscribed() == count:
                return True
            time.sleep(0.05)
        return False

    def logged(self, text: str, level: int) -> list[str]:
        return [
            msg.msg
            for msg in list(self.client.received['/rosout'])
            if msg.name == 'cva_confidence' and msg.level == level and text in msg.msg
        ]

    def close(self) -> None:
        self.spinner.stop()
        self.node.destroy_node()
        self.client.node.destroy_node()


@pytest.fixture
def managed() -> Iterator[_Managed]:
    with localhost_context(spare_domain_id()) as context:
        state = _Managed(context, list(REFUSED))
        try:
            yield state
        finally:
            state.close()


def _answers(managed: _Managed) -> dict[str, Any]:
    left, right = textured_pair(seed=3)
    return managed.client.send_until_output(
        left, right, managed.next_stamp(), topics=('disparity', 'confidence'), timeout=40
    )


def test_a_refused_configure_leaves_it_unconfigured_until_the_parameters_are_fixed(
    managed: _Managed,
) -> None:
    assert managed.state() == 'unconfigured'
    assert not managed.node.configured
    time.sleep(1.0)  # discovery: an unconfigured node subscribes to nothing
    assert managed.inputs_subscribed() == 0

    assert managed.transition('configure') is False
    assert managed.state() == 'unconfigured'
    assert managed.client.wait_for(
        lambda: bool(managed.logged('configure failed', Log.ERROR)), timeout=10
    )
    (line,) = managed.logged('configure failed', Log.ERROR)
    assert 'cvanet_fast' in line and 'D = 16' in line, line

    # Unconfigured, parameters are checked as a configuration, not built.
    refused = managed.node.set_parameters([Parameter('matcher', value='no_such_matcher')])
    assert not refused[0].successful
    assert 'no_such_matcher' in refused[0].reason
    accepted = managed.node.set_parameters([Parameter('confidence_method', value='mlm')])
    assert accepted[0].successful, accepted[0].reason

    assert managed.transition('configure') is True
    assert managed.state() == 'inactive'
    assert managed.node.configured
    assert managed.node.pipeline_config.confidence_method == 'mlm'


def test_only_an_active_node_subscribes_and_publishes(managed: _Managed) -> None:
    managed.node.set_parameters([Parameter('confidence_method', value='mlm')])
    assert managed.transition('configure') is True
    time.sleep(1.0)
    assert managed.inputs_subscribed() == 0, 'inactive, the node must not subscribe'

    assert managed.transition('activate') is True
    assert managed.state() == 'active'
    assert managed.wait_inputs(4)
    out = _answers(managed)
    disparity = disparity_from_message(out['disparity'])
    assert disparity.shape == (64, 96)
    assert np.mean(np.abs(disparity[4:-4, MAX_DISPARITY + 4:-4] - 5.0) < 0.5) > 0.95
    confidence = float_image_to_array(out['confidence'])
    assert np.all((confidence >= 0) & (confidence <= 1))

    assert managed.transition('deactivate') is True
    assert managed.state() == 'inactive'
    assert managed.wait_inputs(0)
    # (the counter moves just after the outputs are published)
    assert managed.client.wait_for(lambda: managed.node.stats()['frames_processed'] >= 1)
    processed = managed.node.stats()['frames_processed']
    stamp = managed.next_stamp()
    left, right = textured_pair(seed=4)
    managed.client.publish_frame(left, right, stamp)
    time.sleep(1.5)
    assert managed.client.by_stamp('disparity', stamp) is None
    assert managed.node.stats()['frames_processed'] == processed

    # Active again: pairing starts afresh and frames are answered.
    assert managed.transition('activate') is True
    assert managed.wait_inputs(4)
    _answers(managed)
    assert managed.client.wait_for(
        lambda: managed.node.stats()['frames_processed'] > processed, timeout=10
    )


def test_cleanup_releases_the_pipeline_and_configure_builds_it_again(managed: _Managed) -> None:
    managed.node.set_parameters([Parameter('confidence_method', value='mlm')])
    assert managed.transition('configure') is True
    assert managed.transition('activate') is True
    assert managed.wait_inputs(4)
    _answers(managed)
    worker = managed.node._worker
    assert worker is not None and worker.is_alive()

    # cleanup is refused from active (the standard state machine), allowed from inactive
    assert managed.transition('cleanup') is False
    assert managed.state() == 'active'
    assert managed.transition('deactivate') is True
    assert managed.transition('cleanup') is True
    assert managed.state() == 'unconfigured'
    assert not managed.node.configured
    worker.join(5.0)
    assert not worker.is_alive()
    assert managed.wait_inputs(0)

    # Another configuration this time: census_sgm.
    managed.node.set_parameters([Parameter('matcher', value='census_sgm')])
    assert managed.transition('configure') is True
    assert managed.transition('activate') is True
    assert managed.node.pipeline_config.matcher == 'census_sgm'
    assert managed.wait_inputs(4)
    _answers(managed)
    assert managed.transition('shutdown') is True
    assert managed.state() == 'finalized'
    assert not managed.node.configured


CVA_LIFECYCLE_NODE = Path(sys.executable).parent / 'cva-lifecycle-node'
PROCESS_NAMESPACE = '/lifecycle_process'


def test_installed_lifecycle_node_autostarts_serves_and_stops_on_sigint() -> None:
    if not CVA_LIFECYCLE_NODE.exists():
        pytest.skip(f'{CVA_LIFECYCLE_NODE.name} is not installed next to the interpreter')
    domain = spare_domain_id()
    # In a namespace of its own: the other tests talk to /cva_confidence in this domain.
    process = NodeProcess(
        CVA_LIFECYCLE_NODE, domain, '-r', f'__ns:={PROCESS_NAMESPACE}',
        '-p', 'autostart:=true', '-p', 'confidence_method:=mlm',
        '-p', f'max_disparity:={MAX_DISPARITY}',
    )  # fmt: skip
    try:
        with localhost_context(domain) as context:
            client = StereoClient(context, namespace=PROCESS_NAMESPACE)
            spinner = Spinner(context, client.node)
            try:
                left, right = textured_pair(seed=5)
                out = client.send_until_output(
                    left, right, first_stamp(), topics=('disparity', 'confidence'), timeout=90
                )
            finally:
                spinner.stop()
                client.node.destroy_node()
    finally:
        code = process.stop(signal.SIGINT)
    assert code == 0, process.output
    assert disparity_from_message(out['disparity']).shape == (64, 96)
    assert 'ready: active; matcher=census_bm' in process.output, process.output
    assert 'configured: matcher=census_bm' in process.output, process.output


CVA_LIFECYCLE = Path(sys.executable).parent / 'cva-lifecycle'


def _cli(domain: int, *args: str) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    return subprocess.run(
        [str(CVA_LIFECYCLE), '--timeout', '20', *args],
        capture_output=True, text=True, timeout=90, env=env,
    )  # fmt: skip


def test_cva_lifecycle_drives_the_node_as_ros2_lifecycle_would() -> None:
    if not CVA_LIFECYCLE.exists():
        pytest.skip(f'{CVA_LIFECYCLE.name} is not installed next to the interpreter')
    domain = spare_domain_id()
    with localhost_context(domain) as context:
        managed = _Managed(context, list(REFUSED))
        try:
            got = _cli(domain, 'get', '/cva_confidence')
            assert (got.returncode, got.stdout.strip()) == (0, 'unconfigured [1]'), got
            refused = _cli(domain, 'set', 'cva_confidence', 'configure')
            assert refused.returncode == 1, refused
            assert "refused 'configure' (its state allows it, so the transition itself " \
                'failed: see its log)' in refused.stderr, refused
            managed.node.set_parameters([Parameter('confidence_method', value='mlm')])
            for transition in ('configure', 'activate'):
                done = _cli(domain, 'set', '/cva_confidence', transition)
                assert (done.returncode, done.stdout.strip()) == (0, 'Transitioning successful')
            assert managed.state() == 'active'
            listed = _cli(domain, 'list', '/cva_confidence')
            assert listed.returncode == 0, listed
            labels = {line[2:].split(' [')[0] for line in listed.stdout.splitlines()
                      if line.startswith('- ')}
            assert {'deactivate', 'shutdown'} <= labels and 'configure' not in labels, labels
            wrong = _cli(domain, 'set', '/cva_confidence', 'configure')  # not from active
            assert wrong.returncode == 1 and managed.state() == 'active'
            assert "refused 'configure' (its state allows: deactivate, shutdown)" \
                in wrong.stderr, wrong
            bogus = _cli(domain, 'set', '/cva_confidence', 'bogus')
            assert bogus.returncode == 1 and managed.state() == 'active'
            assert "refused 'bogus' (its state allows: deactivate, shutdown)" in bogus.stderr
        finally:
            managed.close()
        missing = _cli(domain, '--timeout', '1', 'get', '/no_such_node')
        assert missing.returncode == 2
        assert '/no_such_node/get_state' in missing.stderr


def test_cva_lifecycle_sends_a_slow_transition_once() -> None:
    # It sent the request again every ATTEMPT_S (3 s): a configure that took longer (one that
    # loads a network) was answered, and each copy refused with an rcl_lifecycle warning in
    # the node's log ("No transition matching configure found for current state inactive").
    from cva_confidence_ros.ros.lifecycle_cli import ATTEMPT_S

    if not CVA_LIFECYCLE.exists():
        pytest.skip(f'{CVA_LIFECYCLE.name} is not installed next to the interpreter')
    domain = spare_domain_id()
    with localhost_context(domain) as context:
        overrides = [Parameter('confidence_method', value='mlm'),
                     Parameter('max_disparity', value=MAX_DISPARITY)]
        managed = _Managed(context, overrides)
        try:
            (service,) = [srv for srv in managed.node.services
                          if srv.srv_name.endswith('/change_state')]
            labels: list[str] = []
            answer = service.callback

            def slow(request: Any, response: Any) -> Any:
                labels.append(request.transition.label)
                if len(labels) == 1:
                    time.sleep(ATTEMPT_S + 1.5)
                return answer(request, response)

            service.callback = slow
            done = _cli(domain, 'set', '/cva_confidence', 'configure')
            assert (done.returncode, done.stdout.strip()) == (0, 'Transitioning successful'), done
            assert labels == ['configure']
            assert managed.state() == 'inactive'
        finally:
            managed.close()


def test_a_destroyed_managed_node_leaves_rosout_to_the_next_node_of_its_name() -> None:
    # rclpy's LifecycleNode.destroy_node leaves the state machine holding the node, which then
    # ends only when collected; ending there unregistered the /rosout publisher of its name, by
    # then a later node's, whose log lines were lost (the in-process node tests failed so).
    nodes = []
    for _ in range(2):
        with localhost_context(spare_domain_id()) as context:
            nodes.append(ManagedConfidenceNode(context=context, parameter_overrides=list(REFUSED)))
            nodes[-1].destroy_node()
    with localhost_context(spare_domain_id()) as context:
        managed = _Managed(context, list(REFUSED))
        try:
            nodes.clear()
            gc.collect()

            def marked() -> bool:
                managed.node.get_logger().warning('rosout marker')
                return bool(managed.logged('rosout marker', Log.WARN))

            assert managed.client.wait_for(marked, timeout=15, poll=0.2)
        finally:
            managed.close()


def test_a_frame_that_outlasts_the_cleanup_is_not_published_after_a_new_configure(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # The old configuration's worker, left running with a long frame (CVA-Net on a CPU) when
    # cleanup's wait ran out, drops its result: nothing on the new configuration's publishers
    # (old parameters, old stamp), nothing in its statistics.
    from cva_confidence_ros.ros import confidence_node

    monkeypatch.setattr(confidence_node.ConfidenceCore.stop, '__defaults__', (0.3,))
    overrides = [
        Parameter('matcher', value='census_bm'),
        Parameter('max_disparity', value=MAX_DISPARITY),
        Parameter('confidence_method', value='mlm'),
        Parameter('autostart', value=True),
    ]
    with localhost_context(spare_domain_id()) as context:
        node = ManagedConfidenceNode(context=context, parameter_overrides=overrides)
        started, release = held_pipeline(node)
        try:
            published: list[Any] = []
            monkeypatch.setattr(node, '_publish', lambda *args: published.append(args))
            left, right = textured_pair()
            stamp = first_stamp()
            left_info, right_info = info_msgs(stamp)
            for key, msg in (('left_info', left_info), ('right_info', right_info),
                             ('left', image_msg(left, stamp)), ('right', image_msg(right, stamp))):
                node._on_message(key, msg)
            assert started.wait(10.0), 'the frame did not start'
            old_worker = node._worker
            node.trigger_deactivate()
            node.trigger_cleanup()
            assert old_worker is not None and old_worker.is_alive()
            node.set_parameters([Parameter('downsample', value=2)])
            node.trigger_configure()
            node.trigger_activate()
            release.set()
            old_worker.join(20.0)
            assert not old_worker.is_alive()
            assert published == []
            assert node.stats()['frames_processed'] == 0
        finally:
            release.set()
            node.destroy_node()


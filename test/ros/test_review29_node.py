"""Review 29 of the confidence node: a frame of an old configuration counted in the new one's
statistics, a parameter change whose pipeline raised something unforeseen ending the executor's
spin, and a window's status naming a bad frame's reason as its failure (each a regression test
of a fault found in the review)."""

from __future__ import annotations

import os
import threading
from typing import Any

from diagnostic_msgs.msg import DiagnosticStatus
from node_test_utils import (
    SMALL_MLM,
    Spinner,
    StereoClient,
    feed_frame,
    first_stamp,
    localhost_context,
    spare_domain_id,
    textured_pair,
    wait_until,
)
import numpy as np
import pytest
from rcl_interfaces.srv import SetParameters
from rclpy.parameter import Parameter

from cva_confidence_ros.errors import InputError
from cva_confidence_ros.node import ConfidenceNode, ManagedConfidenceNode
from cva_confidence_ros.ros import confidence_node

pytestmark = pytest.mark.timeout(180)

NAMESPACE = f'review29_{os.getpid()}'
OVERRIDES = [
    *SMALL_MLM,
]


@pytest.mark.parametrize('where', ['process', 'publish'])
def test_a_frame_of_the_old_configuration_is_not_counted_in_the_new_one(
    monkeypatch: pytest.MonkeyPatch, where: str
) -> None:
    # A frame left running when cleanup's wait ran out ends after a new configure: found
    # invalid (its images did not fit the old parameters), or done publishing. It counted as
    # the new configuration's invalid or processed frame (frames_invalid 1 of 0 received, and
    # a '1 bad frame(s) dropped' warning in its first /diagnostics).
    monkeypatch.setattr(confidence_node.ConfidenceCore.stop, '__defaults__', (0.3,))
    with localhost_context(spare_domain_id()) as context:
        node = ManagedConfidenceNode(
            context=context,
            namespace=NAMESPACE,
            parameter_overrides=[*OVERRIDES, Parameter('autostart', value=True)],
        )
        started, release = threading.Event(), threading.Event()
        try:
            if where == 'process':

                def slow_invalid(left: np.ndarray, right: np.ndarray) -> Any:
                    started.set()
                    release.wait(30.0)
                    raise InputError('a frame the old configuration cannot take')

                node._pipeline.process = slow_invalid
            else:

                def slow_publish(*args: Any) -> None:
                    started.set()
                    release.wait(30.0)

                monkeypatch.setattr(node, '_publish', slow_publish)
            left, right = textured_pair()
            feed_frame(node, left, right, first_stamp())
            assert started.wait(30.0), 'the frame did not start'
            old_worker = node._worker
            node.trigger_deactivate()
            node.trigger_cleanup()
            assert old_worker is not None and old_worker.is_alive()
            node.trigger_configure()
            node.trigger_activate()
            release.set()
            old_worker.join(30.0)
            assert not old_worker.is_alive()
            stats = node.stats()
            assert stats['frames_received'] == 0
            assert stats['frames_invalid'] == 0, stats
            assert stats['frames_processed'] == 0, stats
            status = node.diagnostics()
            assert 'bad frame' not in status.message, status.message
        finally:
            release.set()
            node.destroy_node()


def test_a_pipeline_that_raises_unforeseen_refuses_the_change_and_the_node_spins_on(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # Building the new pipeline can raise other than a CVAError (CUDA out of memory loading
    # the weights, a fault in a library): it left the parameter callback, ended the executor's
    # spin (the node dead, the parameter service never answering).
    with localhost_context(spare_domain_id()) as context:
        node = ConfidenceNode(context=context, namespace=NAMESPACE, parameter_overrides=OVERRIDES)
        client = StereoClient(context, namespace=NAMESPACE)
        spinner = Spinner(context, node, client.node)
        try:

            def unforeseen(config: Any) -> Any:
                raise RuntimeError('CUDA out of memory (simulated)')

            monkeypatch.setattr(confidence_node, 'StereoPipeline', unforeseen)
            service = client.node.create_client(
                SetParameters, f'/{NAMESPACE}/cva_confidence/set_parameters'
            )
            assert service.wait_for_service(timeout_sec=30.0), 'no parameter service'
            future = service.call_async(SetParameters.Request(
                parameters=[Parameter('max_disparity', value=24).to_parameter_msg()]
            ))
            assert wait_until(future.done, 60.0), 'the parameter service did not answer'
            (result,) = future.result().results
            assert not result.successful
            assert 'CUDA out of memory (simulated)' in result.reason
            assert node.get_parameter('max_disparity').value == 16
            assert node.pipeline_config.max_disparity == 16
            monkeypatch.undo()
            # The executor still spins: the next change is answered, and taken.
            future = service.call_async(SetParameters.Request(
                parameters=[Parameter('max_rate_hz', value=5.0).to_parameter_msg()]
            ))
            answered = wait_until(future.done, 60.0)
            assert answered, 'the node stopped answering after the refusal'
            assert future.result().results[0].successful
            assert node.node_config.max_rate_hz == 5.0
        finally:
            spinner.stop()
            node.destroy_node()
            client.node.destroy_node()


def test_a_windows_status_names_the_failure_and_the_bad_frame_each_by_its_own() -> None:
    # One last_error for both: a bad frame after a failure made the ERROR read 'processing
    # fails: left and right images must have the same size …', and a failure after a bad
    # frame made the WARN read 'bad frame(s) dropped: RuntimeError …'.
    with localhost_context(spare_domain_id()) as context:
        node = ConfidenceNode(context=context, namespace=NAMESPACE, parameter_overrides=OVERRIDES)
        try:
            pipeline = node._pipeline
            process = pipeline.process
            fail = [True]

            def failing(left: np.ndarray, right: np.ndarray) -> Any:
                if fail[0]:
                    raise RuntimeError('simulated failure inside the pipeline')
                return process(left, right)

            pipeline.process = failing
            left, right = textured_pair()
            narrow = np.ascontiguousarray(right[:, :50])
            stamp = first_stamp()

            def counted(name: str, value: int) -> bool:
                return node.stats()[name] == value

            node.diagnostics()  # a fresh window
            feed_frame(node, left, right, stamp)
            assert wait_until(lambda: counted('frames_failed', 1), 60.0)
            feed_frame(node, left, narrow, stamp + 10**9)
            assert wait_until(lambda: counted('frames_invalid', 1), 60.0)
            status = node.diagnostics()
            assert status.level == DiagnosticStatus.ERROR
            assert 'simulated failure inside the pipeline' in status.message, status.message

            feed_frame(node, left, narrow, stamp + 2 * 10**9)
            assert wait_until(lambda: counted('frames_invalid', 2), 60.0)
            feed_frame(node, left, right, stamp + 3 * 10**9)
            assert wait_until(lambda: counted('frames_failed', 2), 60.0)
            fail[0] = False
            feed_frame(node, left, right, stamp + 4 * 10**9)
            assert wait_until(lambda: counted('frames_processed', 1), 60.0)
            status = node.diagnostics()
            assert status.level == DiagnosticStatus.WARN
            assert 'same size' in status.message, status.message
        finally:
            node.destroy_node()

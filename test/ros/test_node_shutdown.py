"""Stopping the node while a frame is being processed: the worker ends quietly, no error logged.

Each test brings its own context up and shuts it down under the node, the way ``rclpy.shutdown``
or Ctrl-C do in ``cva-node``, while a frame large enough to take a while is in the worker.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
import subprocess
import sys

from node_test_utils import (
    Spinner,
    StereoClient,
    first_stamp,
    spare_domain_id,
    textured_pair,
    wait_until,
)
import pytest
import rclpy
from rclpy.context import Context
from rclpy.parameter import Parameter

from cva_confidence_ros.node import ConfidenceNode

pytestmark = pytest.mark.timeout(120)

# Census-SGM on a VGA pair with LRD (a second, right-reference SGM volume) takes ≈ 200 ms on a
# 2-core CPU, and numba holds the GIL for ≤ 30 ms at a time: far longer than a shutdown.
HEIGHT, WIDTH, MAX_DISPARITY = 480, 640, 128
OVERRIDES = [
    Parameter('matcher', value='census_sgm'),
    Parameter('max_disparity', value=MAX_DISPARITY),
    Parameter('confidence_method', value='lrd'),
]


def test_rclpy_shutdown_during_a_frame_stops_the_worker_quietly(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    context = Context()
    rclpy.init(context=context, domain_id=spare_domain_id())
    node = client = spinner = None
    try:
        node = ConfidenceNode(context=context, parameter_overrides=list(OVERRIDES))
        client = StereoClient(context)
        spinner = Spinner(context, node, client.node)
        assert client.wait_connected(), 'the node and the client did not discover'
        left, right = textured_pair(HEIGHT, WIDTH, disparity=9)
        client.publish_frame(left, right, first_stamp())
        received = wait_until(lambda: node.stats()['frames_received'] == 1, poll=0.002)
        assert received, 'the frame did not arrive'
        # The worker has the frame (or is about to take it) and will publish in a moment.
        context.try_shutdown()
        node._worker.join(20.0)
        assert not node._worker.is_alive(), 'the worker did not stop with the context'
        stats = node.stats()
        assert stats['frames_failed'] == 0, stats
        assert stats['frames_processed'] == 0, 'the frame finished before the shutdown: no race'
    finally:
        if spinner is not None:
            spinner.stop()
        context.try_shutdown()
        for owner in (node, client.node if client is not None else None):
            if owner is not None:
                owner.destroy_node()


# The node in a process of its own, with rclpy's signal handlers installed as in cva-node, so
# that SIGINT shuts the context down the way Ctrl-C does: in C, without Python callbacks.
_CTRL_C_SCRIPT = """
import json, os, signal, sys, time
import rclpy
from rclpy.parameter import Parameter
from node_test_utils import Spinner, StereoClient, first_stamp, textured_pair
from cva_confidence_ros.node import ConfidenceNode

rclpy.init(domain_id=int(sys.argv[1]))
context = rclpy.get_default_context()
node = ConfidenceNode(parameter_overrides=[
    Parameter('matcher', value='census_sgm'),
    Parameter('max_disparity', value=int(sys.argv[2])),
    Parameter('confidence_method', value='lrd'),
])
client = StereoClient(context)
spinner = Spinner(context, node, client.node)
assert client.wait_connected(), 'not connected'
left, right = textured_pair(int(sys.argv[3]), int(sys.argv[4]), disparity=9)
client.publish_frame(left, right, first_stamp())
deadline = time.monotonic() + 20
while node.stats()['frames_received'] == 0 and time.monotonic() < deadline:
    time.sleep(0.002)
try:
    os.kill(os.getpid(), signal.SIGINT)
    time.sleep(5)
except KeyboardInterrupt:
    pass
node._worker.join(20)
print('RESULT', json.dumps(dict(node.stats(), worker_alive=node._worker.is_alive(),
                                context_ok=context.ok())), flush=True)
# Tear down as cva-node does: a spin thread or a DDS participant left to the interpreter's exit
# can abort it in C++ (terminate called without an active exception).
spinner.stop()
client.node.destroy_node()
node.destroy_node()
"""


def test_ctrl_c_during_a_frame_stops_the_worker_quietly() -> None:
    env = dict(
        os.environ,
        ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
        PYTHONPATH=os.pathsep.join(
            p for p in (str(Path(__file__).parent), os.environ.get('PYTHONPATH', '')) if p
        ),
        OMP_NUM_THREADS='1',
    )
    args = [str(spare_domain_id()), str(MAX_DISPARITY), str(HEIGHT), str(WIDTH)]
    done = subprocess.run(
        [sys.executable, '-c', _CTRL_C_SCRIPT, *args],
        env=env,
        capture_output=True,
        text=True,
        timeout=90,
    )
    output = done.stdout + done.stderr
    assert done.returncode == 0, output
    (line,) = [line for line in done.stdout.splitlines() if line.startswith('RESULT ')]
    result = json.loads(line.removeprefix('RESULT '))
    assert not result['context_ok'], 'SIGINT did not shut the context down'
    assert not result['worker_alive'], output
    assert result['frames_failed'] == 0, output
    assert result['frames_processed'] == 0, 'the frame finished before Ctrl-C: no race'
    assert 'processing failed' not in output, output
    assert 'Traceback' not in output, output

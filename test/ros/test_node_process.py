"""The installed ``cva-node`` as a separate process, talked to over DDS, stopped by signals."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
import signal
import sys
import time

from diagnostic_msgs.msg import DiagnosticArray
from node_test_utils import NodeProcess as SharedNodeProcess
from node_test_utils import (
    Spinner,
    StereoClient,
    domain_id,
    first_stamp,
    localhost_context,
    textured_pair,
)
import numpy as np
import pytest

from cva_confidence_ros.ros.convert import disparity_from_message, float_image_to_array

pytestmark = pytest.mark.timeout(180)

CVA_NODE = Path(sys.executable).parent / 'cva-node'
CONFIG = Path(__file__).resolve().parents[2] / 'config' / 'cva_confidence.yaml'
DOMAIN = domain_id(2)
NAMESPACE = '/stereo'


class NodeProcess(SharedNodeProcess):
    """``cva-node`` in a subprocess in this module's domain and namespace."""

    def __init__(self, *ros_args: str) -> None:
        super().__init__(CVA_NODE, DOMAIN, '-r', f'__ns:={NAMESPACE}', *ros_args)


@pytest.fixture(scope='module')
def client() -> Iterator[StereoClient]:
    if not CVA_NODE.exists():
        pytest.skip(f'{CVA_NODE.name} is not installed next to the interpreter (make setup)')
    with localhost_context(DOMAIN) as context:
        stereo = StereoClient(context, namespace=NAMESPACE)
        spinner = Spinner(context, stereo.node)
        try:
            yield stereo
        finally:
            spinner.stop()
            stereo.node.destroy_node()


def _started(node: NodeProcess, timeout: float = 90.0) -> None:
    deadline = time.monotonic() + timeout
    while not node.ready.wait(0.2):
        if node.process.poll() is not None or time.monotonic() > deadline:
            node.stop(signal.SIGKILL)
            pytest.fail('cva-node printed no ready line; output:\n' + node.output)


def test_cva_node_serves_over_dds_and_stops_on_sigint(client: StereoClient) -> None:
    node = NodeProcess(
        '--params-file', str(CONFIG),
        '-p', 'confidence_method:=mlm',
        '-p', 'max_disparity:=16',
    )  # fmt: skip
    try:
        _started(node)
        assert client.wait_connected(30), node.output
        left, right = textured_pair(seed=11)
        out = client.send_until_output(left, right, first_stamp(), timeout=40)
    finally:
        code = node.stop(signal.SIGINT)
    disparity = disparity_from_message(out['disparity'])
    assert disparity.shape == (64, 96)
    assert np.mean(np.abs(disparity[4:-4, 20:-4] - 5.0) < 0.5) > 0.95
    confidence = float_image_to_array(out['confidence'])
    assert np.all((confidence >= 0) & (confidence <= 1))
    assert out['points2'].header.frame_id == 'left_optical'
    assert code == 0, node.output
    assert 'Traceback' not in node.output, node.output


def test_cva_net_with_given_weights_and_sigterm(client: StereoClient, tmp_path: Path) -> None:
    torch = pytest.importorskip('torch')
    from cva_confidence_ros.model import CVANet, save_weights

    torch.manual_seed(0)
    weights = tmp_path / 'random_cvanet_d16.pt'
    meta = {'matcher': 'census_bm', 'max_disparity': 16, 'arch': 'cvanet'}
    save_weights(CVANet(16), weights, meta=meta)
    node = NodeProcess(
        '-p', 'confidence_method:=cva_net',
        '-p', f'model_path:={weights}',
        '-p', 'max_disparity:=16',
        '-p', 'confidence_threshold:=0.0',
    )  # fmt: skip
    try:
        _started(node)
        assert client.wait_connected(30), node.output
        left, right = textured_pair(seed=12)
        out = client.send_until_output(left, right, first_stamp() + 10**12, timeout=60)
    finally:
        code = node.stop(signal.SIGTERM)
    confidence = float_image_to_array(out['confidence'])
    assert confidence.shape == (64, 96)
    # A sigmoid output: strictly inside (0, 1), and not constant over a textured image.
    assert np.all((confidence > 0) & (confidence < 1))
    assert confidence.std() > 0
    assert code == 0, node.output
    assert 'Traceback' not in node.output, node.output


def _frames_received(client: StereoClient) -> int:
    """The node's ``frames_received`` in the newest diagnostics that carry it, else 0."""
    for array in reversed(client.received['/diagnostics']):
        for entry in array.status:
            for value in entry.values:
                if value.key == 'frames_received':
                    return int(value.value)
    return 0


def test_stop_during_a_long_frame_ends_the_process_cleanly(
    client: StereoClient, tmp_path: Path
) -> None:
    # The paper network on a CPU takes longer a frame than the stop waits: the process must
    # still end with 0 and a warning, not abort (SIGABRT) while finalising under torch.
    torch = pytest.importorskip('torch')
    from cva_confidence_ros.model import CVANet, save_weights
    from cva_confidence_ros.ros.confidence_node import STOP_TIMEOUT_S

    torch.manual_seed(0)
    weights = tmp_path / 'random_cvanet_d64.pt'
    save_weights(CVANet(64), weights, meta={'matcher': 'census_bm', 'max_disparity': 64})
    node = NodeProcess(
        '-p', 'confidence_method:=cva_net',
        '-p', f'model_path:={weights}',
        '-p', 'max_disparity:=64',
    )  # fmt: skip
    try:
        _started(node)
        assert client.wait_connected(30), node.output
        # 240×320 at D = 64: ≈ 2.7 T multiply-adds, tens of seconds on one thread. Sent again
        # (a new stamp) until the node's diagnostics count it: a first publish can be lost.
        client.subscribe('/diagnostics', DiagnosticArray)
        left, right = textured_pair(height=240, width=320, seed=14)
        deadline = time.monotonic() + 30.0
        sent = []
        for stamp in range(first_stamp() + 2 * 10**12, first_stamp() + 3 * 10**12, 10**9):
            client.publish_frame(left, right, stamp)
            sent.append(stamp)
            if client.wait_for(lambda: _frames_received(client) > 0, timeout=1.5):
                break
            assert time.monotonic() < deadline, f'the node counted no frame:\n{node.output}'
        time.sleep(2.0)  # past matching: the network is running
        done = [stamp for stamp in sent if client.by_stamp('confidence', stamp) is not None]
        assert not done, 'the frame ended before the stop'
        start = time.monotonic()
    finally:
        code = node.stop(signal.SIGINT, timeout=STOP_TIMEOUT_S + 50)
    assert time.monotonic() - start < STOP_TIMEOUT_S + 20
    assert code == 0, node.output
    assert 'still being processed' in node.output, node.output
    assert 'terminate called' not in node.output and 'Traceback' not in node.output


@pytest.mark.parametrize(
    ('args', 'message'),
    [
        (('-p', 'matcher:=no_such_matcher'), 'no_such_matcher'),
        (('-p', 'max_disparity:=5000'), 'max_disparity'),
        (('-p', 'confidence_method:=cva_net', '-p', 'model_path:=/nonexistent.pt'), 'cannot'),
        # rcl would only say it "couldn't parse" it.
        pytest.param(
            ('--params-file', '/nonexistent.yaml'),
            '--params-file /nonexistent.yaml: no such file',
            id='missing-params-file',
        ),
        # Refused by rcl itself, in rclpy.init.
        pytest.param(('--no-such-ros-flag',), '--no-such-ros-flag', id='unknown-ros-flag'),
        pytest.param(('-p',), 'trailing -p', id='trailing-p'),
    ],
)
def test_invalid_start_configuration_exits_cleanly(args: tuple[str, ...], message: str) -> None:
    if not CVA_NODE.exists():
        pytest.skip('cva-node is not installed')
    node = NodeProcess(*args)
    code = node.process.wait(90)
    node._reader.join(10)
    assert code == 2, node.output
    assert message in node.output
    assert 'Traceback' not in node.output, node.output
    (line,) = [line for line in node.lines if 'cannot start' in line]
    assert message in line and '[FATAL]' in line


def test_params_file_that_is_not_yaml_is_refused_by_rcl(tmp_path: Path) -> None:
    if not CVA_NODE.exists():
        pytest.skip('cva-node is not installed')
    params = tmp_path / 'params.yaml'
    params.write_text('cva_confidence:\n  ros__parameters: [\n')
    node = NodeProcess('--params-file', str(params))
    code = node.process.wait(90)
    node._reader.join(10)
    assert code == 2, node.output
    (line,) = [line for line in node.lines if 'cannot start' in line]
    assert f"parse params file: '--params-file {params}'" in line, node.output
    assert 'Traceback' not in node.output, node.output


def _loaded(pid: int, library: str, timeout: float = 30.0) -> bool:
    """Wait until the process ``pid`` has mapped a shared library whose path holds ``library``."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            if library in Path(f'/proc/{pid}/maps').read_text():
                return True
        except OSError:
            return False
        time.sleep(0.005)
    return False


@pytest.mark.parametrize('delay', [0.0, 0.35, 1.0])
def test_early_ctrl_c_exits_quietly(delay: float) -> None:
    # Counted from rclpy's extension being loaded (the node's imports, after its entry point
    # took SIGINT over; before that, Python's own start-up has it): within the imports of
    # rclpy, torch and the pipeline (0, 0.35 s), or while the node is built and warmed up
    # (about 1 s later here: numba compiles then).
    if not CVA_NODE.exists():
        pytest.skip('cva-node is not installed')
    node = NodeProcess('-p', 'max_disparity:=16', '-p', 'confidence_method:=mlm')
    assert _loaded(node.process.pid, '_rclpy_pybind11'), node.output
    time.sleep(delay)
    code = node.stop(signal.SIGINT)
    assert 'Traceback' not in node.output, node.output
    assert 'KeyboardInterrupt' not in node.output, node.output
    if delay < 1.0:
        assert 'ready:' not in node.output, 'the node came up before the signal: nothing tested'
    # Interrupted before the node is up (130), or stopped once it is (0).
    assert code == (0 if 'ready:' in node.output else 130), node.output

"""Review 38 of the node on small computers with high-resolution cameras: frames whose matching
cannot fit the memory left, and the parameter changes that get out of it (regression tests of
the faults found). A small machine is simulated in-process: ``memory.available_memory`` gives
a few hundred kB and every need is checked, so that 160×120 px images stand in for 5 MP ones."""

from __future__ import annotations

from node_test_utils import (
    LogRecorder,
    first_stamp,
    node_and_client,
    set_parameters_by_service,
    textured_pair,
)
import pytest
from rclpy.parameter import Parameter

from cva_confidence_ros import memory
from cva_confidence_ros.node import ConfidenceNode

pytestmark = pytest.mark.timeout(120)

#: census_bm at 160×120 px needs 4 bytes a pixel and disparity: 2.46 MB at D = 32, 154 kB at
#: downsample 4, 77 kB at downsample 4 and D = 16; 100 kB are left.
_LEFT = 100_000
_PARAMS = [
    Parameter('matcher', value='census_bm'),
    Parameter('max_disparity', value=32),
    Parameter('confidence_method', value='mlm'),
    Parameter('diagnostics_period_seconds', value=600.0),
]


@pytest.fixture
def small_machine(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(memory, '_CHECKED_FROM', 0)
    monkeypatch.setattr(memory, 'available_memory', lambda: _LEFT)


@pytest.mark.usefixtures('small_machine')
def test_frames_beyond_memory_are_left_one_param_set_at_a_time() -> None:
    # Neither downsample 4 (154 kB) nor max_disparity 16 (1.2 MB) alone fits, both do (77 kB):
    # each step was refused for memory while every frame was dropped, and only a restart got
    # out (cva-param sets one parameter at a time).
    with node_and_client(
        lambda context: ConfidenceNode(context=context, parameter_overrides=_PARAMS)
    ) as (node, client):
        log = LogRecorder()
        node.get_logger = lambda: log
        assert client.wait_connected()
        left, right = textured_pair(120, 160)
        stamp = first_stamp()
        for i in range(100):  # sent again until received (discovery may lag behind)
            client.publish_frame(left, right, stamp + i * 10**8)
            if client.wait_for(lambda: node.stats()['frames_invalid'] >= 3, timeout=0.2):
                break
        # Logged (throttled) and in /diagnostics with the need and what lowers it.
        dropped = [line for _, line in log.lines if line.startswith('dropped frame')]
        assert 1 <= len(dropped) < node.stats()['frames_invalid']
        status = node.diagnostics()
        assert 'needs at least' in status.message and 'GB of memory' in status.message
        assert 'a smaller max_disparity (now 32)' in status.message
        # A change that needs more is refused, with the memory reason.
        (more,) = set_parameters_by_service(client.node, max_disparity=36)
        assert not more.successful
        assert 'GB of memory are available' in more.reason and '160×120 px' in more.reason
        # One the images are too narrow for is refused as before, though it needs less.
        narrow = node.set_parameters_atomically(
            [Parameter('downsample', value=4), Parameter('max_disparity', value=40)]
        )
        assert not narrow.successful and 'image width 40' in narrow.reason
        # A step toward fitting is taken, and says that the images do not fit yet.
        (step,) = set_parameters_by_service(client.node, downsample=4)
        assert step.successful, step.reason
        assert any(
            line.startswith('parameters set: downsample=4; the images coming in still do not fit')
            for kind, line in log.lines if kind == 'warning'
        )
        (fits,) = set_parameters_by_service(client.node, max_disparity=16)
        assert fits.successful, fits.reason
        assert node.pipeline_config.downsample == 4
        out = client.send_until_output(left, right, stamp + 10**10, topics=('disparity',))
        assert out['disparity'].image.width == 40

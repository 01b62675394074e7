"""``cva-bag-replay --mode live``: the bag played over real DDS to a real ``cva-node`` process."""

from __future__ import annotations

import json
import os
from pathlib import Path
import signal
import subprocess
import sys
import time

from msg_test_utils import MAX_DISPARITY, dataset_bag, domain_id, read_bag
import numpy as np
import pytest

from cva_confidence_ros.ros.convert import (
    cloud_to_array,
    depth_image_to_array,
    disparity_from_message,
    float_image_to_array,
    image_to_array,
)
import msg_tools
from msg_tools.bag_replay import main
from msg_tools.convert import stamp_to_ns

ROOT = Path(msg_tools.__file__).resolve().parents[1]

METRICS = ('error_rate', 'auc', 'auc_opt', 'kept_density', 'kept_error_rate', 'n_pixels',
           'kept_fraction', 'mean_confidence', 'scan_beams', 'scan_phantom_rate', 'scan_far_rate',
           'scan_none_rate')


@pytest.fixture(autouse=True)
def _own_domain(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv('ROS_DOMAIN_ID', str(domain_id()))
    # The replay and its node talk on this host only (no cross-talk with other machines' runs).
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')


def _replay(bag: Path, tmp_path: Path, mode: str, *extra: str) -> tuple[int, dict]:
    code = main([
        str(bag), '--mode', mode, '--out', str(tmp_path / f'{mode}_bag'),
        '--report', str(tmp_path / mode), '--matcher', 'census_bm',
        '--max-disparity', str(MAX_DISPARITY), '--confidence-method', 'pkrn',
        '--downsample', '2', '--confidence-threshold', '0.3', *extra,
    ])
    report = tmp_path / mode / 'report.json'
    return code, json.loads(report.read_text()) if report.exists() else {}


def _offline_and_live(bag: Path, tmp_path: Path, *extra: str) -> tuple[dict, dict]:
    """Replay ``bag`` offline, then live to a node the replay starts; both must succeed."""
    code, offline = _replay(bag, tmp_path, 'offline', *extra)
    assert code == 0
    # --rate-scale 0.5: frames at half the bag's rate, margin for a loaded CI machine.
    code, live = _replay(
        bag, tmp_path, 'live', *extra, '--startup-timeout', '90', '--rate-scale', '0.5'
    )
    assert code == 0, (tmp_path / 'live' / 'node.log').read_text()
    return offline, live


@pytest.mark.timeout(180)
def test_live_gives_the_offline_results(tmp_path: Path) -> None:
    # Three tiny frames at 2 Hz: slow enough that the node drops nothing.
    bag = dataset_bag(tmp_path, 'mcap', 3, '--rate', '2')
    extra = ('--overlay', '--scan', '--scan-height', '-5', '5', '--scan-range', '0.05', '50',
             '--scan-frame-id', 'rig')
    offline, live = _offline_and_live(bag, tmp_path, *extra)
    assert live['summary']['dropped'] == 0 and live['summary']['processed'] == 3
    assert live['config']['mode'] == 'live'
    for a, b in zip(offline['frames'], live['frames'], strict=True):
        assert (a['frame'], a['stamp_ns']) == (b['frame'], b['stamp_ns'])
        for key in METRICS:
            assert a[key] == b[key], key
        assert b['latency_ms'] > 0
    # The node's messages are the offline ones: same stamps, arrays and clouds.
    first, second = read_bag(tmp_path / 'offline_bag'), read_bag(tmp_path / 'live_bag')
    assert first.keys() == second.keys() == {
        '/disparity', '/confidence', '/disparity_filtered', '/points2', '/depth', '/camera_info',
        '/confidence_overlay', '/scan',
    }
    for topic, read in (
        ('/disparity', disparity_from_message),
        ('/disparity_filtered', disparity_from_message),
        ('/confidence', float_image_to_array),
        ('/points2', cloud_to_array),
        ('/depth', depth_image_to_array),
        ('/confidence_overlay', image_to_array),
        ('/scan', lambda scan: np.concatenate([scan.ranges, scan.intensities])),
        ('/camera_info', lambda info: np.concatenate([info.k, info.p, [info.width, info.height]])),
    ):
        assert [t for t, _ in first[topic]] == [t for t, _ in second[topic]]
        for (_, a), (_, b) in zip(first[topic], second[topic], strict=True):
            assert stamp_to_ns(a.header.stamp) == stamp_to_ns(b.header.stamp)
            assert a.header.frame_id == b.header.frame_id
            left, right = read(a), read(b)
            if left.dtype.names:
                left = np.stack([left[n] for n in left.dtype.names])
                right = np.stack([right[n] for n in right.dtype.names])
            np.testing.assert_array_equal(left, right)
    assert {msg.header.frame_id for _, msg in second['/scan']} == {'rig'}
    assert sum(np.isfinite(msg.ranges).sum() for _, msg in second['/scan']) > 20
    # The report's overlays (of frames spread over the bag, and of the frame kept least) are
    # drawn from the images the replay published: the same pictures as offline.
    pictures = sorted(p.name for p in (tmp_path / 'live').glob('*overlay_*.png')) + sorted(
        p.name for p in (tmp_path / 'live').glob('least_kept_*.png'))
    assert pictures == sorted(p.name for p in (tmp_path / 'offline').glob('*overlay_*.png')) \
        + sorted(p.name for p in (tmp_path / 'offline').glob('least_kept_*.png'))
    assert len(pictures) == 4  # three frames, one least kept
    for name in pictures:
        live_png, offline_png = (tmp_path / mode / name for mode in ('live', 'offline'))
        assert live_png.read_bytes() == offline_png.read_bytes(), name


@pytest.mark.timeout(180)
def test_live_records_the_nodes_compressed_topics(tmp_path: Path) -> None:
    # --compressed: the replay subscribes to the node's depth/compressedDepth and
    # confidence_overlay/compressed (which it encodes only while subscribed) under the prefix,
    # not to the raw ones, and hands it the settings as parameters: the bytes of the offline
    # run, which encodes with the node's functions.
    from rosbags.rosbag2 import Reader

    prefix = '/stereo'
    bag = dataset_bag(tmp_path, 'mcap', 2, '--rate', '2', '--topic-prefix', prefix)
    extra = ('--topic-prefix', prefix, '--overlay', '--compressed', '--jpeg-quality', '70',
             '--compressed-depth-max', '3', '--compressed-depth-png-level', '6')
    _, live = _offline_and_live(bag, tmp_path, *extra)
    assert live['summary']['dropped'] == 0 and live['summary']['processed'] == 2
    with Reader(tmp_path / 'live_bag') as reader:
        types = {conn.topic: conn.msgtype for conn in reader.connections}
    packed = {f'{prefix}/depth/compressedDepth', f'{prefix}/confidence_overlay/compressed'}
    assert set(types) == packed | {
        f'{prefix}/{name}' for name in
        ('disparity', 'confidence', 'disparity_filtered', 'points2', 'camera_info')
    }
    assert {types[topic] for topic in packed} == {'sensor_msgs/msg/CompressedImage'}
    first, second = read_bag(tmp_path / 'offline_bag'), read_bag(tmp_path / 'live_bag')
    assert first.keys() == second.keys()
    for topic in packed:
        assert [(t, stamp_to_ns(m.header.stamp), m.header.frame_id, m.format, bytes(m.data))
                for t, m in first[topic]] == [
            (t, stamp_to_ns(m.header.stamp), m.header.frame_id, m.format, bytes(m.data))
            for t, m in second[topic]], topic
        assert len(second[topic]) == 2


def test_no_node_to_connect_to(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag = dataset_bag(tmp_path, 'mcap', 1)
    code, _ = _replay(bag, tmp_path, 'live', '--no-start-node', '--startup-timeout', '1')
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith('cva-bag-replay: error: no node connected to /left/image_rect')
    assert 'drop --no-start-node' in err
    assert not (tmp_path / 'live_bag').exists()


def _processes_with(argument: str) -> list[int]:
    """Pids of the running processes whose command line holds ``argument``."""
    found = []
    for entry in Path('/proc').iterdir():
        try:
            if entry.name.isdigit() and argument in entry.joinpath('cmdline').read_bytes().decode(
                errors='replace'
            ).split('\0'):
                found.append(int(entry.name))
        except OSError:
            pass  # ended meanwhile
    return found


def _restore_sigint() -> None:
    # As a terminal's foreground job has it, even when the tests run with SIGINT ignored.
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.mark.timeout(90)
def test_ctrl_c_during_start_up_reaches_the_replay_only(tmp_path: Path) -> None:
    bag = dataset_bag(tmp_path, 'mcap', 1)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        p for p in (str(ROOT), os.environ.get('PYTHONPATH', '')) if p))
    replay = subprocess.Popen(
        [sys.executable, '-m', 'msg_tools.bag_replay', str(bag), '--mode', 'live',
         '--out', str(tmp_path / 'out'), '--report', str(tmp_path / 'report'),
         '--max-disparity', str(MAX_DISPARITY), '--confidence-method', 'pkrn'],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
        start_new_session=True, preexec_fn=_restore_sigint,
    )
    assert replay.stderr is not None
    for line in replay.stderr:
        if 'started cva-node' in line:
            break
    [node] = _processes_with(f'__node:=cva_confidence_replay_{replay.pid}')
    assert os.getsid(node) != os.getsid(replay.pid)  # a session (and process group) of its own
    time.sleep(0.5)  # the node is still starting
    os.killpg(replay.pid, signal.SIGINT)  # Ctrl-C in a terminal: the foreground process group
    _, err = replay.communicate(timeout=60)
    assert replay.returncode == 130, err
    assert 'Traceback' not in err and 'cva-node exited' not in err, err
    assert err.strip().endswith('cva-bag-replay: interrupted')
    assert 'Traceback' not in (tmp_path / 'report' / 'node.log').read_text()
    assert not _processes_with(f'__node:=cva_confidence_replay_{replay.pid}')  # stopped

"""The node in this process, talked to over real DDS by a client node in the same context."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
import threading
import time

import cv2
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from node_test_utils import (
    BASELINE,
    FX,
    TRUE_DISPARITY,
    Spinner,
    StereoClient,
    domain_id,
    first_stamp,
    image_msg,
    info_msgs,
    running_nodes,
    set_parameters_by_service,
    textured_pair,
)
import numpy as np
import pytest
from rcl_interfaces.msg import Log, SetParametersResult
import rclpy
from rclpy.context import Context
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
import torch

from cva_confidence_ros.matching import remove_speckles
from cva_confidence_ros.node import ConfidenceNode
from cva_confidence_ros.pipeline import PipelineConfig, StereoPipeline
from cva_confidence_ros.ros.convert import (
    cloud_to_array,
    compressed_image_to_array,
    depth_image_to_array,
    disparity_from_message,
    float_image_to_array,
    image_to_array,
)
from cva_confidence_ros.ros.params import PARAMETERS, NodeConfig
from cva_confidence_ros.ros.transport import compressed_depth_to_array

pytestmark = pytest.mark.timeout(120)

MAX_DISPARITY = 16
THRESHOLD = 0.5
OVERRIDES = [
    Parameter('matcher', value='census_bm'),
    Parameter('max_disparity', value=MAX_DISPARITY),
    Parameter('confidence_method', value='mlm'),
    Parameter('confidence_threshold', value=THRESHOLD),
]


def _kept(disparity: np.ndarray, confidence: np.ndarray) -> np.ndarray:
    """The pixels the node keeps: finite disparity, confidence ≥ threshold, and not in a
    speckle of those (the default speckle_size and speckle_range)."""
    defaults = PipelineConfig()
    keep = np.isfinite(disparity) & (confidence >= THRESHOLD)
    return remove_speckles(disparity, keep, defaults.speckle_size, defaults.speckle_range)


class _Running:
    def __init__(self, context: Context) -> None:
        self.context = context
        self.node = ConfidenceNode(context=context, parameter_overrides=list(OVERRIDES))
        self.client = StereoClient(context)
        self.client.subscribe('/diagnostics', DiagnosticArray)
        self.client.subscribe('camera_info', CameraInfo)
        self.client.subscribe('depth', Image)
        self.client.subscribe('/rosout', Log, QoSProfile(depth=100))
        self.spinner = Spinner(context, self.node, self.client.node)
        self.stamp = first_stamp()
        assert self.client.wait_connected(), 'the node and the client did not discover'

    def next_stamp(self) -> int:
        # Far apart, so the retries of send_until_output never reach the next test's stamps.
        self.stamp += 10_000_000_000
        return self.stamp

    def set(self, **values: object) -> SetParametersResult:
        """Set parameters all at once (the callback the parameter service runs)."""
        return self.node.set_parameters_atomically(
            [Parameter(k, value=v) for k, v in values.items()]
        )

    def set_by_service(self, **values: object) -> list[SetParametersResult]:
        """Set parameters over the node's ``set_parameters`` service (``ros2 param set``)."""
        return set_parameters_by_service(self.client.node, **values)

    def logged(self, text: str, level: int = Log.WARN) -> list[str]:
        """The node's ``/rosout`` messages of ``level`` that contain ``text``."""
        return [
            msg.msg
            for msg in list(self.client.received['/rosout'])
            if msg.name == 'cva_confidence' and msg.level == level and text in msg.msg
        ]


@pytest.fixture(scope='module')
def running() -> Iterator[_Running]:
    with running_nodes(domain_id(0), _Running) as state:
        yield state


def _interior(array: np.ndarray, border: int) -> np.ndarray:
    return array[border:-border, MAX_DISPARITY + border : -border]


def test_outputs_for_a_known_disparity(running: _Running) -> None:
    left, right = textured_pair()
    out = running.client.send_until_output(left, right, running.next_stamp())
    disparity_msg, confidence_msg = out['disparity'], out['confidence']
    filtered_msg, cloud_msg = out['disparity_filtered'], out['points2']
    stamp = disparity_msg.header.stamp

    for msg in (disparity_msg, confidence_msg, filtered_msg, cloud_msg):
        assert msg.header.frame_id == 'left_optical'
        assert msg.header.stamp == stamp

    # Disparity: filled like stereo_image_proc.
    assert disparity_msg.image.encoding == '32FC1'
    assert (disparity_msg.image.height, disparity_msg.image.width) == (64, 96)
    assert disparity_msg.f == pytest.approx(FX)
    assert disparity_msg.t == pytest.approx(BASELINE)
    assert (disparity_msg.min_disparity, disparity_msg.max_disparity) == (0.0, 15.0)
    assert disparity_msg.delta_d == 0.0  # sub-pixel disparities (subpixel: equiangular)
    assert disparity_msg.valid_window.x_offset == MAX_DISPARITY - 1
    disparity = disparity_from_message(disparity_msg)
    inner = _interior(disparity, 4)
    assert np.mean(np.abs(inner - TRUE_DISPARITY) < 0.5) > 0.95
    assert np.any(inner != np.round(inner))

    # Confidence: same size, [0, 1].
    assert confidence_msg.encoding == '32FC1'
    confidence = float_image_to_array(confidence_msg)
    assert confidence.shape == (64, 96)
    assert np.all((confidence >= 0) & (confidence <= 1))

    # The filtered disparity keeps exactly the confident pixels outside speckles; the
    # speckle filter drops some of the confident ones (the unmatched left border, where the
    # disparities are noise).
    confident = np.isfinite(disparity) & (confidence >= THRESHOLD)
    keep = _kept(disparity, confidence)
    assert 0 < keep.sum() < confident.sum()
    filtered = disparity_from_message(filtered_msg)
    np.testing.assert_array_equal(np.isfinite(filtered), keep)
    np.testing.assert_array_equal(filtered[keep], disparity[keep])

    # The cloud: organised, only confident points, at Z = fB/d, X = (u − cx)Z/f, Y = (v − cy)Z/f.
    assert (cloud_msg.height, cloud_msg.width) == (64, 96)
    assert not cloud_msg.is_dense
    cloud = cloud_to_array(cloud_msg)
    finite = np.isfinite(cloud['z'])
    np.testing.assert_array_equal(finite, keep & (disparity > 0))
    rows, cols = np.nonzero(finite)
    z = FX * BASELINE / disparity[rows, cols]
    np.testing.assert_allclose(cloud['z'][rows, cols], z, rtol=1e-5)
    np.testing.assert_allclose(
        cloud['x'][rows, cols], (cols - 48.0) * z / FX, rtol=1e-5, atol=1e-6
    )
    np.testing.assert_allclose(
        cloud['y'][rows, cols], (rows - 32.0) * z / FX, rtol=1e-5, atol=1e-6
    )
    # Where the disparity is right, the depth is f·B/5 = 2 m (within the ±0.5 px of the
    # sub-pixel step, and on the median much closer); the colour is the gray value.
    good = finite & (np.abs(disparity - TRUE_DISPARITY) < 0.5)
    assert good.sum() > 0.5 * finite.sum()
    np.testing.assert_allclose(cloud['z'][good], 2.0, rtol=0.12)
    assert np.median(cloud['z'][good]) == pytest.approx(2.0, rel=0.01)
    bits = cloud['rgb'][good].view(np.uint32)
    gray = left[good].astype(np.uint32)
    np.testing.assert_array_equal(bits, (gray << 16) | (gray << 8) | gray)


@pytest.mark.parametrize('encoding', ['rgb8', 'bgr8', 'rgba8', 'bgra8', 'mono16'])
def test_other_encodings(running: _Running, encoding: str) -> None:
    left, right = textured_pair(seed=1)
    if encoding == 'mono16':
        # 12-bit data: scaled jointly back to 8 bits, matching is unchanged.
        left16, right16 = left.astype(np.uint16) * 16, right.astype(np.uint16) * 16
        left_msg, right_msg = image_msg(left16, 0), image_msg(right16, 0)
    else:
        channels = {'rgb8': 3, 'bgr8': 3, 'rgba8': 4, 'bgra8': 4}[encoding]
        left_msg = image_msg(np.repeat(left[..., None], channels, 2), 0, encoding)
        right_msg = image_msg(np.repeat(right[..., None], channels, 2), 0, encoding)
    stamp = running.next_stamp()
    client = running.client
    for attempt in range(10):
        now = stamp + attempt * 1_000_000
        for msg in (left_msg, right_msg):
            msg.header.stamp = rclpy.time.Time(nanoseconds=now).to_msg()
        left_info, right_info = info_msgs(now)
        client.pubs['left_info'].publish(left_info)
        client.pubs['right_info'].publish(right_info)
        client.pubs['left'].publish(left_msg)
        client.pubs['right'].publish(right_msg)
        if client.wait_for(lambda s=now: client.by_stamp('disparity', s) is not None, 2.0):
            break
    else:
        pytest.fail(f'no disparity for a {encoding} pair')
    disparity = disparity_from_message(client.by_stamp('disparity', now))
    assert np.mean(np.abs(_interior(disparity, 4) - TRUE_DISPARITY) < 0.5) > 0.95


def test_diagnostics(running: _Running) -> None:
    client = running.client
    left, right = textured_pair(seed=2)
    client.send_until_output(left, right, running.next_stamp(), topics=('disparity',))

    def status():
        for array in reversed(client.received['/diagnostics']):
            for entry in array.status:
                values = {kv.key: kv.value for kv in entry.values}
                if entry.name.startswith('cva_confidence') and 'mean_matching_ms' in values:
                    return entry, values
        return None

    assert client.wait_for(lambda: status() is not None, timeout=10.0)
    entry, values = status()
    assert entry.hardware_id.endswith('cva_confidence')
    assert int(values['frames_processed']) >= 1
    assert int(values['frames_received']) >= int(values['frames_processed'])
    for key in ('frames_dropped', 'frames_invalid', 'messages_received', 'messages_unmatched'):
        assert int(values[key]) >= 0
    for stage in ('resize', 'matching', 'confidence', 'total', 'convert', 'publish', 'frame'):
        assert float(values[f'mean_{stage}_ms']) >= 0.0
    assert values['matcher'] == 'census_bm' and values['confidence_method'] == 'mlm'


def test_diagnostics_give_the_confident_share_and_warn_below_a_floor(running: _Running) -> None:
    client = running.client
    left, right = textured_pair(seed=7)
    topics = ('disparity', 'confidence')
    out = client.send_until_output(left, right, running.next_stamp(), topics=topics)
    disparity = disparity_from_message(out['disparity'])
    confidence = float_image_to_array(out['confidence'])
    share = float(np.mean(_kept(disparity, confidence)))
    assert 0.0 < share < 1.0

    def status(predicate):
        for array in reversed(client.received['/diagnostics']):
            for entry in array.status:
                values = {kv.key: kv.value for kv in entry.values}
                if entry.name.startswith('cva_confidence') and predicate(entry, values):
                    return entry, values
        return None

    def reports_share(entry, values) -> bool:
        return values.get('last_kept_fraction') == f'{share:.4f}'

    assert client.wait_for(lambda: status(reports_share) is not None, timeout=10.0)
    _, values = status(reports_share)
    assert 0.0 <= float(values['last_mean_confidence']) <= 1.0
    # The pixels that passed the threshold but were dropped as speckles.
    confident = np.isfinite(disparity) & (confidence >= THRESHOLD)
    speckles = float(np.mean(confident)) - share
    assert float(values['last_speckle_fraction']) == pytest.approx(speckles, abs=1e-4)

    # A floor above the share: the period's status is a warning that says so.
    assert running.set(min_kept_fraction=min(1.0, share + 0.2)).successful
    try:
        def warns(entry, values) -> bool:
            return entry.level == DiagnosticStatus.WARN and 'are confident' in entry.message

        client.send_until_output(left, right, running.next_stamp(), topics=topics)
        assert client.wait_for(lambda: status(warns) is not None, timeout=10.0)
        entry, values = status(warns)
        assert f'only {100 * share:.1f} % of the pixels' in entry.message
        assert float(values['kept_fraction']) == pytest.approx(share, abs=1e-4)
        assert not running.set(min_kept_fraction=1.5).successful
    finally:
        assert running.set(min_kept_fraction=0.0).successful


def test_diagnostics_give_the_error_a_network_predicts_for_the_kept_pixels(
    running: _Running,
) -> None:
    client = running.client
    left, right = textured_pair(seed=12)
    topics = ('disparity', 'confidence')

    def status(predicate):
        for array in reversed(client.received['/diagnostics']):
            for entry in array.status:
                values = {kv.key: kv.value for kv in entry.values}
                if entry.name.startswith('cva_confidence') and predicate(values):
                    return values
        return None

    # MLM's values are no probabilities: no estimate.
    client.send_until_output(left, right, running.next_stamp(), topics=topics)
    assert client.wait_for(
        lambda: status(lambda v: v.get('confidence_method') == 'mlm'
                       and v.get('last_kept_fraction')) is not None, timeout=10.0
    )
    values = status(lambda v: v.get('confidence_method') == 'mlm')
    assert values['expected_kept_error'] == values['last_expected_kept_error'] == ''

    # CVA-Net-Fast's are: mean(1 − confidence) over the pixels the node keeps.
    assert running.set(confidence_method='cva_net_fast', max_disparity=64).successful
    try:
        out = client.send_until_output(left, right, running.next_stamp(), topics=topics)
        disparity = disparity_from_message(out['disparity'])
        confidence = float_image_to_array(out['confidence']).astype(np.float64)
        kept = _kept(disparity, confidence.astype(np.float32))
        assert kept.any()
        expected = 1.0 - confidence[kept].mean()

        def reports_it(values) -> bool:
            text = values.get('last_expected_kept_error', '')
            return bool(text) and abs(float(text) - expected) <= 1e-4

        assert client.wait_for(lambda: status(reports_it) is not None, timeout=10.0)
        values = status(reports_it)
        assert values['confidence_method'] == 'cva_net_fast'
        assert 0.0 <= float(values['expected_kept_error']) <= 1.0

        # A ceiling below it: the period's status is a warning that names the prediction.
        assert running.set(max_expected_kept_error=expected / 2).successful

        def warns(entry) -> bool:
            return entry.level == DiagnosticStatus.WARN and 'wrong disparities' in entry.message

        def warning():
            for array in reversed(client.received['/diagnostics']):
                for entry in array.status:
                    if entry.name.startswith('cva_confidence') and warns(entry):
                        return entry
            return None

        client.send_until_output(left, right, running.next_stamp(), topics=topics)
        assert client.wait_for(lambda: warning() is not None, timeout=10.0)
        assert f'predicts {100 * expected:.1f} %' in warning().message
        assert not running.set(max_expected_kept_error=-0.1).successful
    finally:
        assert running.set(
            confidence_method='mlm', max_disparity=MAX_DISPARITY, max_expected_kept_error=1.0
        ).successful


def test_parameters_are_declared_with_descriptions_and_ranges(running: _Running) -> None:
    node = running.node
    names = {spec.name for spec in PARAMETERS}
    assert names <= set(node._parameters)
    descriptors = node.describe_parameters(sorted(names))
    by_name = {d.name: d for d in descriptors}
    assert all(d.description for d in descriptors)
    assert by_name['max_disparity'].integer_range[0].from_value == 1
    assert by_name['confidence_threshold'].floating_point_range[0].to_value == 1.0
    assert by_name['input_qos'].read_only


def test_invalid_parameter_changes_are_rejected_with_a_reason(running: _Running) -> None:
    before = running.node.pipeline_config
    result = running.set(matcher='no_such_matcher')
    assert not result.successful and 'no_such_matcher' in result.reason
    result = running.set(max_disparity=5000)  # outside the declared range
    assert not result.successful
    result = running.set(downsample=3)
    assert not result.successful and 'downsample' in result.reason
    result = running.set(confidence_method='cva_net', model_path='/nonexistent/weights.pt')
    assert not result.successful and result.reason
    result = running.set(input_qos='reliable')  # read-only after start
    assert not result.successful
    assert running.node.pipeline_config == before
    assert running.node.get_parameter('matcher').value == 'census_bm'


def test_parameter_service_rebuilds_the_pipeline(running: _Running) -> None:
    client = running.client
    try:
        answers = set_parameters_by_service(client.node, max_disparity=24)
        assert [r.successful for r in answers] == [True]
        assert running.node.pipeline_config.max_disparity == 24
        left, right = textured_pair(seed=3)
        out = client.send_until_output(left, right, running.next_stamp(), topics=('disparity',))
        assert out['disparity'].max_disparity == 23.0
    finally:
        result = running.set(max_disparity=MAX_DISPARITY)
        assert result.successful


def test_a_new_pipeline_is_warmed_up_on_the_worker_before_its_first_frame(
    running: _Running, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A change that rebuilds the pipeline warms it up as the start does (the matcher's numba
    # kernels compile: seconds on a cold cache), on the worker and not in the parameter
    # callback: the executor goes on serving parameters and diagnostics, and frames wait.
    client = running.client
    calls: list[tuple[int, str]] = []
    release = threading.Event()
    warm_up = StereoPipeline.warm_up

    def slow_warm_up(pipeline: StereoPipeline) -> None:
        if pipeline.config.max_disparity == 24:  # not one an earlier test left to warm up
            calls.append((pipeline.config.max_disparity, threading.current_thread().name))
            release.wait(20.0)
        warm_up(pipeline)

    monkeypatch.setattr(StereoPipeline, 'warm_up', slow_warm_up)
    left, right = textured_pair(seed=12)
    try:
        tic = time.monotonic()
        result = running.set(max_disparity=24)
        assert result.successful and time.monotonic() - tic < 2.0
        assert client.wait_for(lambda: bool(calls), 10.0), 'the new pipeline was not warmed up'
        assert calls == [(24, 'cva_confidence_worker')]
        # While it warms up, the parameter service answers and a frame waits for it.
        (answer,) = running.set_by_service(min_kept_fraction=0.0)
        assert answer.successful
        stamps = [running.next_stamp(), running.next_stamp()]
        for stamp in stamps:
            client.publish_frame(left, right, stamp)
        time.sleep(1.0)
        assert all(client.by_stamp('disparity', stamp) is None for stamp in stamps)
        release.set()
        # The newest waiting frame goes first (best-effort input: either may be lost).
        assert client.wait_for(
            lambda: any(client.by_stamp('disparity', stamp) for stamp in stamps), 20.0
        )
        out = client.send_until_output(left, right, running.next_stamp(), topics=('disparity',))
        assert out['disparity'].max_disparity == 23.0
        assert client.wait_for(
            lambda: bool(running.logged('new pipeline warmed up in', Log.INFO)), 5.0
        )
    finally:
        release.set()
        monkeypatch.undo()
        assert running.set(max_disparity=MAX_DISPARITY).successful
    assert len(calls) == 1


def test_downsample_publishes_at_lower_resolution(running: _Running) -> None:
    result = running.set(downsample=2, max_disparity=8)
    assert result.successful
    try:
        left, right = textured_pair(height=64, width=96, disparity=6, seed=4)
        topics = ('disparity', 'confidence', 'points2', 'camera_info')
        out = running.client.send_until_output(left, right, running.next_stamp(), topics=topics)
        disparity_msg = out['disparity']
        assert (disparity_msg.image.height, disparity_msg.image.width) == (32, 48)
        info = out['camera_info']
        assert (info.width, info.height) == (48, 32)
        # cx = 48 → (48 + 0.5)/2 − 0.5 = 23.75; cy = 32 → 15.75.
        np.testing.assert_allclose(info.k, [50, 0, 23.75, 0, 50, 15.75, 0, 0, 1])
        assert disparity_msg.f == pytest.approx(FX / 2)
        assert disparity_msg.t == pytest.approx(BASELINE)
        disparity = disparity_from_message(disparity_msg)
        inner = disparity[3:-3, 10:-3]
        assert np.mean(np.abs(inner - 3.0) <= 1.0) > 0.8
        confidence = float_image_to_array(out['confidence'])
        assert confidence.shape == (32, 48)
        cloud = cloud_to_array(out['points2'])
        assert cloud.shape == (32, 48)
        finite = np.isfinite(cloud['z'])
        # Depth is resolution independent: f/2 · B / (d/2).
        rows, cols = np.nonzero(finite)
        np.testing.assert_allclose(
            cloud['z'][rows, cols], (FX / 2) * BASELINE / disparity[rows, cols], rtol=1e-5
        )
    finally:
        result = running.set(downsample=1, max_disparity=MAX_DISPARITY)
        assert result.successful


def test_depth_of_the_confident_pixels_in_both_encodings(running: _Running) -> None:
    # REP 118 depth beside camera_info: Z = f·B/d on the pixels disparity_filtered keeps.
    topics = ('disparity', 'confidence', 'depth', 'camera_info')
    left, right = textured_pair(seed=6)
    out = running.client.send_until_output(left, right, running.next_stamp(), topics=topics)
    depth_msg = out['depth']
    assert depth_msg.header == out['disparity'].header == out['camera_info'].header
    assert (depth_msg.encoding, depth_msg.height, depth_msg.width) == ('32FC1', 64, 96)
    disparity = disparity_from_message(out['disparity'])
    confidence = float_image_to_array(out['confidence'])
    keep = _kept(disparity, confidence) & (disparity > 0)
    depth = depth_image_to_array(depth_msg)
    np.testing.assert_array_equal(np.isfinite(depth), keep)
    np.testing.assert_allclose(depth[keep], FX * BASELINE / disparity[keep], rtol=1e-5)
    good = keep & (np.abs(disparity - TRUE_DISPARITY) < 0.5)
    np.testing.assert_allclose(depth[good], 2.0, rtol=0.12)  # f·B/5 = 2 m, d within 0.5 px

    # 16UC1 as a run-time change: whole millimetres, 0 where there is no depth.
    assert running.set(depth_encoding='16UC1').successful
    try:
        out = running.client.send_until_output(left, right, running.next_stamp(), topics=topics)
        depth_msg = out['depth']
        assert (depth_msg.encoding, depth_msg.step) == ('16UC1', 2 * 96)
        millimetres = np.frombuffer(bytes(depth_msg.data), '<u2').reshape(64, 96)
        np.testing.assert_array_equal(millimetres > 0, keep)
        np.testing.assert_allclose(millimetres[keep], depth[keep] * 1000, atol=0.5)
        refused = running.set(depth_encoding='16UC2')
        assert not refused.successful and 'depth_encoding' in refused.reason
    finally:
        assert running.set(depth_encoding='32FC1').successful


def test_compressed_transports_of_the_overlay_and_the_depth(running: _Running) -> None:
    # image_transport's confidence_overlay/compressed (JPEG) and depth/compressedDepth (PNG of
    # inverse-depth codes), encoded while subscribed: decoded, they are the raw outputs within
    # the JPEG loss and the quantisation step depth² / (q·(q + 1)).
    running.client.subscribe('confidence_overlay', Image)
    running.client.subscribe('confidence_overlay/compressed', CompressedImage)
    running.client.subscribe('depth/compressedDepth', CompressedImage)
    topics = ('depth', 'confidence_overlay', 'confidence_overlay/compressed',
              'depth/compressedDepth')
    left, right = textured_pair(seed=11)
    out = running.client.send_until_output(left, right, running.next_stamp(), topics=topics)
    jpeg, packed = out['confidence_overlay/compressed'], out['depth/compressedDepth']
    assert jpeg.header == packed.header == out['depth'].header
    assert jpeg.format == 'rgb8; jpeg compressed bgr8'
    overlay = image_to_array(out['confidence_overlay']).astype(float)
    decoded = compressed_image_to_array(jpeg)
    assert decoded.shape == overlay.shape
    assert np.abs(decoded - overlay).mean() < 4.0
    assert packed.format == '32FC1; compressedDepth png'
    depth = depth_image_to_array(out['depth'])
    back = compressed_depth_to_array(packed)
    with np.errstate(invalid='ignore'):
        kept = np.isfinite(depth) & (depth < 10.0)  # compressed_depth_max (image_transport's)
    assert kept.any()
    np.testing.assert_array_equal(np.isfinite(back), kept)
    step = depth[kept] ** 2 / (100.0 * 101.0)
    assert np.all(np.abs(back[kept] - depth[kept]) <= step * 1.01)

    # At run time: a nearer depth_max sends only the nearer pixels, a lower quality is smaller.
    assert running.set(compressed_depth_max=1.9, overlay_jpeg_quality=30).successful
    try:
        out = running.client.send_until_output(left, right, running.next_stamp(), topics=topics)
        depth = depth_image_to_array(out['depth'])
        back = compressed_depth_to_array(out['depth/compressedDepth'])
        with np.errstate(invalid='ignore'):
            np.testing.assert_array_equal(np.isfinite(back), np.isfinite(depth) & (depth < 1.9))
        assert np.isfinite(depth).sum() > np.isfinite(back).sum()
        assert len(out['confidence_overlay/compressed'].data) < len(jpeg.data)
        for bad in ({'overlay_jpeg_quality': 0}, {'compressed_depth_max': 0.0},
                    {'compressed_depth_png_level': 10}):
            refused = running.set(**bad)
            assert not refused.successful and next(iter(bad)) in refused.reason
    finally:
        assert running.set(compressed_depth_max=10.0, overlay_jpeg_quality=95).successful


def test_subpixel_changes_at_run_time(running: _Running) -> None:
    # Integer disparities (and delta_d 1) with subpixel: none; the refined ones lie within
    # half a pixel of them, for the same confidence.
    left, right = textured_pair(seed=8)
    topics = ('disparity', 'confidence')
    refined = running.client.send_until_output(left, right, running.next_stamp(), topics=topics)
    assert running.set(subpixel='none').successful
    try:
        out = running.client.send_until_output(left, right, running.next_stamp(), topics=topics)
        assert out['disparity'].delta_d == 1.0
        integer = disparity_from_message(out['disparity'])
        assert np.all(integer[np.isfinite(integer)] == np.round(integer[np.isfinite(integer)]))
        step = disparity_from_message(refined['disparity']) - integer
        assert np.all(np.abs(step[np.isfinite(step)]) <= 0.5) and np.any(step != 0)
        np.testing.assert_array_equal(
            float_image_to_array(out['confidence']),
            float_image_to_array(refined['confidence']),
        )
        refused = running.set(subpixel='cubic')
        assert not refused.successful and 'subpixel' in refused.reason
    finally:
        assert running.set(subpixel='equiangular').successful


def test_speckle_filter_changes_at_run_time(running: _Running) -> None:
    # speckle_size: 0 keeps every confident pixel; a larger region size drops more of them.
    left, right = textured_pair(seed=9)
    topics = ('disparity', 'confidence', 'disparity_filtered')

    def kept_pixels() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        out = running.client.send_until_output(left, right, running.next_stamp(), topics=topics)
        disparity = disparity_from_message(out['disparity'])
        confidence = float_image_to_array(out['confidence'])
        return disparity, confidence, np.isfinite(disparity_from_message(
            out['disparity_filtered']))

    disparity, confidence, default = kept_pixels()
    np.testing.assert_array_equal(default, _kept(disparity, confidence))
    assert running.set(speckle_size=0).successful
    try:
        disparity, confidence, off = kept_pixels()
        np.testing.assert_array_equal(off, np.isfinite(disparity) & (confidence >= THRESHOLD))
        assert running.set(speckle_size=400, speckle_range=0.25).successful
        disparity, confidence, strict = kept_pixels()
        keep = np.isfinite(disparity) & (confidence >= THRESHOLD)
        np.testing.assert_array_equal(strict, remove_speckles(disparity, keep, 400, 0.25))
        assert strict.sum() < default.sum() < off.sum()
        for bad in ({'speckle_size': -1}, {'speckle_range': -1.0}):
            refused = running.set(**bad)
            assert not refused.successful
    finally:
        defaults = PipelineConfig()
        assert running.set(
            speckle_size=defaults.speckle_size, speckle_range=defaults.speckle_range
        ).successful


def _published(
    running: _Running, left: np.ndarray, right: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One frame as the node publishes it: disparity, confidence, the kept pixels (finite in
    ``disparity_filtered``) and depth."""
    out = running.client.send_until_output(
        left, right, running.next_stamp(),
        topics=('disparity', 'confidence', 'disparity_filtered', 'depth'),
    )
    return (disparity_from_message(out['disparity']),
            float_image_to_array(out['confidence']),
            np.isfinite(disparity_from_message(out['disparity_filtered'])),
            depth_image_to_array(out['depth']))


def test_region_of_interest_changes_at_run_time(running: _Running) -> None:
    # roi_top / roi_bottom: only those rows are processed; the rest is published as nothing
    # kept (invalid disparity, confidence 0), and /diagnostics gives the region's kept share.
    left, right = textured_pair(seed=11)
    whole = _published(running, left, right)
    assert running.set(roi_top=0.25, roi_bottom=0.75).successful
    try:
        disparity, confidence, kept, depth = _published(running, left, right)
        y0, y1 = PipelineConfig(roi_top=0.25, roi_bottom=0.75).roi_rows(64)
        assert (y0, y1) == (16, 48)
        outside = np.r_[0:y0, y1:64]
        assert np.isnan(disparity[outside]).all() and (confidence[outside] == 0).all()
        assert not kept[outside].any() and np.isnan(depth[outside]).all()
        # Census-BM and MLM reach a few rows: inside, the whole image's values.
        np.testing.assert_array_equal(disparity[y0:y1], whole[0][y0:y1])
        np.testing.assert_array_equal(confidence[y0:y1], whole[1][y0:y1])
        assert kept[y0:y1].any()
        share = f'{kept[y0:y1].mean():.4f}'

        def reports_share() -> bool:
            return any(
                {kv.key: kv.value for kv in entry.values}.get('last_kept_fraction') == share
                for array in running.client.received['/diagnostics'] for entry in array.status
            )

        assert running.client.wait_for(reports_share, timeout=10.0)
        refused = running.set(roi_top=0.8)
        assert not refused.successful and 'roi_top must be smaller than roi_bottom' \
            in refused.reason
    finally:
        assert running.set(roi_top=0.0, roi_bottom=1.0).successful


def test_ignore_mask_changes_at_run_time(running: _Running, tmp_path: Path) -> None:
    # mask_path: black pixels (the robot's own bumper) are published as nothing kept, in every
    # output; a mask of another size than the images is refused with both sizes named.
    left, right = textured_pair(seed=12)
    whole = _published(running, left, right)
    mask = np.full((64, 96), 255, np.uint8)
    mask[52:, :30] = 0
    mask[:, 90:] = 0
    path = tmp_path / 'bumper.png'
    assert cv2.imwrite(str(path), mask)
    assert running.set(mask_path=str(path)).successful
    try:
        disparity, confidence, kept, depth = _published(running, left, right)
        ignored = mask == 0
        assert np.isnan(disparity[ignored]).all() and (confidence[ignored] == 0).all()
        assert not kept[ignored].any() and np.isnan(depth[ignored]).all()
        np.testing.assert_array_equal(disparity[~ignored], whole[0][~ignored])
        np.testing.assert_array_equal(confidence[~ignored], whole[1][~ignored])
        assert kept[~ignored].any()
        wrong = tmp_path / 'half.png'
        assert cv2.imwrite(str(wrong), mask[::2, ::2])
        refused = running.set(mask_path=str(wrong))
        assert not refused.successful
        assert 'is 48×32 px but the images are 96×64 px' in refused.reason
        missing = running.set(mask_path=str(tmp_path / 'nowhere.png'))
        assert not missing.successful and 'nowhere.png' in missing.reason
        assert 'is not a file' in missing.reason
        # A region of interest that leaves none of the mask's pixels is refused (rather than
        # taken, and every frame dropped after it).
        top = tmp_path / 'top.png'
        only_top = np.full((64, 96), 255, np.uint8)
        only_top[24:] = 0
        assert cv2.imwrite(str(top), only_top)
        assert running.set(mask_path=str(top)).successful
        refused = running.set(roi_top=0.5)
        assert not refused.successful and 'no pixel in common' in refused.reason
        assert running.set(mask_path=str(path)).successful
        # /diagnostics: the share judged, and the kept share of those pixels.
        judged, share = f'{(~ignored).mean():.4f}', f'{kept[~ignored].mean():.4f}'

        def reports_shares() -> bool:
            return any(
                (values.get('last_judged_fraction'), values.get('last_kept_fraction'))
                == (judged, share)
                for array in running.client.received['/diagnostics'] for entry in array.status
                for values in [{kv.key: kv.value for kv in entry.values}]
            )

        assert running.client.wait_for(reports_shares, timeout=10.0)
        assert 'mask=bumper.png' in running.node.summary()
    finally:
        assert running.set(mask_path='').successful


def test_a_mask_edited_under_its_name_is_read_when_mask_path_is_set_again(
    running: _Running, tmp_path: Path
) -> None:
    # The README's "add a mast" step: cva-mask --start bumper.png --overwrite, then set
    # mask_path again. The same path compared equal, so the old mask stayed while "set" was
    # logged.
    left, right = textured_pair(seed=13)
    mask = np.full((64, 96), 255, np.uint8)
    mask[52:, :30] = 0
    path = tmp_path / 'bumper.png'
    assert cv2.imwrite(str(path), mask)
    assert running.set(mask_path=str(path)).successful
    try:
        disparity = _published(running, left, right)[0]
        assert np.isnan(disparity[52:, :30]).all() and np.isfinite(disparity[:40, 60:80]).any()
        mask[:, 60:80] = 0  # a mast
        assert cv2.imwrite(str(path), mask)
        assert running.set(mask_path=str(path)).successful
        disparity = _published(running, left, right)[0]
        assert np.isnan(disparity[:, 60:80]).all()
    finally:
        assert running.set(mask_path='').successful


def test_confidence_overlay_for_a_person_to_look_at(running: _Running) -> None:
    # rgb8 at the output size with the left image's header: the kept pixels tinted (green above
    # red where the confidence is high), the others a dimmed grey (r = g = b).
    from cva_confidence_ros.plots import confidence_overlay
    from cva_confidence_ros.ros.convert import image_to_array

    running.client.subscribe('confidence_overlay', Image)
    left, right = textured_pair(seed=10)
    topics = ('disparity', 'confidence', 'disparity_filtered', 'confidence_overlay')
    out = running.client.send_until_output(left, right, running.next_stamp(), topics=topics)
    msg = out['confidence_overlay']
    assert (msg.encoding, msg.height, msg.width) == ('rgb8', 64, 96)
    assert msg.header == out['disparity'].header
    overlay = image_to_array(msg)
    confidence = float_image_to_array(out['confidence'])
    kept = np.isfinite(disparity_from_message(out['disparity_filtered']))
    assert 0 < kept.sum() < kept.size
    np.testing.assert_array_equal(overlay, confidence_overlay(left, confidence, kept))
    grey = (overlay[..., 0] == overlay[..., 1]) & (overlay[..., 1] == overlay[..., 2])
    assert grey[~kept].all() and not grey[kept].any()
    sure = kept & (confidence > 0.9)
    assert sure.any() and np.all(overlay[sure, 1] > overlay[sure, 0])


def test_scan_of_the_confident_pixels_for_obstacle_layers(running: _Running) -> None:
    # A LaserScan in the body frame beside left_optical ('left'), stamped like the images,
    # equal to disparity_to_scan of the published outputs; the textured wall 2 m ahead
    # (d = 5) gives ranges of 2 / cos(bearing) where the disparity is right.
    from sensor_msgs.msg import LaserScan

    from cva_confidence_ros.pointcloud import StereoGeometry
    from cva_confidence_ros.scan import ScanConfig, disparity_to_scan

    running.client.subscribe('scan', LaserScan)
    left, right = textured_pair(seed=11)
    topics = ('disparity', 'confidence', 'disparity_filtered', 'scan')
    geometry = StereoGeometry(fx=FX, fy=FX, cx=48.0, cy=32.0, cx_right=48.0, baseline=BASELINE)

    def scan_and_reference(config: ScanConfig) -> tuple[LaserScan, object, dict]:
        out = running.client.send_until_output(left, right, running.next_stamp(), topics=topics)
        disparity = disparity_from_message(out['disparity'])
        kept = np.isfinite(disparity_from_message(out['disparity_filtered']))
        confidence = float_image_to_array(out['confidence'])
        reference = disparity_to_scan(disparity, geometry, kept, confidence, config)
        return out['scan'], reference, out

    msg, reference, out = scan_and_reference(ScanConfig())
    assert msg.header.frame_id == 'left' and msg.header.stamp == out['disparity'].header.stamp
    np.testing.assert_array_equal(np.asarray(msg.ranges), reference.ranges)
    np.testing.assert_array_equal(np.asarray(msg.intensities), reference.intensities)
    assert (msg.angle_min, msg.angle_max) == pytest.approx((reference.angle_min,
                                                            reference.angle_max))
    assert msg.angle_increment == pytest.approx(reference.angle_increment)
    assert (msg.range_min, msg.range_max, msg.time_increment) == pytest.approx((0.1, 20.0, 0.0))
    ranges = np.asarray(msg.ranges)
    bearings = msg.angle_min + msg.angle_increment * np.arange(ranges.size)
    near_two = np.abs(ranges * np.cos(bearings) - 2.0) < 0.2
    assert near_two.mean() > 0.8

    # Run-time changes: another frame, a band above the camera; a band that is empty refused.
    assert running.set(scan_frame_id='stereo_link', scan_min_height=0.3,
                       scan_max_height=0.6).successful
    try:
        config = ScanConfig(min_height=0.3, max_height=0.6)
        msg, reference, _ = scan_and_reference(config)
        assert msg.header.frame_id == 'stereo_link'
        np.testing.assert_array_equal(np.asarray(msg.ranges), reference.ranges)
        assert np.isfinite(reference.ranges).any()
        refused = running.set(scan_min_height=0.7)
        assert not refused.successful and 'scan_min_height' in refused.reason
    finally:
        defaults = NodeConfig()
        assert running.set(scan_frame_id='', scan_min_height=defaults.scan_min_height,
                           scan_max_height=defaults.scan_max_height).successful


def test_a_scan_in_a_frame_not_named_optical_is_warned_about(running: _Running) -> None:
    # A camera frame without the optical suffix: the scan goes out in it, with one warning
    # that says to set scan_frame_id (a LaserScan in an optical frame would be turned).
    from sensor_msgs.msg import LaserScan

    client = running.client
    client.subscribe('scan', LaserScan)
    left, right = textured_pair(seed=12)
    deadline = time.monotonic() + 30.0
    scan = None
    while scan is None and time.monotonic() < deadline:
        stamp = running.next_stamp()
        messages = {
            'left_info': info_msgs(stamp)[0], 'right_info': info_msgs(stamp)[1],
            'left': image_msg(left, stamp), 'right': image_msg(right, stamp),
        }
        for key, msg in messages.items():
            msg.header.frame_id = 'stereo_cam'
            client.pubs[key].publish(msg)
        client.wait_for(lambda s=stamp: client.by_stamp('scan', s) is not None, timeout=2.0)
        scan = client.by_stamp('scan', stamp)
    assert scan is not None and scan.header.frame_id == 'stereo_cam'
    assert client.wait_for(lambda: bool(running.logged('set scan_frame_id')))
    (line,) = running.logged('set scan_frame_id')
    assert "camera frame 'stereo_cam'" in line


def test_a_pitched_scan_in_the_camera_body_frame_is_warned_about(running: _Running) -> None:
    # The scan is level (scan_pitch taken out) but went out in the camera's body frame, which
    # is pitched with the camera: consumers put its returns on a tilted plane, without a word.
    from sensor_msgs.msg import LaserScan

    client = running.client
    client.subscribe('scan', LaserScan)
    left, right = textured_pair(seed=14)
    assert running.set(scan_pitch=0.2).successful
    try:
        client.send_until_output(left, right, running.next_stamp(), topics=('scan',))
        assert client.wait_for(lambda: bool(running.logged('pitched with the camera')))
        (line,) = running.logged('pitched with the camera')
        assert 'scan_pitch 0.2 rad' in line and 'set scan_frame_id to a level frame' in line
        client.send_until_output(left, right, running.next_stamp(), topics=('scan',))
        assert len(running.logged('pitched with the camera')) == 1  # once
    finally:
        assert running.set(scan_pitch=0.0).successful


def test_dense_cloud(running: _Running) -> None:
    result = running.set(points_organized=False)
    assert result.successful
    try:
        left, right = textured_pair(seed=5)
        out = running.client.send_until_output(left, right, running.next_stamp())
        cloud_msg = out['points2']
        assert cloud_msg.height == 1 and cloud_msg.is_dense
        cloud = cloud_to_array(cloud_msg)[0]
        assert np.isfinite(cloud['z']).all()
        confidence = float_image_to_array(out['confidence'])
        disparity = disparity_from_message(out['disparity'])
        keep = _kept(disparity, confidence) & (disparity > 0)
        assert cloud.shape[0] == keep.sum()
        np.testing.assert_allclose(cloud['z'], FX * BASELINE / disparity[keep], rtol=1e-5)
    finally:
        result = running.set(points_organized=True)
        assert result.successful


def test_cloud_with_confidence_cut_downstream_by_the_filter_node(running: _Running) -> None:
    # points_confidence: every point that can be triangulated, each with its confidence; the
    # cloud_filter node (over DDS, in this context) then keeps what the node alone would have.
    from sensor_msgs.msg import PointCloud2

    from cva_confidence_ros.pointcloud import CLOUD_CONFIDENCE_DTYPE
    from cva_confidence_ros.ros.cloud_filter_node import CloudFilterNode

    cloud_filter = CloudFilterNode(
        context=running.context, parameter_overrides=[Parameter('threshold', value=THRESHOLD)]
    )
    spinner = Spinner(running.context, cloud_filter)
    running.client.subscribe('points2_filtered', PointCloud2)
    assert running.set(points_confidence=True).successful
    try:
        left, right = textured_pair(seed=12)
        out = running.client.send_until_output(
            left, right, running.next_stamp(),
            topics=('disparity', 'confidence', 'points2', 'points2_filtered'),
        )  # fmt: skip
        cloud = cloud_to_array(out['points2'])
        assert cloud.dtype == CLOUD_CONFIDENCE_DTYPE and cloud.shape == (64, 96)
        assert out['points2'].point_step == 20
        confidence = float_image_to_array(out['confidence'])
        disparity = disparity_from_message(out['disparity'])
        triangulable = np.isfinite(disparity) & (disparity > 0)
        np.testing.assert_array_equal(np.isfinite(cloud['z']), triangulable)
        np.testing.assert_array_equal(cloud['confidence'][triangulable], confidence[triangulable])
        kept = triangulable & (confidence >= THRESHOLD)
        assert 0 < kept.sum() < triangulable.sum(), 'the threshold must cut something here'
        filtered = cloud_to_array(out['points2_filtered'])
        np.testing.assert_array_equal(np.isfinite(filtered['z']), kept)
        np.testing.assert_array_equal(filtered['z'][kept], cloud['z'][kept])
        np.testing.assert_array_equal(filtered['rgb'][kept], cloud['rgb'][kept])
    finally:
        assert running.set(points_confidence=False).successful
        spinner.stop()
        cloud_filter.destroy_node()


def test_max_rate_skips_the_frames_in_between(running: _Running) -> None:
    # A 10 Hz camera (stamps 0.1 s apart) into a node limited to 4 Hz: it takes the frames at
    # 0, 0.3 and 0.6 s (the first ≥ 0.98 / 4 s after the last one taken), skips the others,
    # and takes every frame again once the limit is off. Each frame waits for the node's
    # answer (or its throttled count), so none is lost to the one-slot mailbox.
    client, node = running.client, running.node
    left, right = textured_pair(seed=11)
    assert running.set(max_rate_hz=4.0).successful
    try:
        base = running.next_stamp()
        for k in range(8):
            if k == 7:
                assert running.set(max_rate_hz=0.0).successful
            stamp = base + k * 100_000_000
            before = node.stats()['frames_throttled']
            client.publish_frame(left, right, stamp)
            taken = k in (0, 3, 6, 7)
            if taken:
                assert client.wait_for(
                    lambda s=stamp: client.by_stamp('disparity', s) is not None, 30.0
                ), f'no output for the frame at {k / 10:.1f} s'
            else:
                assert client.wait_for(
                    lambda b=before: node.stats()['frames_throttled'] == b + 1, 30.0
                ), f'the frame at {k / 10:.1f} s was not throttled'
        answered = [k for k in range(8) if client.by_stamp('disparity', base + k * 100_000_000)]
        assert answered == [0, 3, 6, 7]
        # Stamps reset where the synchroniser cannot see it (made anew by a sync parameter, as
        # on activate): the first frame is taken, not skipped until time is back.
        assert running.set(max_rate_hz=4.0, queue_size=11).successful
        earlier = base - 5_000_000_000
        client.publish_frame(left, right, earlier)
        assert client.wait_for(lambda: client.by_stamp('disparity', earlier) is not None, 30.0)
        refused = running.set(max_rate_hz=-1.0)
        assert not refused.successful
        # ros2 param set ... max_rate_hz 2 sends an integer: a number like 2.0; text is not.
        assert running.set(max_rate_hz=2).successful
        assert running.node.node_config.max_rate_hz == 2.0
        refused = running.set(max_rate_hz='fast')
        assert not refused.successful and 'max_rate_hz must be a number' in refused.reason
    finally:
        assert running.set(max_rate_hz=0.0, queue_size=10).successful


def test_approximate_sync(running: _Running) -> None:
    client = running.client
    left, right = textured_pair(seed=6)
    result = running.set(approximate_sync=True, approximate_sync_tolerance_seconds=0.005)
    assert result.successful
    try:
        for _ in range(10):
            stamp = running.next_stamp()
            left_info, _ = info_msgs(stamp)
            _, right_info = info_msgs(stamp + 2_000_000)  # right camera 2 ms late
            client.pubs['left_info'].publish(left_info)
            client.pubs['right_info'].publish(right_info)
            client.pubs['left'].publish(image_msg(left, stamp))
            client.pubs['right'].publish(image_msg(right, stamp + 2_000_000))
            if client.wait_for(lambda s=stamp: client.by_stamp('disparity', s) is not None, 2.0):
                break
        else:
            pytest.fail('no output for a pair 2 ms apart after 10 tries')
    finally:
        result = running.set(approximate_sync=False)
        assert result.successful


def test_stamps_jumping_back_are_logged_and_pairing_goes_on(running: _Running) -> None:
    # ros2 bag play --loop, a driver restart or a simulator reset: time starts over, earlier.
    client, node = running.client, running.node
    left, right = textured_pair(seed=7)
    stamp = running.next_stamp()
    client.send_until_output(left, right, stamp, topics=('disparity',))
    jumps_before = node.stats()['stamp_jumps']
    back = stamp - 100 * 10**9
    for attempt in range(5):
        # Resent 1 ms later should a message of the first try be lost (best-effort input).
        earlier = back + attempt * 1_000_000
        client.publish_frame(left, right, earlier)
        if client.wait_for(lambda s=earlier: client.by_stamp('disparity', s) is not None, 2.0):
            break
    else:
        pytest.fail('no output after the stamps jumped back 100 s')
    following = earlier + 10**9
    client.publish_frame(left, right, following)
    assert client.wait_for(lambda: client.by_stamp('disparity', following) is not None, 5.0)
    assert node.stats()['stamp_jumps'] == jumps_before + 1
    assert client.wait_for(lambda: bool(running.logged('jumped back 100.')), 5.0)
    (warning,) = running.logged('jumped back 100.')
    assert f'{earlier // 10**9}.{earlier % 10**9:09d}' in warning
    # Later frames, newer again, pair as before.
    client.send_until_output(left, right, running.next_stamp(), topics=('disparity',))


def test_a_bag_shorter_than_a_second_on_a_loop_goes_on_pairing(running: _Running) -> None:
    # ros2 bag play --loop of a 0.3 s bag: each pass goes back by less than the 1 s that makes
    # a jump at once; the second frame back tells that the stamps jumped, and the pass pairs
    # (before, every later pass was dropped as late: the node went silent after one pass).
    client, node = running.client, running.node
    left, right = textured_pair(seed=13)
    base = running.next_stamp()
    stamps = [base + k * 100_000_000 for k in range(4)]
    for number in range(3):
        before = node.stats()
        for stamp in stamps:
            client.publish_frame(left, right, stamp)
            time.sleep(0.05)
        # Best-effort input: a message may be lost, so not all four frames need to pair.
        assert client.wait_for(
            lambda b=before: node.stats()['frames_received'] >= b['frames_received'] + 2, 20.0
        ), f'pass {number + 1} of the bag did not pair'
        jumps = node.stats()['stamp_jumps'] - before['stamp_jumps']
        assert jumps == (0 if number == 0 else 1)
    # Later frames, newer again, pair as before.
    client.send_until_output(left, right, running.next_stamp(), topics=('disparity',))


def test_rclpy_parameters_are_left_to_rclpy(running: _Running) -> None:
    client, node = running.client, running.node
    left, right = textured_pair(seed=8)
    try:
        for value in (True, False):
            (result,) = running.set_by_service(use_sim_time=value)
            assert result.successful, result.reason
            assert node.get_parameter('use_sim_time').value is value
            assert node.get_clock().ros_time_is_active is value
            client.send_until_output(left, right, running.next_stamp(), topics=('disparity',))
        assert running.set(use_sim_time=True).successful
        # Parameters no one declared are still refused, by rclpy.
        (result,) = running.set_by_service(no_such_parameter=1)
        assert not result.successful
    finally:
        assert running.set(use_sim_time=False).successful
    assert node.pipeline_config.max_disparity == MAX_DISPARITY


def test_changes_that_could_not_run_here_are_refused_and_logged(running: _Running) -> None:
    client, node = running.client, running.node
    left, right = textured_pair(seed=9)
    client.send_until_output(left, right, running.next_stamp(), topics=('disparity',))
    before = node.pipeline_config
    # The images coming in are 96 px wide: a depth of 96 could never be matched on them.
    result = running.set(max_disparity=96)
    assert not result.successful
    assert 'max_disparity must be smaller than the image width 96; got 96' in result.reason
    result = running.set(max_disparity=48, downsample=2)  # 48 px wide after downsampling
    assert not result.successful and 'image width 48 (96 px at downsample = 2)' in result.reason
    if not torch.cuda.is_available():
        result = running.set(device='cuda')
        assert not result.successful and 'CUDA is not available' in result.reason
    assert node.pipeline_config == before
    # /rosout is a topic: wait for the line itself, not just the first of the three.
    assert client.wait_for(
        lambda: any('max_disparity=96' in line
                    for line in running.logged('parameter change refused')), 5.0
    )
    client.send_until_output(left, right, running.next_stamp(), topics=('disparity',))


def test_the_paper_network_on_every_pixel_of_a_cpu_is_warned_about(running: _Running) -> None:
    if torch.cuda.is_available():
        pytest.skip('device auto picks CUDA here')
    try:
        result = running.set(confidence_method='cva_net', max_disparity=64, device='cpu')
        assert result.successful, result.reason
        assert running.client.wait_for(lambda: bool(running.logged('cva_net on the CPU')), 5.0)
    finally:
        assert running.set(confidence_method='mlm', max_disparity=MAX_DISPARITY).successful


def test_input_that_never_pairs_names_the_silent_topic(running: _Running) -> None:
    client, node = running.client, running.node
    left, right = textured_pair(seed=10)
    period = node.node_config.diagnostics_period_seconds
    deadline = time.monotonic() + max(10.0, 6 * period)
    # No right camera info, ever: a camera driver that publishes only one.
    while time.monotonic() < deadline and not running.logged('nothing on right/camera_info'):
        stamp = running.next_stamp()
        left_info, _ = info_msgs(stamp)
        client.pubs['left_info'].publish(left_info)
        client.pubs['left'].publish(image_msg(left, stamp))
        client.pubs['right'].publish(image_msg(right, stamp))
        time.sleep(0.1)
    (line, *_) = running.logged('nothing on right/camera_info')
    assert line.startswith('messages arrive but none pair up')
    assert 'left/camera_info' not in line.split(';')[0]
    assert '512 kB' not in line  # the large-image hint is for silent images only
    client.send_until_output(left, right, running.next_stamp(), topics=('disparity',))


def test_camera_infos_without_images_point_at_the_large_message_profile(
    running: _Running, monkeypatch: pytest.MonkeyPatch
) -> None:
    # What a 1242×375 colour pair over Fast DDS without the profile looks like: the camera
    # infos come, the images (fragments over UDP, best effort) never do.
    for name in ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE'):
        monkeypatch.delenv(name, raising=False)
    client, node = running.client, running.node
    left, right = textured_pair(seed=12)
    wanted = 'nothing on left/image_rect, right/image_rect'
    deadline = time.monotonic() + max(10.0, 6 * node.node_config.diagnostics_period_seconds)
    while time.monotonic() < deadline and not running.logged(wanted):
        left_info, right_info = info_msgs(running.next_stamp())
        client.pubs['left_info'].publish(left_info)
        client.pubs['right_info'].publish(right_info)
        time.sleep(0.1)
    (line, *_) = running.logged(wanted)
    assert 'images over 512 kB' in line and 'fastdds_large_messages.xml' in line
    client.send_until_output(left, right, running.next_stamp(), topics=('disparity',))


def test_an_approximate_tolerance_of_half_the_frame_period_is_warned_about(
    running: _Running,
) -> None:
    client = running.client
    left, right = textured_pair(seed=11)
    assert running.set(approximate_sync=True, approximate_sync_tolerance_seconds=0.06).successful
    try:
        base = running.next_stamp()
        for index in range(20):  # 10 Hz: left images 0.1 s apart, pairs 0.12 s apart possible
            client.publish_frame(left, right, base + index * 100_000_000)
            if running.logged('at least half the frame period'):
                break
            time.sleep(0.05)
        assert client.wait_for(lambda: bool(running.logged('half the frame period')), 5.0)
        (line, *_) = running.logged('half the frame period')
        assert 'approximate_sync_tolerance_seconds = 0.06' in line and 'below 0.050' in line
    finally:
        assert running.set(approximate_sync=False).successful

"""``cva-bag-replay --compressed``: depth and overlay as image_transport's compressed transports,
as the node sends them, in place of the raw images (offline; live in test_bag_replay_live)."""

from __future__ import annotations

from dataclasses import asdict
import json
from pathlib import Path
import struct

import cv2
from msg_test_utils import MAX_DISPARITY, dataset_bag, read_bag
import numpy as np
import pytest

from cva_confidence_ros.ros.convert import depth_image_to_array, depth_to_image, image_to_array
from cva_confidence_ros.ros.transport import (
    compressed_depth_to_array,
    depth_image_to_compressed_depth,
    rgb_to_compressed,
)
from msg_tools.bag_replay import build_parser, main, options_from_args
from msg_tools.convert import stamp_to_ns
from msg_tools.live import node_arguments, recorded_outputs
from msg_tools.replay import CompressionConfig, TopicNames

PREFIX = '/stereo'
SCORED = {'disparity', 'confidence', 'disparity_filtered', 'points2', 'camera_info'}


def _replay(bag: Path, tmp_path: Path, name: str, *extra: str) -> tuple[int, dict]:
    code = main([
        str(bag), '--out', str(tmp_path / f'{name}_bag'), '--report', str(tmp_path / name),
        '--matcher', 'census_bm', '--max-disparity', str(MAX_DISPARITY),
        '--confidence-method', 'mlm', '--topic-prefix', PREFIX, *extra,
    ])
    report = tmp_path / name / 'report.json'
    return code, json.loads(report.read_text()) if report.exists() else {}


def _types(path: Path) -> dict[str, str]:
    """Topic → message type of a bag."""
    from rosbags.rosbag2 import Reader

    with Reader(path) as reader:
        return {conn.topic: conn.msgtype for conn in reader.connections}


def _raw_messages(path: Path) -> list[tuple[str, int, bytes]]:
    from rosbags.rosbag2 import Reader

    with Reader(path) as reader:
        return [(c.topic, t, bytes(d)) for c, t, d in reader.messages()]


def _size(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob('*') if f.is_file())


def _topics(*names: str) -> set[str]:
    return {f'{PREFIX}/{name}' for name in names}


def test_compressed_topics_replace_the_raw_ones(tmp_path: Path) -> None:
    bag = dataset_bag(tmp_path, 'mcap', 2, '--topic-prefix', PREFIX)
    code, _ = _replay(bag, tmp_path, 'raw', '--overlay')
    assert code == 0
    code, report = _replay(bag, tmp_path, 'packed', '--overlay', '--compressed')
    assert code == 0
    compressed = 'sensor_msgs/msg/CompressedImage'
    types = _types(tmp_path / 'packed_bag')
    assert set(types) == _topics(*SCORED, 'depth/compressedDepth', 'confidence_overlay/compressed')
    assert types[f'{PREFIX}/depth/compressedDepth'] == compressed
    assert types[f'{PREFIX}/confidence_overlay/compressed'] == compressed
    assert set(_types(tmp_path / 'raw_bag')) == _topics(*SCORED, 'depth', 'confidence_overlay')
    assert report['config']['compressed'] == asdict(CompressionConfig())
    assert report['config']['topics']['depth_compressed'] == f'{PREFIX}/depth/compressedDepth'

    # The other outputs are those of a raw run, byte for byte.
    same = _topics(*SCORED)
    assert [m for m in _raw_messages(tmp_path / 'raw_bag') if m[0] in same] == [
        m for m in _raw_messages(tmp_path / 'packed_bag') if m[0] in same]
    raw, packed = read_bag(tmp_path / 'raw_bag'), read_bag(tmp_path / 'packed_bag')
    pairs = zip(raw[f'{PREFIX}/depth'], packed[f'{PREFIX}/depth/compressedDepth'], strict=True)
    sent = 0
    for (time_raw, image), (time_packed, msg) in pairs:
        assert (time_raw, stamp_to_ns(image.header.stamp), image.header.frame_id) == (
            time_packed, stamp_to_ns(msg.header.stamp), msg.header.frame_id)
        assert msg.format == '32FC1; compressedDepth png'
        depth, decoded = depth_image_to_array(image), compressed_depth_to_array(msg)
        # Within the format's quantisation, z² / (q (q + 1)) with q = 100 (exactly: the code
        # is truncated, z² / (A − z) with A = q (q + 1)), up to 10 m; no depth (NaN) where the
        # raw depth has none or lies beyond.
        near = np.isfinite(depth) & (depth < 10.0) & (depth > 0.15)
        np.testing.assert_array_equal(np.isfinite(decoded), np.isfinite(depth) & (depth < 10.0))
        assert np.all(np.abs(decoded[near] - depth[near]) <= _bound(depth[near], 100.0))
        sent += int(near.sum())
        # The bytes are those the node sends for this depth image.
        again = depth_image_to_compressed_depth(
            depth_to_image(depth, _header(), '32FC1'), 10.0, 100.0, 3)
        assert bytes(msg.data) == bytes(again.data)
    assert sent > 500
    pairs = zip(raw[f'{PREFIX}/confidence_overlay'],
                packed[f'{PREFIX}/confidence_overlay/compressed'], strict=True)
    for (_, image), (_, msg) in pairs:
        assert msg.format == 'rgb8; jpeg compressed bgr8'
        overlay = image_to_array(image)
        bgr = cv2.imdecode(np.frombuffer(bytes(msg.data), np.uint8), cv2.IMREAD_COLOR)
        decoded = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        assert decoded.shape == overlay.shape
        # JPEG 95: the brightness within a few grey levels; the colour is sampled at half
        # resolution (4:2:0, as compressed_image_transport's OpenCV writes it), which costs
        # more on a tiny image tinted pixel by pixel: PSNR over the three channels.
        luma = [cv2.cvtColor(a, cv2.COLOR_RGB2GRAY).astype(float) for a in (decoded, overlay)]
        assert np.abs(luma[0] - luma[1]).mean() < 3.0
        mse = np.mean((decoded.astype(float) - overlay) ** 2)
        assert 10 * np.log10(255**2 / mse) > 22.0
        again = rgb_to_compressed(overlay, _header(), jpeg_quality=95)
        assert bytes(msg.data) == bytes(again.data)
    assert _size(tmp_path / 'packed_bag') < _size(tmp_path / 'raw_bag')


def _bound(depth: np.ndarray, q: float) -> np.ndarray:
    """The largest error of a 32FC1 compressedDepth of ``depth`` with quantisation ``q``: the
    truncated code gives back at most z² / (A − z), A = q (q + 1) (≈ z² / A), plus float32."""
    a = q * (q + 1.0)
    return depth.astype(float) ** 2 / (a - depth) * (1 + 1e-5) + 1e-6


def _header() -> object:
    from std_msgs.msg import Header

    return Header()


def test_compression_settings_and_16_bit_depth(tmp_path: Path) -> None:
    bag = dataset_bag(tmp_path, 'mcap', 1, '--topic-prefix', PREFIX)
    code, _ = _replay(bag, tmp_path, 'raw', '--overlay', '--depth-encoding', '16UC1')
    assert code == 0
    code, report = _replay(
        bag, tmp_path, 'packed', '--overlay', '--compressed', '--depth-encoding', '16UC1',
        '--jpeg-quality', '40', '--compressed-depth-max', '3', '--compressed-depth-png-level', '9',
    )
    assert code == 0
    assert report['config']['compressed'] == {
        'overlay_jpeg_quality': 40, 'compressed_depth_max': 3.0,
        'compressed_depth_quantization': 100.0, 'compressed_depth_png_level': 9,
    }
    raw, packed = read_bag(tmp_path / 'raw_bag'), read_bag(tmp_path / 'packed_bag')
    image, msg = raw[f'{PREFIX}/depth'][0][1], packed[f'{PREFIX}/depth/compressedDepth'][0][1]
    assert msg.format == '16UC1; compressedDepth png'
    depth = depth_image_to_array(image)
    kept = np.isfinite(depth) & (depth <= 3.0)
    assert 0 < kept.sum() < np.isfinite(depth).sum()  # some depths lie beyond 3 m
    decoded = compressed_depth_to_array(msg)
    # Millimetres travel as they are, those beyond 3 m as no depth.
    np.testing.assert_array_equal(np.isfinite(decoded), kept)
    np.testing.assert_array_equal(decoded[kept], depth[kept])
    # 32FC1 with another quantisation and depth_max: its A and B in the header, its error.
    code, _ = _replay(bag, tmp_path, 'raw32')
    assert code == 0
    code, _ = _replay(bag, tmp_path, 'coarse', '--compressed', '--compressed-depth-quantization',
                      '20', '--compressed-depth-max', '4')
    assert code == 0
    msg = read_bag(tmp_path / 'coarse_bag')[f'{PREFIX}/depth/compressedDepth'][0][1]
    kind, a, b = struct.unpack_from('<iff', bytes(msg.data))
    assert (kind, a, b) == (0, pytest.approx(20 * 21), pytest.approx(1 - 20 * 21 / 4))
    metres = depth_image_to_array(read_bag(tmp_path / 'raw32_bag')[f'{PREFIX}/depth'][0][1])
    decoded = compressed_depth_to_array(msg)
    sent = np.isfinite(metres) & (metres < 4.0)
    np.testing.assert_array_equal(np.isfinite(decoded), sent)
    error = np.abs(decoded[sent] - metres[sent])
    assert np.all(error <= _bound(metres[sent], 20.0)) and error.max() > 1e-2
    jpeg = packed[f'{PREFIX}/confidence_overlay/compressed'][0][1]
    overlay = image_to_array(raw[f'{PREFIX}/confidence_overlay'][0][1])
    assert bytes(jpeg.data) == bytes(rgb_to_compressed(overlay, _header(), jpeg_quality=40).data)


@pytest.mark.parametrize(
    ('option', 'value', 'message'),
    [
        ('--jpeg-quality', '0', 'overlay_jpeg_quality must be an integer in [1, 100]; got 0'),
        ('--jpeg-quality', '101', 'overlay_jpeg_quality must be an integer in [1, 100]'),
        ('--compressed-depth-max', '0', 'compressed_depth_max must be a number in [0.001, '),
        ('--compressed-depth-max', 'nan', 'compressed_depth_max must be a number in'),
        ('--compressed-depth-max', 'inf', 'compressed_depth_max must be a number in'),
        ('--compressed-depth-quantization', '-1', 'compressed_depth_quantization must be a '),
        ('--compressed-depth-quantization', 'nan', 'compressed_depth_quantization must be a '),
        ('--compressed-depth-png-level', '10', 'compressed_depth_png_level must be an integer in '
                                               '[0, 9]; got 10'),
        ('--compressed-depth-png-level', '-1', 'compressed_depth_png_level must be an integer'),
    ],
)
def test_bad_compression_values_are_refused_naming_the_option(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], option: str, value: str, message: str
) -> None:
    # Refused before anything is read or written, with or without --compressed (a bad value
    # is a mistake either way), on one line that names the option and the node parameter.
    for extra in (('--compressed',), ()):
        code = main([str(tmp_path / 'missing_bag'), '--out', str(tmp_path / 'out'),
                     '--report', str(tmp_path / 'report'), *extra, option, value])
        assert code == 2
        err = capsys.readouterr().err
        assert err.count('\n') == 1
        assert err.startswith(f'cva-bag-replay: error: {option}: {message}'), err
    assert not (tmp_path / 'out').exists() and not (tmp_path / 'report').exists()


def test_compression_defaults_are_the_nodes() -> None:
    from cva_confidence_ros.ros.params import NodeConfig

    node, ours = asdict(NodeConfig()), asdict(CompressionConfig())
    assert ours == {name: node[name] for name in ours}
    # An integer depth_max is the number, as the node takes a double parameter.
    assert CompressionConfig(compressed_depth_max=20).compressed_depth_max == 20.0


def test_live_subscribes_to_the_compressed_topics_and_sets_the_node_parameters(
    tmp_path: Path,
) -> None:
    args = build_parser().parse_args([
        str(tmp_path / 'in'), '--mode', 'live', '--out', str(tmp_path / 'out'),
        '--report', str(tmp_path / 'report'), '--topic-prefix', PREFIX, '--overlay',
        '--compressed', '--jpeg-quality', '80', '--compressed-depth-max', '20',
    ])
    options = options_from_args(args)
    assert recorded_outputs(options) == [
        'disparity', 'confidence', 'disparity_filtered', 'points', 'camera_info',
        'depth_compressed', 'overlay_compressed',
    ]
    argv = node_arguments(options, 'replayed')
    params = {argv[i + 1] for i, a in enumerate(argv) if a == '-p'}
    remaps = {argv[i + 1] for i, a in enumerate(argv) if a == '-r'}
    assert {'overlay_jpeg_quality:=80', 'compressed_depth_max:=20.0',
            'compressed_depth_quantization:=100.0', 'compressed_depth_png_level:=3'} <= params
    assert {f'depth/compressedDepth:={PREFIX}/depth/compressedDepth',
            f'confidence_overlay/compressed:={PREFIX}/confidence_overlay/compressed',
            f'depth:={PREFIX}/depth'} <= remaps
    # Without --compressed the raw topics; without --overlay and --no-depth neither.
    raw = options_from_args(build_parser().parse_args([
        str(tmp_path / 'in'), '--out', str(tmp_path / 'out'), '--report', str(tmp_path / 'r'),
        '--overlay']))
    assert recorded_outputs(raw)[-3:] == ['depth', 'overlay', 'camera_info']
    bare = options_from_args(build_parser().parse_args([
        str(tmp_path / 'in'), '--out', str(tmp_path / 'out'), '--report', str(tmp_path / 'r'),
        '--compressed', '--no-depth']))
    assert not {'depth', 'overlay', 'depth_compressed', 'overlay_compressed'} & set(
        recorded_outputs(bare))


def test_compressed_topics_follow_renamed_outputs() -> None:
    names = TopicNames(prefix='/cam', depth='depth_registered', overlay='/viz/overlay')
    outputs = names.outputs()
    assert outputs['depth_compressed'] == '/cam/depth_registered/compressedDepth'
    assert outputs['overlay_compressed'] == '/viz/overlay/compressed'

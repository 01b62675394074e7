"""``cva-bag-replay`` offline: data set → bag → replay → output bag and report."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import cv2
from msg_test_utils import (
    DOFFS,
    MAX_DISPARITY,
    dataset_bag,
    read_bag,
    textured_pair,
    write_stereo_bag,
)
import numpy as np
import pytest

from cva_confidence_ros.confidence import CONFIDENCE_METHODS
from cva_confidence_ros.datasets import load_dataset, resize_disparity
from cva_confidence_ros.evaluation import evaluate_scene
from cva_confidence_ros.pointcloud import StereoGeometry
from cva_confidence_ros.ros.convert import (
    depth_image_to_array,
    disparity_from_message,
    float_image_to_array,
)
from msg_tools.bag_replay import main
from msg_tools.convert import stamp_to_ns
from msg_tools.scoring import REPORT_KEYS

OUTPUTS = {
    '/disparity', '/confidence', '/disparity_filtered', '/points2', '/depth', '/camera_info'
}


def _replay(bag: Path, tmp_path: Path, *extra: str, name: str = 'run') -> tuple[int, dict]:
    code = main([
        str(bag), '--out', str(tmp_path / f'{name}_bag'), '--report', str(tmp_path / name),
        '--matcher', 'census_bm', '--max-disparity', str(MAX_DISPARITY),
        '--confidence-method', 'mlm', *extra,
    ])
    report_file = tmp_path / name / 'report.json'
    report = json.loads(report_file.read_text()) if report_file.exists() else {}
    return code, report


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_round_trip(tmp_path: Path, storage: str, capsys: pytest.CaptureFixture[str]) -> None:
    bag = dataset_bag(tmp_path, storage, 2)
    code, report = _replay(bag, tmp_path, '--storage', storage)
    assert code == 0
    captured = capsys.readouterr()
    assert f'report {tmp_path / "run" / "report.json"}' in captured.out
    assert 'offline: 2/2 frames' in captured.err  # progress with frames and rate

    frames = report['frames']
    assert [f['frame'] for f in frames] == [0, 1]
    assert all(list(f)[: len(REPORT_KEYS)] == list(REPORT_KEYS) for f in frames)
    summary = report['summary']
    for key in ('error_rate', 'auc', 'auc_opt', 'kept_density'):
        assert summary[key] == pytest.approx(np.mean([f[key] for f in frames]))
        assert all(0.0 <= f[key] <= 1.0 for f in frames)
    assert all(f['auc'] >= f['auc_opt'] - 1e-12 for f in frames)
    assert (summary['pairs'], summary['processed'], summary['skipped']) == (2, 2, 0)
    assert summary['interrupted'] is False and summary['error'] is None

    with (tmp_path / 'run' / 'report.csv').open() as stream:
        rows = list(csv.DictReader(stream))
    assert [float(r['auc']) for r in rows] == [f['auc'] for f in frames]
    summary_md = (tmp_path / 'run' / 'summary.md').read_text()
    assert '| frames | scored |' in summary_md
    assert '- speckle_size: 100' in summary_md and '- subpixel: equiangular' in summary_md
    assert report['config']['speckle_range'] == 1.0
    for png in ('auc_over_time.png', 'confidence_00000.png', 'roc_00001.png'):
        assert (tmp_path / 'run' / png).read_bytes()[:4] == b'\x89PNG'

    inputs = read_bag(bag)
    outputs = read_bag(tmp_path / 'run_bag')
    assert set(outputs) == OUTPUTS
    assert f'storage_identifier: {storage}' in (tmp_path / 'run_bag' / 'metadata.yaml').read_text()
    for topic in OUTPUTS:
        # Stamped like the input: same header stamps, frame ids and bag timestamps.
        assert [(t, stamp_to_ns(m.header.stamp), m.header.frame_id) for t, m in outputs[topic]] \
            == [(t, stamp_to_ns(m.header.stamp), m.header.frame_id)
                for t, m in inputs['/left/image_rect']]
    for index, (_, msg) in enumerate(outputs['/disparity']):
        width = inputs['/left/image_rect'][index][1].width
        assert msg.image.width == width and msg.min_disparity == pytest.approx(DOFFS)
        confidence = float_image_to_array(outputs['/confidence'][index][1])
        kept = np.isfinite(disparity_from_message(outputs['/disparity_filtered'][index][1]))
        assert confidence.min() >= 0.0 and confidence.max() <= 1.0
        assert kept.mean() == pytest.approx(frames[index]['kept_density'])
        assert not np.any(kept & (confidence < 0.5))  # the speckle filter only drops more
        assert outputs['/points2'][index][1].width == width  # organised cloud
        # depth: Z = f·T / value of the filtered DisparityImage (its values are d + Δ), on
        # exactly its kept pixels; camera_info: the left camera at the output size.
        filtered = outputs['/disparity_filtered'][index][1]
        depth = depth_image_to_array(outputs['/depth'][index][1])
        np.testing.assert_array_equal(np.isfinite(depth), kept)
        np.testing.assert_allclose(
            depth[kept], filtered.f * filtered.t / disparity_from_message(filtered)[kept],
            rtol=1e-5,
        )
        info = outputs['/camera_info'][index][1]
        assert (info.width, info.height) == (width, msg.image.height)
        assert info.p[0] == pytest.approx(filtered.f)
        np.testing.assert_allclose(info.p, inputs['/left/camera_info'][index][1].p)


def test_auc_equals_cva_evaluate(tmp_path: Path) -> None:
    # cva-evaluate scores the integer winner-takes-all disparity (the paper's protocol).
    bag = dataset_bag(tmp_path, 'mcap', 2)
    code, report = _replay(bag, tmp_path, '--subpixel', 'none')
    assert code == 0
    code, subset = _replay(
        bag, tmp_path, '--subpixel', 'none', '--max-pixels', '300', '--seed', '7', name='subset'
    )
    assert code == 0
    method = CONFIDENCE_METHODS.get('mlm')(matcher='census_bm', max_disparity=MAX_DISPARITY)
    samples = list(load_dataset('middlebury2014', tmp_path / 'data'))
    for frame, sub, sample in zip(report['frames'], subset['frames'], samples, strict=True):
        for record, pixels in ((frame, None), (sub, 300)):
            [expected] = evaluate_scene(
                sample, 'census_bm', {'mlm': method}, max_disparity=MAX_DISPARITY,
                max_pixels=pixels, seed=7,
            )
            assert record['auc'] == pytest.approx(expected.auc, abs=1e-9)
            assert record['auc_opt'] == pytest.approx(expected.auc_opt, abs=1e-9)
            assert record['error_rate'] == pytest.approx(expected.error_rate, abs=1e-9)
            assert record['n_pixels'] == expected.n_pixels
    assert {f['n_pixels'] for f in subset['frames']} == {300}


def test_points_confidence_writes_every_point_with_its_confidence(tmp_path: Path) -> None:
    from cva_confidence_ros.pointcloud import CLOUD_CONFIDENCE_DTYPE, filter_cloud

    bag = dataset_bag(tmp_path, 'mcap', 1)
    # The confidence field is all a consumer has to cut by: the speckle filter (on by
    # default) is a decision of the node's own kept pixels, so it is off here for the check.
    code, _ = _replay(bag, tmp_path, '--points-confidence', '--speckle-size', '0')
    assert code == 0
    outputs = read_bag(tmp_path / 'run_bag')
    msg = outputs['/points2'][0][1]
    assert [f.name for f in msg.fields] == ['x', 'y', 'z', 'rgb', 'confidence']
    assert msg.point_step == 20
    cloud = np.frombuffer(bytes(msg.data), CLOUD_CONFIDENCE_DTYPE).reshape(msg.height, msg.width)
    confidence = float_image_to_array(outputs['/confidence'][0][1])
    disparity = disparity_from_message(outputs['/disparity'][0][1])
    triangulable = np.isfinite(disparity) & (disparity > 0)
    np.testing.assert_array_equal(np.isfinite(cloud['z']), triangulable)
    np.testing.assert_array_equal(cloud['confidence'][triangulable], confidence[triangulable])
    # Cut at the node's threshold, it is the cloud the node keeps: disparity_filtered's pixels.
    kept = np.isfinite(disparity_from_message(outputs['/disparity_filtered'][0][1]))
    from cva_confidence_ros.pipeline import PipelineConfig

    threshold = PipelineConfig().confidence_threshold  # cva-bag-replay's default
    np.testing.assert_array_equal(
        np.isfinite(filter_cloud(cloud, threshold)['z']), kept & triangulable
    )


def test_overlay_is_the_kept_pixels_coloured_over_the_scene(tmp_path: Path) -> None:
    # --overlay: confidence_overlay (rgb8) of the processed left image, the published confidence
    # and disparity_filtered's kept pixels; not written without the flag (test_round_trip).
    from cva_confidence_ros.datasets.resize import resize_image
    from cva_confidence_ros.plots import confidence_overlay
    from cva_confidence_ros.ros.convert import image_to_array

    bag = dataset_bag(tmp_path, 'mcap', 2)
    code, report = _replay(bag, tmp_path, '--overlay', '--downsample', '2')
    assert code == 0
    assert report['config']['topics']['overlay'] == '/confidence_overlay'
    inputs, outputs = read_bag(bag), read_bag(tmp_path / 'run_bag')
    assert set(outputs) == OUTPUTS | {'/confidence_overlay'}
    for index, (_, msg) in enumerate(outputs['/confidence_overlay']):
        assert msg.encoding == 'rgb8'
        assert msg.header.stamp == outputs['/confidence'][index][1].header.stamp
        left = resize_image(image_to_array(inputs['/left/image_rect'][index][1]), 2)
        confidence = float_image_to_array(outputs['/confidence'][index][1])
        kept = np.isfinite(disparity_from_message(outputs['/disparity_filtered'][index][1]))
        np.testing.assert_array_equal(
            image_to_array(msg), confidence_overlay(left, confidence, kept)
        )


def test_scan_is_the_laser_scan_of_the_kept_pixels(tmp_path: Path) -> None:
    # --scan: a LaserScan per frame in the body frame beside the camera's optical frame, equal
    # to disparity_to_scan of the written disparity and kept pixels with the given band.
    from cva_confidence_ros.pointcloud import StereoGeometry
    from cva_confidence_ros.scan import ScanConfig, disparity_to_scan, score_scan

    bag = dataset_bag(tmp_path, 'mcap', 2)
    code, report = _replay(bag, tmp_path, '--scan', '--scan-height', '-5', '5',
                           '--scan-range', '0.05', '50')
    assert code == 0
    assert report['config']['topics']['scan'] == '/scan'
    inputs, outputs = read_bag(bag), read_bag(tmp_path / 'run_bag')
    assert set(outputs) == OUTPUTS | {'/scan'}
    config = ScanConfig(min_height=-5.0, max_height=5.0, range_min=0.05, range_max=50.0)
    for index, (_, msg) in enumerate(outputs['/scan']):
        left_info = inputs['/left/camera_info'][index][1]
        right_info = inputs['/right/camera_info'][index][1]
        assert msg.header.frame_id == 'left_camera_frame'  # beside left_camera_optical_frame
        assert msg.header.stamp == outputs['/disparity'][index][1].header.stamp
        geometry = StereoGeometry.from_projections(left_info.p, right_info.p)
        disparity = disparity_from_message(outputs['/disparity'][index][1])
        disparity -= geometry.disparity_offset  # the message holds d + Δ
        kept = np.isfinite(disparity_from_message(outputs['/disparity_filtered'][index][1]))
        confidence = float_image_to_array(outputs['/confidence'][index][1])
        expected = disparity_to_scan(disparity, geometry, kept, confidence, config)
        np.testing.assert_allclose(msg.ranges, expected.ranges, rtol=1e-5)
        np.testing.assert_allclose(msg.intensities, expected.intensities, rtol=1e-6)
        assert np.isfinite(msg.ranges).mean() > 0.5
        assert (msg.range_min, msg.range_max) == pytest.approx((0.05, 50.0))
        # Scored against the ground truth's scan: the kept pixels with ground truth, the same
        # pixels of the ground truth (the data set's, at its stamp).
        gt = disparity_from_message(inputs['/ground_truth/disparity'][index][1])
        gt -= geometry.disparity_offset
        known = np.isfinite(gt)
        scored = score_scan(
            disparity_to_scan(disparity, geometry, kept & known, confidence, config),
            disparity_to_scan(gt, geometry, known, None, config), geometry, config,
        )
        record = report['frames'][index]
        assert record['scan_beams'] == scored.beams > 10
        for outcome in ('phantom', 'far', 'none'):
            assert record[f'scan_{outcome}_rate'] == pytest.approx(scored.rate(outcome))
    beams = [f['scan_beams'] for f in report['frames']]
    assert report['summary']['scan_beams'] == sum(beams)
    assert report['summary']['scan_phantom_rate'] == pytest.approx(
        sum(f['scan_phantom_rate'] * f['scan_beams'] for f in report['frames']) / sum(beams))
    assert 'Laser scan (`--scan`) of the kept pixels with ground truth' in (
        tmp_path / 'run' / 'summary.md').read_text()
    # Without --scan, no scan score.
    code, plain = _replay(bag, tmp_path, name='plain')
    assert code == 0 and plain['summary']['scan_beams'] is None
    assert {f['scan_beams'] for f in plain['frames']} == {None}


def test_depth_encoding_and_no_depth(tmp_path: Path) -> None:
    bag = dataset_bag(tmp_path, 'mcap', 1)
    code, _ = _replay(bag, tmp_path, '--depth-encoding', '16UC1', '--downsample', '2')
    assert code == 0
    outputs = read_bag(tmp_path / 'run_bag')
    msg = outputs['/depth'][0][1]
    assert (msg.encoding, msg.step) == ('16UC1', 2 * msg.width)
    millimetres = np.frombuffer(bytes(msg.data), '<u2').reshape(msg.height, msg.width)
    # The same depth as the points' z (the kept pixels), in whole millimetres, 0 elsewhere.
    cloud = outputs['/points2'][0][1]
    z = np.frombuffer(bytes(cloud.data), '<f4').reshape(cloud.height, cloud.width, 4)[..., 2]
    np.testing.assert_array_equal(millimetres > 0, np.isfinite(z))
    np.testing.assert_allclose(millimetres[millimetres > 0], z[np.isfinite(z)] * 1000, atol=0.5)
    info = outputs['/camera_info'][0][1]
    assert (info.width, info.height) == (msg.width, msg.height)

    code, _ = _replay(bag, tmp_path, '--no-depth', name='none')
    assert code == 0
    assert set(read_bag(tmp_path / 'none_bag')) == OUTPUTS - {'/depth'}


def test_downsample_scales_ground_truth(tmp_path: Path) -> None:
    bag = dataset_bag(tmp_path, 'mcap', 2)
    code, report = _replay(bag, tmp_path, '--downsample', '2')
    assert code == 0
    samples = list(load_dataset('middlebury2014', tmp_path / 'data'))
    for record, sample in zip(report['frames'], samples, strict=True):
        height, width = sample.disparity.shape
        assert (record['width'], record['height']) == (width // 2, height // 2)
        # Every pixel the data sets' NaN-aware halving keeps is scored.
        assert record['n_pixels'] == int(np.isfinite(resize_disparity(sample.disparity, 2)).sum())
        assert record['auc'] is not None


def test_ground_truth_at_the_output_size_is_read_with_its_own_offset(tmp_path: Path) -> None:
    # Camera infos with Δ = cx_right − cx_left = 6 px. A DisparityImage holds d + Δ at its own
    # resolution: one at the output size of --downsample 2 holds d/2 + 3, not d/2 + 6. It is
    # the same ground truth as the input-size one (4 px, the 4 left columns unknown) halved.
    geometry = StereoGeometry(fx=50.0, fy=50.0, cx=20.0, cy=15.0, cx_right=26.0, baseline=0.1)
    half = np.full((15, 20), 2.0, np.float32)
    half[:, :2] = np.nan
    frames = [dict(zip(('left', 'right'), textured_pair(30, 40, 4, seed), strict=True))
              for seed in range(2)]
    scored = {}
    for name, extra in (('input_size', {}), ('output_size', {'gt': half, 'gt_scale': 0.5})):
        bag = write_stereo_bag(tmp_path / f'in_{name}', [{**frame, **extra} for frame in frames],
                               geometry=geometry)
        gt_msg = read_bag(bag)['/ground_truth/disparity'][0][1]
        assert gt_msg.min_disparity == (3.0 if extra else 6.0)
        code, report = _replay(bag, tmp_path, '--downsample', '2', name=name)
        assert code == 0
        scored[name] = [(f['n_pixels'], f['error_rate'], f['auc'], f['auc_opt'])
                        for f in report['frames']]
    assert scored['output_size'] == scored['input_size']
    assert all(n_pixels == 15 * 18 and error < 0.05
               for n_pixels, error, _, _ in scored['output_size'])


def test_downsample_of_an_odd_size_scales_geometry_as_the_node(tmp_path: Path) -> None:
    # 41×31 px at downsample 2: cropped to 40×30, then halved exactly, as the node does (and
    # as camera_info says), not scaled by 20/41 and 15/31.
    frames = [dict(zip(('left', 'right'), textured_pair(31, 41, 4, i), strict=True))
              for i in range(2)]
    bag = write_stereo_bag(tmp_path / 'in', frames)
    code, _ = _replay(bag, tmp_path, '--downsample', '2', '--max-disparity', '8')
    assert code == 0
    node = StereoGeometry(fx=50.0, fy=50.0, cx=20.0, cy=15.0, cx_right=20.0,
                          baseline=0.1).scaled(0.5)
    outputs = read_bag(tmp_path / 'run_bag')
    for (_, disparity), (_, info), (_, depth) in zip(
        outputs['/disparity'], outputs['/camera_info'], outputs['/depth'], strict=True
    ):
        assert (disparity.image.width, disparity.image.height) == (info.width, info.height)
        assert disparity.f == pytest.approx(node.fx) == info.p[0] == 25.0
        assert info.p[2] == pytest.approx(node.cx)
        raw = disparity_from_message(disparity)
        metres = depth_image_to_array(depth)
        known = np.isfinite(metres)
        assert known.any()
        assert np.allclose(metres[known] * raw[known], node.fx * node.baseline)


def test_topic_prefix_and_bag_without_ground_truth(tmp_path: Path) -> None:
    bag = write_stereo_bag(tmp_path / 'in', [{}, {}], prefix='/stereo', ground_truth=False)
    code, report = _replay(bag, tmp_path, '--topic-prefix', '/stereo', '--no-points')
    assert code == 0
    assert [f['auc'] for f in report['frames']] == [None, None]
    assert report['frames'][0]['note'] == 'no ground truth'
    assert set(read_bag(tmp_path / 'run_bag')) == {
        '/stereo/disparity', '/stereo/confidence', '/stereo/disparity_filtered',
        '/stereo/depth', '/stereo/camera_info',
    }
    # Asking for a ground truth the bag does not have is an error.
    code, _ = _replay(bag, tmp_path, '--topic-prefix', '/stereo', '--gt-topic', 'gt', name='b')
    assert code == 2


def _raw_messages(path: Path) -> list[tuple[str, int, bytes]]:
    from rosbags.rosbag2 import Reader

    with Reader(path) as reader:
        return [(c.topic, t, bytes(d)) for c, t, d in reader.messages()]


def test_offline_is_deterministic(tmp_path: Path) -> None:
    bag = write_stereo_bag(tmp_path / 'in', [{'shift': 3}, {'shift': 5}])
    assert _replay(bag, tmp_path, name='a')[0] == 0
    assert _replay(bag, tmp_path, name='b')[0] == 0
    assert _raw_messages(tmp_path / 'a_bag') == _raw_messages(tmp_path / 'b_bag')
    first = read_bag(tmp_path / 'a_bag')
    # A constant shift on random texture is found where the texture is visible (the integer
    # exactly; the sub-pixel curve moves it by less than half a pixel).
    disparity = disparity_from_message(first['/disparity'][1][1])
    assert np.all(np.abs(disparity[4:-4, 5 + 4 : -4] - 5) < 0.5)


@pytest.mark.parametrize(('storage', 'compression'), [('sqlite3', 'message'), ('mcap', 'file')])
def test_compressed_bags(tmp_path: Path, storage: str, compression: str) -> None:
    bag = dataset_bag(tmp_path, storage, 2, '--compression', compression)
    metadata = (bag / 'metadata.yaml').read_text()
    assert f'compression_mode: {compression}' in metadata
    assert 'compression_format: zstd' in metadata
    code, report = _replay(bag, tmp_path)
    assert code == 0
    assert report['summary']['processed'] == 2 and report['summary']['frames_scored'] == 2


def test_compressed_images_replay_like_raw_ones(tmp_path: Path) -> None:
    # image_transport's compressed topics (PNG is lossless: the same outputs as the raw bag)
    frames = [{'shift': 3}, {'shift': 5}]
    raw = write_stereo_bag(tmp_path / 'raw', frames)
    png = write_stereo_bag(tmp_path / 'png', [{**f, 'transport': 'png'} for f in frames])
    assert _replay(raw, tmp_path, name='raw_out')[0] == 0
    topics = ('--left-topic', 'left/image_rect/compressed',
              '--right-topic', 'right/image_rect/compressed')  # fmt: skip
    code, report = _replay(png, tmp_path, *topics, name='png_out')
    assert code == 0 and report['summary']['processed'] == 2
    from_raw, from_png = read_bag(tmp_path / 'raw_out_bag'), read_bag(tmp_path / 'png_out_bag')
    pairs = zip(from_raw['/disparity'], from_png['/disparity'], strict=True)
    for (_, expected), (_, got) in pairs:
        assert np.array_equal(disparity_from_message(got), disparity_from_message(expected))
    # JPEG is lossy, but a textured pair still matches almost everywhere.
    jpeg = write_stereo_bag(tmp_path / 'jpeg', [{**f, 'transport': 'jpeg'} for f in frames])
    code, report = _replay(jpeg, tmp_path, *topics, name='jpeg_out')
    assert code == 0 and report['summary']['processed'] == 2
    disparity = disparity_from_message(read_bag(tmp_path / 'jpeg_out_bag')['/disparity'][1][1])
    assert np.mean(np.abs(disparity[4:-4, 5 + 4 : -4] - 5) < 0.5) > 0.9


def test_a_compressed_image_that_does_not_decode_is_skipped(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    frames = [{'transport': 'png'}, {'transport': 'png', 'compressed_data': b'not an image'},
              {'transport': 'png'}]  # fmt: skip
    bag = write_stereo_bag(tmp_path / 'in', frames)
    code, report = _replay(bag, tmp_path, '--left-topic', 'left/image_rect/compressed',
                           '--right-topic', 'right/image_rect/compressed')  # fmt: skip
    assert code == 0
    summary = report['summary']
    assert (summary['pairs'], summary['processed'], summary['skipped']) == (3, 2, 1)
    err = capsys.readouterr().err
    assert 'skipped frame 1' in err and 'is neither a JPEG nor a PNG' in err


def test_a_network_reports_the_error_it_predicts_for_the_kept_pixels(tmp_path: Path) -> None:
    torch = pytest.importorskip('torch')
    from cva_confidence_ros.model import CVANet, save_weights

    bag = dataset_bag(tmp_path, 'mcap', 2)
    # MLM's values are no probabilities: no prediction, an empty CSV cell.
    code, report = _replay(bag, tmp_path, name='mlm')
    assert code == 0
    assert [f['expected_kept_error'] for f in report['frames']] == [None, None]
    assert [f['predicted_kept_error'] for f in report['frames']] == [None, None]
    assert report['summary']['expected_kept_error'] is None
    with (tmp_path / 'mlm' / 'report.csv').open() as stream:
        assert {row['expected_kept_error'] for row in csv.DictReader(stream)} == {''}

    torch.manual_seed(0)
    weights = tmp_path / 'random.pt'
    save_weights(CVANet(MAX_DISPARITY), weights, {'matcher': 'census_bm'})
    code = main([
        str(bag), '--out', str(tmp_path / 'net_bag'), '--report', str(tmp_path / 'net'),
        '--matcher', 'census_bm', '--max-disparity', str(MAX_DISPARITY),
        '--confidence-method', 'cva_net', '--weights', str(weights),
        '--confidence-threshold', '0.3',
    ])
    assert code == 0
    report = json.loads((tmp_path / 'net' / 'report.json').read_text())
    outputs = read_bag(tmp_path / 'net_bag')
    samples = list(load_dataset('middlebury2014', tmp_path / 'data'))
    for index, (frame, sample) in enumerate(zip(report['frames'], samples, strict=True)):
        confidence = float_image_to_array(outputs['/confidence'][index][1]).astype(np.float64)
        kept = np.isfinite(disparity_from_message(outputs['/disparity_filtered'][index][1]))
        scored = kept & np.isfinite(sample.disparity)
        assert scored.any()
        # mean(1 − confidence) over the scored kept pixels: the pixels of kept_error_rate.
        assert frame['expected_kept_error'] == pytest.approx(1.0 - confidence[scored].mean())
        # ... and over every kept pixel, ground truth or not (what /diagnostics says).
        assert frame['predicted_kept_error'] == pytest.approx(1.0 - confidence[kept].mean())
    assert report['summary']['expected_kept_error'] == pytest.approx(
        np.mean([f['expected_kept_error'] for f in report['frames']])
    )
    assert '| expected kept error % |' in (tmp_path / 'net' / 'summary.md').read_text()


def test_kept_epe_is_the_mean_disparity_error_of_the_kept_pixels(tmp_path: Path) -> None:
    # Synthetic slanted planes: sub-pixel ground truth, which the sub-pixel disparity follows
    # more closely than the integers do.
    bag = dataset_bag(tmp_path, 'mcap', 2)
    samples = list(load_dataset('middlebury2014', tmp_path / 'data'))
    epe = {}
    for subpixel in ('equiangular', 'none'):
        code, report = _replay(bag, tmp_path, '--subpixel', subpixel, name=subpixel)
        assert code == 0
        outputs = read_bag(tmp_path / f'{subpixel}_bag')
        for index, (frame, sample) in enumerate(zip(report['frames'], samples, strict=True)):
            msg = outputs['/disparity_filtered'][index][1]
            # The message holds d + Δ (Δ = cx_right − cx_left, its min_disparity); scored is d.
            filtered = disparity_from_message(msg) - np.float32(msg.min_disparity)
            scored = np.isfinite(filtered) & np.isfinite(sample.disparity)
            expected = np.abs(filtered[scored] - sample.disparity[scored]).mean()
            assert frame['kept_epe'] == pytest.approx(expected, rel=1e-6)
        epe[subpixel] = report['summary']['kept_epe']
        assert epe[subpixel] == pytest.approx(np.mean([f['kept_epe'] for f in report['frames']]))
        with (tmp_path / subpixel / 'report.csv').open() as stream:
            rows = list(csv.DictReader(stream))
        assert [float(row['kept_epe']) for row in rows] == pytest.approx(
            [f['kept_epe'] for f in report['frames']]
        )
        assert '| kept EPE px |' in (tmp_path / subpixel / 'summary.md').read_text()
    assert epe['equiangular'] < epe['none']


def test_a_robot_bag_without_ground_truth_gets_statistics_and_pictures(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # A robot's own bag has no ground truth: every frame still gets the node's /diagnostics
    # numbers (kept share, mean confidence), and the report PNGs a person looks at: overlays
    # of frames spread over the bag, the kept share over time, and the frame kept least.
    from cva_confidence_ros.datasets.resize import resize_image
    from cva_confidence_ros.plots import confidence_overlay
    from cva_confidence_ros.ros.convert import image_to_array

    flat = np.full((30, 40), 128, np.uint8)  # no texture: nothing to trust
    frames: list[dict] = [{}, {'shift': 3}, {}, {'left': flat, 'right': flat}, {}]
    bag = write_stereo_bag(tmp_path / 'in', frames, ground_truth=False)
    capsys.readouterr()
    code, report = _replay(bag, tmp_path, '--max-plots', '2', '--downsample', '2')
    assert code == 0
    inputs, outputs = read_bag(bag), read_bag(tmp_path / 'run_bag')
    kept_shares = []
    for index, record in enumerate(report['frames']):
        assert record['auc'] is None and record['note'] == 'no ground truth'
        confidence = float_image_to_array(outputs['/confidence'][index][1])
        disparity = disparity_from_message(outputs['/disparity'][index][1])
        kept = np.isfinite(disparity_from_message(outputs['/disparity_filtered'][index][1]))
        assert record['kept_fraction'] == pytest.approx(kept.mean())
        has = np.isfinite(disparity)
        assert record['mean_confidence'] == pytest.approx(confidence[has].mean(), rel=1e-5)
        assert record['predicted_kept_error'] is None  # MLM is no probability
        kept_shares.append(kept.mean())
    assert kept_shares[3] < min(kept_shares[:3] + kept_shares[4:])
    summary = report['summary']
    assert summary['kept_fraction'] == pytest.approx(np.mean(kept_shares))
    assert (summary['min_kept_fraction'], summary['min_kept_fraction_frame']) == (
        pytest.approx(kept_shares[3]), 3
    )

    folder = tmp_path / 'run'
    # Five frames, two plots: frames 0 and 3 (every third), no ROC without ground truth.
    pngs = sorted(p.name for p in folder.glob('*.png'))
    assert pngs == [
        'confidence_00000.png', 'confidence_00003.png', 'confidence_over_time.png',
        'least_kept_00003.png', 'overlay_00000.png', 'overlay_00003.png',
    ]
    for index, name in ((0, 'overlay_00000.png'), (3, 'overlay_00003.png'),
                        (3, 'least_kept_00003.png')):
        left = resize_image(image_to_array(inputs['/left/image_rect'][index][1]), 2)
        confidence = float_image_to_array(outputs['/confidence'][index][1])
        kept = np.isfinite(disparity_from_message(outputs['/disparity_filtered'][index][1]))
        written = cv2.cvtColor(cv2.imread(str(folder / name)), cv2.COLOR_BGR2RGB)
        np.testing.assert_array_equal(written, confidence_overlay(left, confidence, kept))
    summary_md = (folder / 'summary.md').read_text()
    assert 'no ground truth needed' in summary_md
    assert f'| {100 * kept_shares[3]:.2f} (frame 3) |' in summary_md
    out = capsys.readouterr().out
    assert f'kept {100 * np.mean(kept_shares):.1f} % of the pixels (least ' \
        f'{100 * kept_shares[3]:.1f} % in frame 3)' in out


def test_region_of_interest_as_the_node(tmp_path: Path) -> None:
    # --roi TOP BOTTOM: the node's roi_top / roi_bottom; the report's kept share is that of the
    # region, as /diagnostics gives it.
    bag = write_stereo_bag(tmp_path / 'in', [{}, {}], ground_truth=False)
    code, report = _replay(bag, tmp_path, '--roi', '0.2', '0.7')
    assert code == 0
    assert (report['config']['roi_top'], report['config']['roi_bottom']) == (0.2, 0.7)
    outputs = read_bag(tmp_path / 'run_bag')
    for index, record in enumerate(report['frames']):
        disparity = disparity_from_message(outputs['/disparity'][index][1])
        kept = np.isfinite(disparity_from_message(outputs['/disparity_filtered'][index][1]))
        assert disparity.shape == (30, 40)
        # Rows 6 to 21 of 30: floor(0.2 · 30), ceil(0.7 · 30).
        assert np.isnan(disparity[:6]).all() and np.isnan(disparity[21:]).all()
        assert np.isfinite(disparity[6:21]).any()
        assert record['kept_fraction'] == pytest.approx(kept[6:21].mean())
    assert '- roi_top: 0.2' in (tmp_path / 'run' / 'summary.md').read_text()
    code, _ = _replay(bag, tmp_path, '--roi', '0.7', '0.2', name='bad')
    assert code == 2


def test_ignore_mask_as_the_node(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # --mask PNG: the node's mask_path; nothing is kept at its black pixels, and the report's
    # kept share is that of the others, as /diagnostics gives it.
    bag = write_stereo_bag(tmp_path / 'in', [{}, {}], ground_truth=False)
    mask = np.full((30, 40), 255, np.uint8)
    mask[20:, 25:] = 0
    path = tmp_path / 'mask.png'
    assert cv2.imwrite(str(path), mask)
    code, report = _replay(bag, tmp_path, '--mask', str(path))
    assert code == 0
    assert report['config']['mask_path'] == str(path)
    outputs = read_bag(tmp_path / 'run_bag')
    judged = mask > 0
    for index, record in enumerate(report['frames']):
        disparity = disparity_from_message(outputs['/disparity'][index][1])
        kept = np.isfinite(disparity_from_message(outputs['/disparity_filtered'][index][1]))
        assert np.isnan(disparity[~judged]).all() and np.isfinite(disparity[judged]).any()
        assert record['kept_fraction'] == pytest.approx(kept[judged].mean())
    # A mask that cannot be read, or of another size than the images, is named.
    capsys.readouterr()
    code, _ = _replay(bag, tmp_path, '--mask', str(tmp_path / 'none.png'), name='missing')
    assert code == 2 and 'none.png' in capsys.readouterr().err
    assert not (tmp_path / 'missing_bag').exists()
    assert cv2.imwrite(str(path), mask[:, :32])
    code, report = _replay(bag, tmp_path, '--mask', str(path), name='other')
    assert report['summary']['processed'] == 0
    # Review 31: named by the tool's own option and the file (it said 'mask_path').
    assert f'the mask (--mask {str(path)!r}) is 32×30 px but the images are 40×30 px' in (
        capsys.readouterr().err)

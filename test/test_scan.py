"""The laser scan of the kept pixels (cva_confidence_ros.scan)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.pointcloud import StereoGeometry, disparity_to_points
from cva_confidence_ros.scan import (
    Scan,
    ScanConfig,
    ScanScore,
    bearing_range,
    disparity_to_scan,
    scan_frame_id,
    score_scan,
)

GEOMETRY = StereoGeometry(fx=100.0, fy=100.0, cx=47.5, cy=31.5, cx_right=47.5, baseline=0.1)


def _bearings(scan) -> np.ndarray:
    return scan.angle_min + scan.angle_increment * np.arange(scan.ranges.size)


def _reference(disparity, geometry, mask, confidence, config):
    """The scan point by point, from disparity_to_points turned by the pitch."""
    points = disparity_to_points(disparity, geometry, mask).astype(np.float64)
    x, y, z = points[..., 0], points[..., 1], points[..., 2]
    sin_p, cos_p = math.sin(config.pitch), math.cos(config.pitch)
    up = -(y * cos_p + z * sin_p)
    forward = z * cos_p - y * sin_p
    # The extreme bearings of every pixel's ray (a ray not pointing forward: ±pi/2).
    rows, columns = np.mgrid[: disparity.shape[0], : disparity.shape[1]].astype(np.float64)
    ray_forward = cos_p - (rows - geometry.cy) / geometry.fy * sin_p
    lateral = geometry.cx - columns
    with np.errstate(divide='ignore', invalid='ignore'):
        ahead = np.arctan2(lateral, geometry.fx * ray_forward)
    ray_bearings = np.where(ray_forward > 0, ahead, np.sign(lateral) * np.pi / 2)
    angle_min, angle_max = float(ray_bearings.min()), float(ray_bearings.max())
    beams = int(math.floor((angle_max - angle_min) * geometry.fx)) + 1
    increment = (angle_max - angle_min) / (beams - 1)
    nearest = {}
    state = np.zeros(beams, int)
    for v, u in zip(*np.nonzero(np.isfinite(z)), strict=True):
        if not config.min_height <= up[v, u] <= config.max_height or forward[v, u] <= 0:
            continue
        beam = math.floor((math.atan2(-x[v, u], forward[v, u]) - angle_min) / increment + 0.5)
        if not 0 <= beam < beams:
            continue
        distance = math.hypot(x[v, u], forward[v, u])
        if distance > config.range_max:
            state[beam] = max(state[beam], 1)
        elif distance < config.range_min:
            state[beam] = max(state[beam], 2)
        elif beam not in nearest or distance < nearest[beam][0]:
            nearest[beam] = (distance, confidence[v, u])
            state[beam] = 3
    ranges = np.full(beams, np.nan)
    ranges[state == 1], ranges[state == 2] = np.inf, -np.inf
    intensities = np.zeros(beams)
    for beam, (distance, value) in nearest.items():
        ranges[beam], intensities[beam] = distance, value
    return ranges, intensities


def test_a_wall_gives_its_distance_along_every_bearing() -> None:
    # A wall 2 m ahead (d = f·B/Z = 5): each beam's range is that of its nearest column,
    # 2 / cos(bearing) within half a beam, left columns at positive bearings; no beam empty.
    disparity = np.full((64, 96), 5.0, np.float32)
    scan = disparity_to_scan(disparity, GEOMETRY)
    assert scan.angle_min == pytest.approx(math.atan2(47.5 - 95, 100.0))
    assert scan.angle_max == pytest.approx(math.atan2(47.5, 100.0)) and scan.angle_max > 0
    assert np.all(np.isfinite(scan.ranges))
    bearings = np.abs(_bearings(scan))
    half = scan.angle_increment / 2
    assert np.all(scan.ranges >= 2.0 / np.cos(np.maximum(bearings - half, 0)) - 1e-6)
    assert np.all(scan.ranges <= 2.0 / np.cos(bearings + half) + 1e-6)
    assert scan.ranges[np.argmin(bearings)] == pytest.approx(2.0, rel=1e-4)
    assert (scan.range_min, scan.range_max) == (0.1, 20.0)
    np.testing.assert_array_equal(scan.intensities, 0.0)


@pytest.mark.parametrize('width, fx', [(96, 100.0), (640, 200.0), (1242, 721.5), (64, 5.0)])
def test_no_beam_falls_between_two_columns(width: int, fx: float) -> None:
    # The increment is at least the bearing step of the centre columns (1 / fx or more): every
    # beam of a dense map has a point, however wide the lens.
    geometry = StereoGeometry(fx=fx, fy=fx, cx=(width - 1) / 2, cy=4.0, cx_right=(width - 1) / 2,
                              baseline=0.1)
    scan = disparity_to_scan(np.full((9, width), 5.0, np.float32), geometry,
                             config=ScanConfig(min_height=-1e3, max_height=1e3, range_max=1e3))
    assert 2 <= scan.ranges.size <= width
    assert scan.angle_increment >= 1.0 / fx - 1e-12
    assert np.all(np.isfinite(scan.ranges))


@pytest.mark.parametrize('density', [0.7, 0.02])
@pytest.mark.parametrize('pitch', [0.0, 0.3, -0.2, 1.4])
def test_matches_the_points_turned_level_point_by_point(pitch: float, density: float) -> None:
    rng = np.random.default_rng(3)
    geometry = StereoGeometry(fx=80.0, fy=82.0, cx=40.0, cy=25.0, cx_right=43.0, baseline=0.2)
    disparity = rng.uniform(-3.5, 30.0, size=(50, 90)).astype(np.float32)
    disparity[rng.random(disparity.shape) < 0.1] = np.nan
    mask = rng.random(disparity.shape) < density
    confidence = rng.random(disparity.shape).astype(np.float32)
    config = ScanConfig(min_height=-0.4, max_height=0.3, range_min=0.8, range_max=4.0,
                        pitch=pitch)
    scan = disparity_to_scan(disparity, geometry, mask, confidence, config)
    ranges, intensities = _reference(disparity, geometry, mask, confidence, config)
    np.testing.assert_allclose(scan.ranges, ranges, rtol=1e-6)
    np.testing.assert_allclose(scan.intensities, intensities, rtol=1e-6)
    if density > 0.5 or abs(pitch) > 1.0:
        return
    # All four beam states occur in the sparse map (looking almost straight down, no band
    # point lies beyond range_max).
    assert np.isnan(scan.ranges).any() and np.isposinf(scan.ranges).any()
    assert np.isneginf(scan.ranges).any() and np.isfinite(scan.ranges).any()


@pytest.mark.parametrize('pitch', [0.3, -0.3])
def test_a_pitched_camera_keeps_the_points_of_its_wider_corners(pitch: float) -> None:
    # Looking down, the bottom corners see farther to the side than the columns' centres do
    # at the horizon (up: the top corners): a point there was in no beam (1,734 of 25,000 in
    # the band for a 200×150 view of a wall at pitch 0.3).
    disparity = np.full((64, 96), np.nan, np.float32)
    confidence = np.zeros((64, 96), np.float32)
    row = 63 if pitch > 0 else 0
    disparity[row, 95] = disparity[row, 0] = 40.0  # 0.25 m ahead of the camera
    confidence[row, 95], confidence[row, 0] = 0.9, 0.8
    config = ScanConfig(min_height=-1.0, max_height=1.0, range_min=0.0, pitch=pitch)
    scan = disparity_to_scan(disparity, GEOMETRY, confidence=confidence, config=config)
    level = math.atan2(GEOMETRY.cx - 95, GEOMETRY.fx), math.atan2(GEOMETRY.cx, GEOMETRY.fx)
    assert scan.angle_min < level[0] and scan.angle_max > level[1]
    assert (scan.angle_min, scan.angle_max) == bearing_range(GEOMETRY, 96, 64, pitch)
    finite = np.flatnonzero(np.isfinite(scan.ranges))
    # The two points are the outermost beams, with their confidences.
    assert finite.tolist() == [0, scan.ranges.size - 1]
    assert scan.intensities[finite] == pytest.approx([0.9, 0.8])
    # Level, the scan is as before: the last and first column's centres.
    assert bearing_range(GEOMETRY, 96, 64) == pytest.approx(level)


def test_nan_confidence_is_intensity_zero() -> None:
    disparity = np.full((64, 96), 5.0, np.float32)
    confidence = np.full((64, 96), np.nan, np.float32)
    scan = disparity_to_scan(disparity, GEOMETRY, confidence=confidence)
    assert np.isfinite(scan.ranges).all() and (scan.intensities == 0).all()


def test_the_nearest_point_wins_and_brings_its_confidence() -> None:
    disparity = np.full((64, 96), np.nan, np.float32)
    confidence = np.zeros((64, 96), np.float32)
    disparity[30, 47], confidence[30, 47] = 5.0, 0.9   # 2 m
    disparity[33, 47], confidence[33, 47] = 10.0, 0.6  # 1 m, same column: nearer
    disparity[31, 10], confidence[31, 10] = 4.0, 0.7   # 2.5 m, to the left
    scan = disparity_to_scan(disparity, GEOMETRY, confidence=confidence)
    hits = np.flatnonzero(np.isfinite(scan.ranges))
    assert hits.size == 2
    right, left = hits  # beam 0 looks along the last column
    assert scan.ranges[right] == pytest.approx(math.hypot(-0.5 * 1.0 / 100, 1.0), rel=1e-6)
    assert scan.intensities[right] == pytest.approx(0.6)
    bearing = math.atan2(37.5, 100.0)
    assert _bearings(scan)[left] == pytest.approx(bearing, abs=scan.angle_increment)
    assert scan.ranges[left] == pytest.approx(math.hypot(37.5 * 2.5 / 100, 2.5), rel=1e-6)
    assert scan.intensities[left] == pytest.approx(0.7)
    assert np.isnan(np.delete(scan.ranges, hits)).all()
    assert np.all(np.delete(scan.intensities, hits) == 0.0)


def test_ranges_outside_the_limits_follow_rep_117() -> None:
    disparity = np.full((64, 96), np.nan, np.float32)
    disparity[31, 70] = 0.2   # 50 m: beyond range_max → +inf
    disparity[31, 20] = 200.0  # 5 cm: nearer than range_min → −inf
    disparity[31, 40] = 0.2
    disparity[32, 40] = 200.0  # both in one beam: −inf (something too close is there)
    mask = np.isfinite(disparity)
    scan = disparity_to_scan(disparity, GEOMETRY, mask, np.ones((64, 96)))
    finite = {u: scan.ranges[np.argmin(np.abs(_bearings(scan) - math.atan2(47.5 - u, 100.0)))]
              for u in (70, 20, 40)}
    assert finite == {70: np.inf, 20: -np.inf, 40: -np.inf}
    assert np.all(scan.intensities == 0.0)
    assert np.isnan(scan.ranges).sum() == scan.ranges.size - 3


def test_the_height_band_and_the_mask_choose_the_points() -> None:
    # A wall 2 m ahead: a row v lies (31.5 − v) · 2 / 100 m above the camera.
    disparity = np.full((64, 96), 5.0, np.float32)
    above = ScanConfig(min_height=0.3, max_height=0.5)  # rows 6.5 … 16.5
    scan = disparity_to_scan(disparity, GEOMETRY, config=above)
    assert np.all(np.isfinite(scan.ranges))
    mask = np.ones((64, 96), bool)
    mask[7:17] = False
    assert np.isnan(disparity_to_scan(disparity, GEOMETRY, mask, config=above).ranges).all()
    below = ScanConfig(min_height=-10.0, max_height=-0.7)  # rows 66.5 and below: none
    assert np.isnan(disparity_to_scan(disparity, GEOMETRY, config=below).ranges).all()


@pytest.mark.parametrize(
    'values, message',
    [
        ({'min_height': 0.5, 'max_height': 0.5}, 'scan_min_height must be < scan_max_height'),
        ({'range_min': -1.0}, 'scan_range_min'),
        ({'range_min': 5.0, 'range_max': 5.0}, 'scan_range_min < scan_range_max'),
        ({'range_max': math.inf}, 'scan_range_max must be a finite number'),
        ({'pitch': 1.6}, 'scan_pitch'),
        ({'max_height': '1'}, 'scan_max_height must be a finite number'),
        ({'min_height': math.nan}, 'scan_min_height'),
    ],
)
def test_config_names_what_it_refuses(values: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        ScanConfig(**values)


def test_inputs_that_do_not_fit_are_named() -> None:
    disparity = np.full((4, 6), 5.0, np.float32)
    with pytest.raises(InputError, match='confidence must be a real array'):
        disparity_to_scan(disparity, GEOMETRY, confidence=np.zeros((4, 5)))
    with pytest.raises(InputError, match='mask must have the disparity shape'):
        disparity_to_scan(disparity, GEOMETRY, np.ones((3, 6), bool))
    with pytest.raises(InputError, match='at least 2 columns'):
        disparity_to_scan(np.ones((4, 1), np.float32), GEOMETRY)
    with pytest.raises(InputError, match='disparity must be'):
        disparity_to_scan(np.ones(6, np.float32), GEOMETRY)
    with pytest.raises(ConfigError, match='ScanConfig'):
        disparity_to_scan(disparity, GEOMETRY, config={'min_height': 0.0})


@pytest.mark.parametrize(
    'camera, configured, expected',
    [
        ('zed_left_camera_optical_frame', '', 'zed_left_camera_frame'),
        ('camera_color_optical_frame', '', 'camera_color_frame'),
        ('left_optical', '', 'left'),
        ('camera_link', '', 'camera_link'),
        ('_optical_frame', '', '_optical_frame'),
        ('left_optical', 'base_scan', 'base_scan'),
    ],
)
def test_the_scan_frame_is_the_body_frame_beside_the_optical_one(
    camera: str, configured: str, expected: str
) -> None:
    assert scan_frame_id(camera, configured) == expected


def _scan(ranges: list[float]) -> Scan:
    values = np.array(ranges, np.float32)
    return Scan(ranges=values, intensities=np.zeros_like(values), angle_min=-0.03,
                angle_max=-0.03 + 0.01 * (values.size - 1), angle_increment=0.01,
                range_min=0.1, range_max=20.0)


def test_beams_are_judged_by_the_kitti_criterion_in_disparity() -> None:
    # fx · B = 50 px·m: 5 m is 10 px. 2 m (25 px) is a phantom, 9 m (5.6 px) is too far, 5.1 m
    # (9.8 px) is right; −inf (too close) counts as a phantom, +inf (nothing in range) as far,
    # NaN as none; a beam without a true return is not scored.
    geometry = StereoGeometry(fx=100.0, fy=100.0, cx=50.0, cy=30.0, cx_right=50.0,
                              baseline=0.5)
    truth = _scan([5.0, 5.0, 5.0, 5.0, 5.0, 5.0, 5.0, float('nan')])
    estimate = _scan([5.0, 2.0, 9.0, 5.1, float('nan'), -np.inf, np.inf, 3.0])
    score = score_scan(estimate, truth, geometry)
    assert (score.beams, score.phantom, score.far, score.none) == (7, 2, 2, 1)
    assert score.rate('phantom') == pytest.approx(2 / 7)
    assert score_scan(truth, truth, geometry).rate('phantom') == 0.0
    # 6.5 m is 7.7 px, 2.3 px off: within 3 px, right; at fx · B = 150 the same ranges are
    # 6.9 px apart, and wrong.
    near = _scan([6.5])
    assert score_scan(near, _scan([5.0]), geometry).far == 0
    wide = StereoGeometry(fx=300.0, fy=300.0, cx=50.0, cy=30.0, cx_right=50.0, baseline=0.5)
    assert score_scan(near, _scan([5.0]), wide).far == 1
    with pytest.raises(InputError, match='scans with different beams'):
        score_scan(_scan([5.0, 5.0]), truth, geometry)
    assert ScanScore(beams=0, phantom=0, far=0, none=0).rate('none') is None


@pytest.mark.parametrize('pitch', [0.0, 0.2])
def test_a_scan_against_the_scan_of_its_ground_truth(pitch: float) -> None:
    # A plane 0.4 m ahead, a level or pitched camera: the estimate's columns 10-19 nearer by
    # 6 px make phantoms there, columns 60-69 farther by 6 px make far beams, a masked band
    # makes beams without a return, the rest is right.
    height, width = 64, 96
    truth = np.full((height, width), 25.0, np.float32)  # 0.4 m: fx · B = 10 px·m
    estimate = truth.copy()
    estimate[:, 10:20] += 6.0
    estimate[:, 60:70] -= 6.0
    mask = np.ones((height, width), bool)
    mask[:, 40:45] = False
    config = ScanConfig(min_height=-0.05, max_height=0.05, range_min=0.0, range_max=50.0,
                        pitch=pitch)
    reference = disparity_to_scan(truth, GEOMETRY, None, None, config)
    scan = disparity_to_scan(estimate, GEOMETRY, mask, None, config)
    score = score_scan(scan, reference, GEOMETRY, config)
    assert score.beams > 80
    assert 8 <= score.phantom <= 11 and 8 <= score.far <= 11 and 4 <= score.none <= 6
    assert score_scan(reference, reference, GEOMETRY, config).phantom == 0

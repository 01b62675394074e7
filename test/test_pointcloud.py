"""Tests of disparity triangulation and colour packing against hand-computed values."""

from __future__ import annotations

import numpy as np
import pytest

from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.pointcloud import (
    CLOUD_CONFIDENCE_DTYPE,
    CLOUD_DTYPE,
    StereoGeometry,
    disparity_to_depth,
    disparity_to_points,
    filter_cloud,
    make_cloud,
    pack_rgb,
    stereo_cloud,
    unpack_rgb,
)

# fx = fy = 100 px, cx = 2, cy = 1, baseline 0.5 m → P_right[0, 3] = −50.
P_LEFT = [100.0, 0.0, 2.0, 0.0, 0.0, 100.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]
P_RIGHT = [100.0, 0.0, 2.0, -50.0, 0.0, 100.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]


def test_geometry_from_projections() -> None:
    geometry = StereoGeometry.from_projections(P_LEFT, np.reshape(P_RIGHT, (3, 4)))
    assert geometry == StereoGeometry(fx=100, fy=100, cx=2, cy=1, cx_right=2, baseline=0.5)
    assert geometry.disparity_offset == 0.0


def test_points_hand_computed() -> None:
    geometry = StereoGeometry.from_projections(P_LEFT, P_RIGHT)
    disparity = np.array([[10.0, 20.0, 5.0, np.nan], [0.0, 25.0, -1.0, 50.0]], np.float32)
    points = disparity_to_points(disparity, geometry)
    assert points.shape == (2, 4, 3) and points.dtype == np.float32
    # (v, u) = (0, 0), d = 10: Z = 100·0.5/10 = 5; X = (0 − 2)·5/100 = −0.1; Y = (0 − 1)·5/100.
    np.testing.assert_allclose(points[0, 0], [-0.1, -0.05, 5.0], rtol=1e-6)
    # (0, 1), d = 20: Z = 2.5; X = −1·2.5/100; Y = −1·2.5/100.
    np.testing.assert_allclose(points[0, 1], [-0.025, -0.025, 2.5], rtol=1e-6)
    # (0, 2), d = 5: Z = 10; X = 0; Y = −0.1.
    np.testing.assert_allclose(points[0, 2], [0.0, -0.1, 10.0], rtol=1e-6, atol=1e-7)
    # (1, 1), d = 25: Z = 2; X = −0.02; Y = 0.
    np.testing.assert_allclose(points[1, 1], [-0.02, 0.0, 2.0], rtol=1e-6, atol=1e-7)
    # (1, 3), d = 50: Z = 1; X = 0.01; Y = 0.
    np.testing.assert_allclose(points[1, 3], [0.01, 0.0, 1.0], rtol=1e-6, atol=1e-7)
    # NaN, zero and negative disparities are not points.
    for v, u in ((0, 3), (1, 0), (1, 2)):
        assert np.all(np.isnan(points[v, u]))


def test_principal_point_offset_and_fy() -> None:
    # Verged principal points: cx_right = 12 → Δ = 10; fy = 200.
    p_left = [100.0, 0, 2.0, 0, 0, 200.0, 1.0, 0, 0, 0, 1, 0]
    p_right = [100.0, 0, 12.0, -50.0, 0, 200.0, 1.0, 0, 0, 0, 1, 0]
    geometry = StereoGeometry.from_projections(p_left, p_right)
    assert geometry.disparity_offset == 10.0
    disparity = np.array([[0.0, -10.0, 15.0]], np.float32)
    points = disparity_to_points(disparity, geometry)
    # d = 0 → d + Δ = 10 → Z = 5; X = (0 − 2)·5/100; Y = (0 − 1)·5/200.
    np.testing.assert_allclose(points[0, 0], [-0.1, -0.025, 5.0], rtol=1e-6)
    assert np.all(np.isnan(points[0, 1]))
    # d = 15 → 25 → Z = 2; X = 0; Y = −0.01.
    np.testing.assert_allclose(points[0, 2], [0.0, -0.01, 2.0], rtol=1e-6, atol=1e-7)


def test_reprojection_round_trip() -> None:
    rng = np.random.default_rng(0)
    geometry = StereoGeometry(
        fx=700.0, fy=700.0, cx=320.5, cy=240.0, cx_right=325.0, baseline=0.12
    )
    disparity = rng.uniform(1, 60, size=(6, 8)).astype(np.float32)
    points = disparity_to_points(disparity, geometry).astype(np.float64)
    u = geometry.fx * points[..., 0] / points[..., 2] + geometry.cx
    v = geometry.fy * points[..., 1] / points[..., 2] + geometry.cy
    np.testing.assert_allclose(u, np.arange(8)[None, :].repeat(6, 0), atol=1e-3)
    np.testing.assert_allclose(v, np.arange(6)[:, None].repeat(8, 1), atol=1e-3)
    # The right camera sees the point at x_right = x_left − d.
    u_right = geometry.fx * (points[..., 0] - geometry.baseline) / points[..., 2]
    u_right += geometry.cx_right
    np.testing.assert_allclose(u - u_right, disparity, atol=1e-3)


def test_mask_drops_points() -> None:
    geometry = StereoGeometry.from_projections(P_LEFT, P_RIGHT)
    disparity = np.full((2, 2), 10.0, np.float32)
    mask = np.array([[True, False], [False, True]])
    points = disparity_to_points(disparity, geometry, mask)
    assert np.isfinite(points[0, 0]).all() and np.isfinite(points[1, 1]).all()
    assert np.isnan(points[0, 1]).all() and np.isnan(points[1, 0]).all()


def test_scaled_geometry_keeps_pixel_centres() -> None:
    geometry = StereoGeometry(fx=100.0, fy=80.0, cx=63.5, cy=31.5, cx_right=65.5, baseline=0.3)
    half = geometry.scaled(0.5)
    assert half == StereoGeometry(fx=50.0, fy=40.0, cx=31.5, cy=15.5, cx_right=32.5, baseline=0.3)
    # A disparity of 20 px at full size is 10 px at half size: the same depth comes out.
    full_point = disparity_to_points(np.array([[20.0]], np.float32), geometry)
    half_point = disparity_to_points(np.array([[10.0]], np.float32), half)
    assert full_point[0, 0, 2] == pytest.approx(100 * 0.3 / 22)
    assert half_point[0, 0, 2] == pytest.approx(50 * 0.3 / 11)
    assert geometry.scaled(1.0) == geometry
    anisotropic = geometry.scaled(0.5, 0.25)
    assert (anisotropic.fx, anisotropic.fy) == (50.0, 20.0)
    assert (anisotropic.cx, anisotropic.cy) == (31.5, 7.5)


def test_pack_rgb_bits() -> None:
    image = np.array([[[255, 0, 0], [0, 255, 0]], [[0, 0, 255], [1, 2, 3]]], np.uint8)
    packed = pack_rgb(image)
    assert packed.dtype == np.float32 and packed.shape == (2, 2)
    bits = packed.view(np.uint32)
    assert bits.tolist() == [[0xFF0000, 0x00FF00], [0x0000FF, 0x010203]]
    np.testing.assert_array_equal(unpack_rgb(packed), image)
    gray = pack_rgb(np.array([[7]], np.uint8))
    assert gray.view(np.uint32)[0, 0] == 0x070707


def test_make_cloud_organised_and_dense() -> None:
    geometry = StereoGeometry.from_projections(P_LEFT, P_RIGHT)
    disparity = np.array([[10.0, np.nan], [20.0, 25.0]], np.float32)
    points = disparity_to_points(disparity, geometry)
    colours = pack_rgb(np.array([[1, 2], [3, 4]], np.uint8))
    organised = make_cloud(points, colours, organized=True)
    assert organised.dtype == CLOUD_DTYPE and CLOUD_DTYPE.itemsize == 16
    assert organised.shape == (2, 2)
    assert np.isnan(organised['z'][0, 1])
    assert organised['z'][0, 0] == pytest.approx(5.0)
    dense = make_cloud(points, colours, organized=False)
    assert dense.shape == (3,)
    np.testing.assert_allclose(dense['z'], [5.0, 2.5, 2.0], rtol=1e-6)
    assert unpack_rgb(dense['rgb'])[:, 0].tolist() == [1, 3, 4]


@pytest.mark.parametrize(
    ('p_left', 'p_right', 'match'),
    [
        (P_LEFT[:11], P_RIGHT, '12 values'),
        (P_LEFT, [100.0, 0, 2, 50.0, 0, 100, 1, 0, 0, 0, 1, 0], 'baseline'),
        (P_LEFT, [0.0] * 12, 'fx'),
        ([0.0] * 12, P_RIGHT, 'focal'),
        ([np.nan] * 12, P_RIGHT, 'finite'),
        (P_LEFT, [50.0, 0, 2, -25.0, 0, 50, 1, 0, 0, 0, 1, 0], 'must share fx'),
        ([1e40, 0, 2, 0, 0, 1e40, 1, 0, 0, 0, 1, 0],
         [1e40, 0, 2, -1e39, 0, 1e40, 1, 0, 0, 0, 1, 0], 'fit float32'),
    ],
)
def test_invalid_projections(p_left: list, p_right: list, match: str) -> None:
    with pytest.raises(InputError, match=match):
        StereoGeometry.from_projections(p_left, p_right)


def test_invalid_arrays() -> None:
    geometry = StereoGeometry.from_projections(P_LEFT, P_RIGHT)
    with pytest.raises(InputError, match='disparity'):
        disparity_to_points(np.zeros((2, 2, 1), np.float32), geometry)
    with pytest.raises(InputError, match='mask'):
        disparity_to_points(np.zeros((2, 2), np.float32), geometry, np.ones((3, 2), bool))
    with pytest.raises(InputError, match='uint8'):
        pack_rgb(np.zeros((2, 2), np.float32))
    with pytest.raises(InputError, match='3'):
        pack_rgb(np.zeros((2, 2, 4), np.uint8))
    with pytest.raises(InputError, match='> 0'):
        geometry.scaled(0.0)


@pytest.mark.parametrize(
    'mask',
    [np.array([[np.nan, 0.2]]), np.array([[1, 0]]), [[1.0, 0.0]], np.array([['a', 'b']])],
    ids=['nan-float', 'int', 'list-float', 'str'],
)
def test_mask_must_be_bool(mask: object) -> None:
    geometry = StereoGeometry.from_projections(P_LEFT, P_RIGHT)
    with pytest.raises(InputError, match='mask must be a bool array'):
        disparity_to_points(np.full((1, 2), 10.0, np.float32), geometry, mask)
    kept = disparity_to_points(np.full((1, 2), 10.0, np.float32), geometry, [[True, False]])
    assert np.isfinite(kept[0, 0]).all() and np.isnan(kept[0, 1]).all()


@pytest.mark.parametrize(
    'disparity',
    [np.ones((2, 2), complex), np.full((2, 2), '1'), np.ones((2, 2), bool)],
    ids=['complex', 'str', 'bool'],
)
def test_disparity_must_be_real(disparity: np.ndarray) -> None:
    geometry = StereoGeometry.from_projections(P_LEFT, P_RIGHT)
    with pytest.raises(InputError, match=f'disparity must hold real numbers.*{disparity.dtype}'):
        disparity_to_points(disparity, geometry)


@pytest.mark.parametrize('geometry', [None, P_LEFT, {'fx': 100.0}])
def test_disparity_to_points_needs_a_geometry(geometry: object) -> None:
    with pytest.raises(InputError, match=f'StereoGeometry; got {type(geometry).__name__}'):
        disparity_to_points(np.ones((2, 2), np.float32), geometry)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    'colours',
    [np.full((2, 2), 255, np.uint8), np.zeros((2, 2), np.float64), np.zeros((2, 2), np.uint32)],
    ids=['uint8', 'float64', 'uint32'],
)
def test_make_cloud_needs_packed_float32_colours(colours: np.ndarray) -> None:
    points = np.zeros((2, 2, 3), np.float32)
    with pytest.raises(InputError, match=f'colours must be float32 packed.*{colours.dtype}'):
        make_cloud(points, colours)


def test_make_cloud_needs_arrays_and_float_points() -> None:
    points = np.zeros((2, 2, 3), np.float32)
    colours = pack_rgb(np.zeros((2, 2), np.uint8))
    with pytest.raises(InputError, match='points must be a numpy array; got list'):
        make_cloud(points.tolist(), colours)  # type: ignore[arg-type]
    with pytest.raises(InputError, match='colours must be a numpy array; got list'):
        make_cloud(points, colours.tolist())  # type: ignore[arg-type]
    with pytest.raises(InputError, match='points must be a float array.*complex64'):
        make_cloud(points.astype(np.complex64), colours)
    big_endian = make_cloud(points, colours.astype('>f4'))
    assert big_endian['rgb'].view(np.uint32).tolist() == [[0, 0], [0, 0]]


@pytest.mark.parametrize('organized', ['no', 0, 1, None])
def test_make_cloud_organized_must_be_bool(organized: object) -> None:
    points = np.zeros((2, 2, 3), np.float32)
    colours = pack_rgb(np.zeros((2, 2), np.uint8))
    expected = f'organized must be a bool; got {type(organized).__name__}'
    with pytest.raises(ConfigError, match=expected):
        make_cloud(points, colours, organized)  # type: ignore[arg-type]
    assert make_cloud(points, colours, np.bool_(False)).shape == (4,)


@pytest.mark.parametrize(
    ('field', 'value'),
    [('fx', 'a'), ('fx', None), ('fx', True), ('baseline', np.bool_(True)), ('cy', 1 + 2j)],
)
def test_geometry_fields_must_be_real_numbers(field: str, value: object) -> None:
    values: dict[str, object] = {
        'fx': 100.0, 'fy': 100.0, 'cx': 2.0, 'cy': 1.0, 'cx_right': 2.0, 'baseline': 0.5
    }
    values[field] = value
    with pytest.raises(InputError, match=f'field {field} must be a real number'):
        StereoGeometry(**values)  # type: ignore[arg-type]
    values[field] = np.float32(2.0) if field != 'fx' else np.int64(100)
    StereoGeometry(**values)  # type: ignore[arg-type]


@pytest.mark.parametrize(('factor', 'factor_y'), [('a', None), (None, None), (True, None),
                                                  (0.5, 'b'), (0.5, False)])
def test_scaled_factors_must_be_real_numbers(factor: object, factor_y: object) -> None:
    geometry = StereoGeometry.from_projections(P_LEFT, P_RIGHT)
    with pytest.raises(InputError, match='must be a real number'):
        geometry.scaled(factor, factor_y)  # type: ignore[arg-type]
    assert geometry.scaled(np.float32(0.5), 1).fx == 50.0


def _cloud_with_confidence() -> tuple[np.ndarray, np.ndarray]:
    points = np.arange(2 * 3 * 3, dtype=np.float32).reshape(2, 3, 3)
    points[0, 1] = np.nan
    confidence = np.array([[0.9, np.nan, 0.2], [0.5, 0.49, 1.0]], np.float32)
    colours = pack_rgb(np.full((2, 3), 7, np.uint8))
    return make_cloud(points, colours, True, confidence=confidence), confidence


def test_make_cloud_carries_confidence() -> None:
    cloud, confidence = _cloud_with_confidence()
    assert cloud.dtype == CLOUD_CONFIDENCE_DTYPE and CLOUD_CONFIDENCE_DTYPE.itemsize == 20
    assert CLOUD_CONFIDENCE_DTYPE.names[:4] == CLOUD_DTYPE.names
    np.testing.assert_array_equal(cloud['confidence'], confidence)
    points = np.zeros((2, 3, 3), np.float32)
    dense = make_cloud(points, np.zeros((2, 3), np.float32), False, confidence=np.ones((2, 3)))
    assert dense.shape == (6,) and (dense['confidence'] == 1).all()


@pytest.mark.parametrize(
    ('confidence', 'match'),
    [
        (np.full((2, 3), 1.5), r'\[0, 1\] at every kept point; 6 do not'),
        (np.full((2, 3), np.nan), r'\[0, 1\]'),
        (np.ones((3, 2)), r'must be \(2, 3\)'),
        (np.ones((2, 3), bool), 'real numbers'),
        ([[1.0] * 3] * 2, 'numpy array'),
    ],
)
def test_make_cloud_refuses_bad_confidence(confidence: object, match: str) -> None:
    with pytest.raises(InputError, match=match):
        make_cloud(np.zeros((2, 3, 3), np.float32), np.zeros((2, 3), np.float32),
                   confidence=confidence)


def test_make_cloud_confidence_may_be_nan_at_dropped_points() -> None:
    points = np.zeros((1, 2, 3), np.float32)
    points[0, 0] = np.nan
    cloud = make_cloud(points, np.zeros((1, 2), np.float32), False,
                       confidence=np.array([[np.nan, 0.3]]))
    assert cloud.shape == (1,) and cloud['confidence'][0] == np.float32(0.3)


def test_filter_cloud_organised_and_dense() -> None:
    cloud, confidence = _cloud_with_confidence()
    before = cloud.copy()
    organised = filter_cloud(cloud, 0.5)
    keep = np.array([[True, False, False], [True, False, True]])
    np.testing.assert_array_equal(np.isfinite(organised['z']), keep)
    np.testing.assert_array_equal(organised['x'][keep], cloud['x'][keep])
    assert np.isnan(organised['y'][~keep]).all()
    np.testing.assert_array_equal(organised['rgb'], cloud['rgb'])  # other fields untouched
    assert cloud.tobytes() == before.tobytes()  # the input is not changed
    dense = filter_cloud(cloud, 0.5, organized=False)
    assert dense.tobytes() == cloud[keep].tobytes()
    # 0 keeps every finite point with a confidence; NaN confidence is never kept.
    assert filter_cloud(cloud, 0.0, organized=False).shape == (5,)
    assert filter_cloud(cloud, 1.0, organized=False)['confidence'].tolist() == [1.0]


def test_filter_cloud_other_layouts() -> None:
    dtype = np.dtype({'names': ['z', 'y', 'x', 'score', 'ring'],
                      'formats': ['<f8', '<f4', '<f4', 'u1', '<u2'],
                      'offsets': [0, 8, 12, 16, 18], 'itemsize': 24})
    cloud = np.zeros(4, dtype)
    cloud['score'] = [0, 100, 200, 255]
    cloud['ring'] = [1, 2, 3, 4]
    kept = filter_cloud(cloud, 0.5, organized=False, field='score')  # 100/255 < 0.5
    assert kept.dtype == dtype and kept['ring'].tolist() == [3, 4]
    with pytest.raises(InputError, match="no confidence field 'confidence'.*'ring'"):
        filter_cloud(cloud, 0.5)


@pytest.mark.parametrize(
    ('cloud', 'kwargs', 'error', 'match'),
    [
        (np.zeros(3, np.float32), {}, InputError, 'structured numpy array'),
        ([1, 2], {}, InputError, 'structured numpy array'),
        (np.zeros((1, 1, 1), CLOUD_CONFIDENCE_DTYPE), {}, InputError, r'\(H, W\) or \(N,\)'),
        (np.zeros(2, [('x', '<f4'), ('y', '<f4'), ('confidence', '<f4')]), {}, InputError,
         "float field 'z'"),
        (np.zeros(2, [('x', '<f4'), ('y', '<f4'), ('z', '<i4'), ('confidence', '<f4')]), {},
         InputError, "float field 'z'"),
        (np.zeros(2, [('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('confidence', '<f4', 2)]),
         {}, InputError, 'one real number a point'),
        (np.zeros(2, CLOUD_CONFIDENCE_DTYPE), {'threshold': 1.5}, ConfigError, r'\[0, 1\]'),
        (np.zeros(2, CLOUD_CONFIDENCE_DTYPE), {'threshold': float('nan')}, ConfigError,
         r'\[0, 1\]'),
        (np.zeros(2, CLOUD_CONFIDENCE_DTYPE), {'threshold': True}, ConfigError, r'\[0, 1\]'),
        (np.zeros(2, CLOUD_CONFIDENCE_DTYPE), {'organized': 'yes'}, ConfigError, 'a bool'),
    ],
)
def test_filter_cloud_refuses(cloud: object, kwargs: dict, error: type, match: str) -> None:
    with pytest.raises(error, match=match):
        filter_cloud(cloud, **{'threshold': 0.5, **kwargs})


def test_stereo_cloud_thresholded_or_annotated() -> None:
    geometry = StereoGeometry.from_projections(P_LEFT, P_RIGHT)
    disparity = np.array([[10.0, np.nan, 5.0], [20.0, 25.0, -1.0]], np.float32)
    confidence = np.array([[0.9, 0.9, 0.1], [0.5, 0.2, 0.9]], np.float32)
    left = np.full((2, 3), 200, np.uint8)
    kept = np.isfinite(disparity) & (confidence >= 0.5)
    plain = stereo_cloud(disparity, confidence, left, geometry, kept)
    assert plain.dtype == CLOUD_DTYPE
    np.testing.assert_array_equal(
        np.isfinite(plain['z']), [[True, False, False], [True, False, False]]
    )
    annotated = stereo_cloud(disparity, confidence, left, geometry, kept, with_confidence=True)
    triangulable = [[True, False, True], [True, True, False]]
    np.testing.assert_array_equal(np.isfinite(annotated['z']), triangulable)
    np.testing.assert_array_equal(annotated['confidence'], confidence)
    # The filter at the node's threshold gives back the plain cloud.
    refiltered = filter_cloud(annotated, 0.5)
    for name in CLOUD_DTYPE.names:
        np.testing.assert_array_equal(refiltered[name], plain[name])
    dense = stereo_cloud(disparity, confidence, left, geometry, kept, organized=False)
    assert dense.shape == (2,)


def test_depth_is_the_z_of_the_points() -> None:
    geometry = StereoGeometry.from_projections(P_LEFT, P_RIGHT)
    disparity = np.array([[10.0, 20.0, 5.0, np.nan], [0.0, 25.0, -1.0, 50.0]], np.float32)
    depth = disparity_to_depth(disparity, geometry)
    assert depth.shape == (2, 4) and depth.dtype == np.float32
    # Z = fx·B / d = 50 / d, hand-computed; NaN, zero and negative disparities have none.
    expected = np.array([[5.0, 2.5, 10.0, np.nan], [np.nan, 2.0, np.nan, 1.0]], np.float32)
    np.testing.assert_array_equal(depth, expected)
    np.testing.assert_array_equal(depth, disparity_to_points(disparity, geometry)[..., 2])
    mask = np.isfinite(expected) & (expected < 6)
    masked = disparity_to_depth(disparity, geometry, mask)
    np.testing.assert_array_equal(masked, np.where(mask, expected, np.nan))


def test_depth_with_principal_point_offset() -> None:
    # cx_right − cx_left = 10: Z = fx·B / (d + 10).
    geometry = StereoGeometry(fx=100.0, fy=100.0, cx=2.0, cy=1.0, cx_right=12.0, baseline=0.5)
    depth = disparity_to_depth(np.array([[0.0, -10.0, 15.0]]), geometry)
    np.testing.assert_allclose(depth, [[5.0, np.nan, 2.0]], rtol=1e-6)


@pytest.mark.parametrize(
    ('disparity', 'mask', 'match'),
    [
        (np.zeros((2, 2, 1), np.float32), None, r'\(H, W\)'),
        (np.zeros((2, 2), bool), None, 'real numbers'),
        (np.zeros((2, 2), np.float32), np.ones((2, 2)), 'bool'),
        (np.zeros((2, 2), np.float32), np.ones((2, 3), bool), 'shape'),
    ],
)
def test_depth_refuses(disparity: np.ndarray, mask: np.ndarray | None, match: str) -> None:
    geometry = StereoGeometry.from_projections(P_LEFT, P_RIGHT)
    with pytest.raises(InputError, match=match):
        disparity_to_depth(disparity, geometry, mask)

"""Review 29 of the point clouds, the cloud filter and the scan: integer confidence read as a
fraction of full scale, and no half-finite points from disparities within a hair of 0."""

from __future__ import annotations

import numpy as np

from cva_confidence_ros.pointcloud import (
    StereoGeometry,
    disparity_to_depth,
    disparity_to_points,
    filter_cloud,
    make_cloud,
    pack_rgb,
)
from cva_confidence_ros.scan import ScanConfig, disparity_to_scan

_XYZ = [('x', '<f4'), ('y', '<f4'), ('z', '<f4')]


def _integer_cloud(values: list[int], dtype: str) -> np.ndarray:
    cloud = np.zeros(len(values), np.dtype([*_XYZ, ('confidence', dtype)]))
    cloud['z'] = 1.0
    cloud['confidence'] = values
    return cloud


def test_filter_cloud_reads_uint8_confidence_as_a_fraction_of_255() -> None:
    # 26/255 ≈ 0.10, 128/255 ≈ 0.50, 200/255 ≈ 0.784, 255/255 = 1.
    cloud = _integer_cloud([0, 26, 128, 200, 255], 'u1')
    assert filter_cloud(cloud, 0.8, organized=False)['confidence'].tolist() == [255]
    assert filter_cloud(cloud, 0.78, organized=False)['confidence'].tolist() == [200, 255]
    assert filter_cloud(cloud, 0.5, organized=False)['confidence'].tolist() == [128, 200, 255]
    organised = filter_cloud(cloud, 0.8)
    np.testing.assert_array_equal(np.isfinite(organised['z']), [False] * 4 + [True])
    assert organised['confidence'].dtype == np.uint8  # the field itself is carried unchanged


def test_filter_cloud_reads_uint16_confidence_as_a_fraction_of_65535() -> None:
    cloud = _integer_cloud([1, 32767, 32768, 65535], '<u2')
    assert filter_cloud(cloud, 0.5, organized=False)['confidence'].tolist() == [32768, 65535]
    assert filter_cloud(cloud, 1.0, organized=False)['confidence'].tolist() == [65535]


def test_make_cloud_reads_integer_confidence_like_the_filter() -> None:
    points = np.ones((1, 3, 3), np.float32)
    uint8 = np.array([[51, 128, 255]], np.uint8)
    cloud = make_cloud(points, pack_rgb(np.zeros((1, 3), np.uint8)), confidence=uint8)
    np.testing.assert_allclose(cloud['confidence'], uint8 / 255.0, rtol=1e-6)
    assert filter_cloud(cloud, 0.5, organized=False).shape == (2,)


def test_scan_reads_integer_confidence_like_the_filter() -> None:
    geometry = StereoGeometry(fx=50.0, fy=50.0, cx=32.0, cy=2.0, cx_right=32.0, baseline=0.1)
    disparity = np.full((5, 64), 10.0, np.float32)
    config = ScanConfig(min_height=-1.0, max_height=1.0)
    scan = disparity_to_scan(
        disparity, geometry, confidence=np.full((5, 64), 128, np.uint8), config=config
    )
    finite = np.isfinite(scan.ranges)
    assert finite.any()
    np.testing.assert_allclose(scan.intensities[finite], 128 / 255.0, rtol=1e-6)


def test_a_disparity_within_a_hair_of_zero_gives_no_half_finite_point() -> None:
    # fx·B / 5e-37 = 2e38 fits float32, but X = (u − cx) · Z / fx reaches 6.4e38 at the sides;
    # 1e-38 gives a Z of 1e40, beyond float32; at 2e-36 every coordinate fits (|X| ≤ 1.6e38).
    geometry = StereoGeometry(fx=100.0, fy=100.0, cx=320.0, cy=2.0, cx_right=320.0, baseline=1.0)
    disparity = np.full((5, 640), 5e-37, np.float32)
    disparity[0] = 1e-38
    disparity[4] = 2e-36
    points = disparity_to_points(disparity, geometry)
    finite = np.isfinite(points)
    np.testing.assert_array_equal(finite.all(axis=2), finite.any(axis=2))
    assert finite[4].all() and not finite[:4].any()
    depth = disparity_to_depth(disparity, geometry)
    np.testing.assert_array_equal(np.isfinite(depth), finite[..., 2])
    np.testing.assert_array_equal(depth[4], points[4, :, 2])
    cloud = make_cloud(points, pack_rgb(np.zeros((5, 640), np.uint8)), organized=False)
    assert cloud.shape == (640,)
    for name in ('x', 'y', 'z'):
        assert np.isfinite(cloud[name]).all()


def test_a_dense_cloud_drops_points_with_any_coordinate_not_finite() -> None:
    points = np.ones((1, 4, 3), np.float32)
    points[0, 0, 0] = np.nan
    points[0, 1, 1] = np.inf
    points[0, 2, 2] = np.nan
    cloud = make_cloud(points, np.zeros((1, 4), np.float32), organized=False)
    assert cloud.shape == (1,)
    assert (cloud['x'] == 1).all() and (cloud['y'] == 1).all() and (cloud['z'] == 1).all()

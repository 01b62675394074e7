"""Review 33 of the geometry of the node's outputs for camera infos that are not the plain case:
binning, a region of interest (REP 104), a left camera off the rectified origin
(``P_left[0, 3] ≠ 0``), fx ≠ fy, and a homogeneous P (third row ``(0, 0, w, 0)``, w ≠ 1), each at
downsample 1, 2 and 4.

The scene is a fronto-parallel plane at Z = 5 m seen with a disparity of 8 px in the images as
they arrive (binned and cropped); the node runs in-process, its publishers replaced by
recorders, and the published depth, points2, scan, disparity and camera_info are compared with
the pinhole model of the effective (folded) intrinsics.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
import os
from typing import Any

from node_test_utils import FRAME, SMALL_MLM, image_msg, localhost_context, spare_domain_id
import numpy as np
import pytest
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, RegionOfInterest
from std_msgs.msg import Header

from cva_confidence_ros.camera_info import check_rows
from cva_confidence_ros.errors import InputError
from cva_confidence_ros.node import ConfidenceNode
from cva_confidence_ros.pointcloud import StereoGeometry
from cva_confidence_ros.ros.convert import (
    camera_info_to_geometry,
    cloud_to_array,
    depth_image_to_array,
    disparity_from_message,
    image_camera_info,
    scale_camera_info,
)
from cva_confidence_ros.sync import MatchedSet
from msg_tools.convert import camera_geometry

pytestmark = pytest.mark.timeout(120)

DEPTH = 5.0
DISPARITY = 8  # px, in the images as they arrive
WIDTH, HEIGHT = 190, 143  # not multiples of 4: the pipeline crops before it shrinks
FX = 100.0  # effective (binned) fx
BASELINE = DISPARITY * DEPTH / FX
CX, CY = 93.5, 70.25  # effective principal point
STAMP = 7 * 10**9


@dataclass(frozen=True)
class Variant:
    """A rectified pair of camera infos; fx, fy, cx, cy, Tx_left of the full sensor."""

    binning: tuple[int, int] = (1, 1)
    roi: tuple[int, int, int, int] = (0, 0, 0, 0)  # x_offset, y_offset, width, height
    fy_ratio: float = 1.0
    tx_left: float = 0.0  # in effective pixels·m: −fx·x of the left camera
    w: float = 1.0  # P's third-row weight (homogeneous P)

    def infos(self) -> tuple[CameraInfo, CameraInfo]:
        bx, by = self.binning
        x0, y0, roi_w, roi_h = self.roi
        fx, fy = FX * bx, FX * self.fy_ratio * by
        cx, cy = CX * bx + x0, CY * by + y0
        calib = (roi_w + 2 * x0, roi_h + 2 * y0) if roi_w else (WIDTH * bx, HEIGHT * by)
        infos = []
        for tx in (self.tx_left * bx, (self.tx_left - FX * BASELINE) * bx):
            p = np.array([[fx, 0, cx, tx], [0, fy, cy, 0], [0, 0, 1, 0]]) * self.w
            infos.append(
                CameraInfo(
                    header=Header(frame_id=FRAME),
                    width=calib[0],
                    height=calib[1],
                    distortion_model='plumb_bob',
                    d=[0.0] * 5,
                    k=[fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0],
                    r=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                    p=p.ravel().tolist(),
                    binning_x=bx,
                    binning_y=by,
                    roi=RegionOfInterest(x_offset=x0, y_offset=y0, width=roi_w, height=roi_h),
                )
            )
        return infos[0], infos[1]


VARIANTS = {
    'plain': Variant(),
    'binning-2': Variant(binning=(2, 2)),
    'roi': Variant(roi=(40, 30, WIDTH, HEIGHT)),
    'binning-2-roi': Variant(binning=(2, 2), roi=(64, 41, 2 * WIDTH, 2 * HEIGHT + 1)),
    'binning-2x1-fx-fy': Variant(binning=(2, 1), fy_ratio=1.3),
    'fx-fy': Variant(fy_ratio=0.8),
    'left-off-origin': Variant(tx_left=FX * 0.3),
    'binning-roi-left-off-origin': Variant(
        binning=(2, 2), roi=(64, 40, 2 * WIDTH, 2 * HEIGHT), tx_left=-FX * 0.3
    ),
    'homogeneous-p': Variant(w=2.0),
    'homogeneous-p-binning-roi': Variant(binning=(2, 2), roi=(8, 6, 2 * WIDTH, 2 * HEIGHT), w=0.5),
}


class _Recorder:
    """Stands in for a publisher with one subscriber."""

    def __init__(self) -> None:
        self.msgs: list[Any] = []

    def get_subscription_count(self) -> int:
        return 1

    def publish(self, msg: Any) -> None:
        self.msgs.append(msg)


_PUBLISHERS = (
    '_pub_disparity', '_pub_filtered', '_pub_confidence', '_pub_points', '_pub_depth',
    '_pub_overlay', '_pub_scan', '_pub_info', '_pub_overlay_compressed', '_pub_depth_compressed',
)


def _pair() -> tuple[np.ndarray, np.ndarray]:
    """A blob texture shifted by DISPARITY: left[y, x] = right[y, x − d]."""
    rng = np.random.default_rng(1)
    coarse = rng.integers(0, 256, size=(HEIGHT // 4 + 2, (WIDTH + DISPARITY) // 4 + 2))
    texture = np.kron(coarse, np.ones((4, 4)))[:HEIGHT, : WIDTH + DISPARITY]
    texture = 0.6 * texture + 0.4 * rng.integers(0, 256, size=texture.shape)
    texture = texture.astype(np.uint8)
    return texture[:, :WIDTH].copy(), texture[:, DISPARITY : DISPARITY + WIDTH].copy()


def _outputs(node: ConfidenceNode, variant: Variant) -> dict[str, Any]:
    recorders = {name: _Recorder() for name in _PUBLISHERS}
    for name, recorder in recorders.items():
        setattr(node, name, recorder)
    left, right = _pair()
    left_info, right_info = variant.infos()
    items = {
        'left': image_msg(left, STAMP),
        'right': image_msg(right, STAMP),
        'left_info': left_info,
        'right_info': right_info,
    }
    node._process(MatchedSet(stamp_ns=STAMP, items=items, stamps_ns={}), node._mailbox)
    return {name[5:]: recorder.msgs[-1] for name, recorder in recorders.items() if recorder.msgs}


def _check(outputs: dict[str, Any], variant: Variant, factor: int) -> None:
    # The true geometry of the output grid: input pixel (x + 0.5)·factor − 0.5.
    fx, fy = FX / factor, FX * variant.fy_ratio / factor
    cx, cy = (CX + 0.5) / factor - 0.5, (CY + 0.5) / factor - 0.5
    truth = StereoGeometry(fx=fx, fy=fy, cx=cx, cy=cy, cx_right=cx, baseline=BASELINE)
    disparity_msg = outputs['disparity']
    raw = disparity_from_message(disparity_msg) - disparity_msg.min_disparity
    height, width = raw.shape
    assert (width, height) == (WIDTH // factor, HEIGHT // factor)
    # The geometry of the outputs is judged where the matcher found the true disparity.
    good = np.abs(raw - DISPARITY / factor) < 1e-3
    assert good.mean() > 0.9
    assert disparity_msg.f == pytest.approx(fx, rel=1e-6)
    assert disparity_msg.t == pytest.approx(BASELINE, rel=1e-6)
    depth = depth_image_to_array(outputs['depth'])
    np.testing.assert_allclose(depth[good], DEPTH, rtol=1e-6)
    np.testing.assert_allclose(
        disparity_msg.f * disparity_msg.t / (raw[good] + disparity_msg.min_disparity),
        DEPTH,
        rtol=1e-6,
    )

    cloud = cloud_to_array(outputs['points'])
    columns, rows = np.meshgrid(np.arange(width), np.arange(height))
    points = good & np.isfinite(cloud['z'])
    assert points.mean() > 0.9
    np.testing.assert_allclose(cloud['z'][points], DEPTH, rtol=1e-6)
    np.testing.assert_allclose(
        cloud['x'][points], (columns[points] - cx) * DEPTH / fx, rtol=1e-5, atol=1e-5
    )
    np.testing.assert_allclose(
        cloud['y'][points], (rows[points] - cy) * DEPTH / fy, rtol=1e-5, atol=1e-5
    )

    # The published camera_info: the output's size, no binning or ROI, and its P puts each
    # point back on its pixel.
    info = outputs['info']
    assert (info.width, info.height) == (width, height)
    assert max(info.binning_x, info.binning_y) <= 1
    roi = info.roi
    assert (roi.x_offset, roi.y_offset, roi.width, roi.height) == (0, 0, 0, 0)
    # The left image's header (stamp and optical frame), as every image output has it.
    assert info.header == outputs['depth'].header == outputs['points'].header
    assert info.header.frame_id == FRAME and info.header.stamp.sec == STAMP // 10**9
    p = np.array(info.p).reshape(3, 4)
    k = np.array(info.k).reshape(3, 3)
    assert p[2].tolist() == [0.0, 0.0, 1.0, 0.0]
    np.testing.assert_allclose(p[:, :3], k, atol=1e-9)
    xyz = np.stack([cloud[name][points] for name in 'xyz'], axis=1).astype(np.float64)
    pixels = xyz @ p[:, :3].T
    np.testing.assert_allclose(pixels[:, 0] / pixels[:, 2], columns[points], atol=1e-4)
    np.testing.assert_allclose(pixels[:, 1] / pixels[:, 2], rows[points], atol=1e-4)
    # Read back with the right camera's info (through the node's path): the geometry the
    # outputs were computed with, by the node's reader and by the bag tools' alike.
    right_out = scale_camera_info(
        image_camera_info(variant.infos()[1], WIDTH, HEIGHT), factor, info.header
    )
    for read in (
        camera_info_to_geometry(info, right_out, width, height),
        camera_geometry(info, right_out)[0],
    ):
        for name in ('fx', 'fy', 'cx', 'cy', 'cx_right', 'baseline'):
            assert getattr(read, name) == pytest.approx(getattr(truth, name), abs=1e-9), name

    # scan: each finite beam holds the nearest point of the plane in its bearing, ±½ beam.
    # Beams that columns left of 2·d see are left out (no match there for the matcher).
    scan = outputs['scan']
    ranges = np.asarray(scan.ranges, dtype=np.float64)
    bearings = scan.angle_min + scan.angle_increment * np.arange(ranges.size)
    assert scan.angle_max == pytest.approx(math.atan2(cx, fx))
    assert scan.angle_min == pytest.approx(math.atan2(cx - (width - 1), fx))
    judged = np.isfinite(ranges) & (bearings < math.atan2(cx - 2 * DISPARITY / factor, fx))
    assert judged.sum() > 0.8 * ranges.size
    off = np.abs(np.arccos(np.minimum(DEPTH / ranges[judged], 1.0)) - np.abs(bearings[judged]))
    assert off.max() <= 0.5 * scan.angle_increment + 1e-6
    assert ranges[judged].min() >= DEPTH * (1 - 1e-6)


@pytest.fixture(scope='module')
def context() -> Any:
    with localhost_context(spare_domain_id()) as context:
        yield context


@pytest.mark.parametrize('factor', [1, 2, 4])
def test_outputs_and_camera_info_agree_with_the_true_geometry(context: Any, factor: int) -> None:
    # Was: a homogeneous P (third row (0, 0, w, 0), w ≠ 1: the same camera) read as its
    # entries: at w = 2 depth 10 m for 5, X and Y 9.5 and 7.1 m off, the scan's nearest range
    # 10 m, and the published P kept w (read as entries: fx and cx w times theirs). The other
    # variants agreed already; they stay here as the end-to-end check.
    node = ConfidenceNode(
        context=context,
        namespace=f'review33_geometry_{os.getpid()}',
        parameter_overrides=[
            *SMALL_MLM,
            Parameter('downsample', value=factor),
            Parameter('confidence_threshold', value=0.0),
            Parameter('speckle_size', value=0),
            Parameter('subpixel', value='none'),
            Parameter('scan_frame_id', value='base_link'),
        ],
    )
    try:
        for name, variant in VARIANTS.items():
            try:
                _check(_outputs(node, variant), variant, factor)
            except AssertionError as error:
                raise AssertionError(f'{name}: {error}') from error
    finally:
        node.destroy_node()


P_LEFT = np.array([[100.0, 0.0, 50.0, 0.0], [0.0, 120.0, 40.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
P_RIGHT = P_LEFT + np.array([[0.0, 0.0, 0.0, -10.0], [0.0] * 4, [0.0] * 4])


@pytest.mark.parametrize('w', [2.0, 0.25])
def test_a_homogeneous_projection_gives_the_geometry_of_its_camera(w: float) -> None:
    # Was: fx, fy, cx, cy read off w·P as they stand (w = 2: fx 200, cx 100, depth twice).
    expected = StereoGeometry.from_projections(P_LEFT, P_RIGHT)
    assert StereoGeometry.from_projections(w * P_LEFT, w * P_RIGHT) == expected
    # One side scaled alone is the same pair of cameras (was: refused for fx 200 ≠ 100).
    assert StereoGeometry.from_projections(w * P_LEFT, P_RIGHT) == expected
    check_rows(w * P_LEFT, P_RIGHT)


def test_a_projection_that_is_no_rectified_camera_is_refused() -> None:
    # Was: the third row never read: (0, 0, 1, 5) (a forward baseline) or (0, 0, 0, 0) taken.
    for row in ([0.0, 0.0, 1.0, 5.0], [0.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0]):
        p_left = P_LEFT.copy()
        p_left[2] = row
        with pytest.raises(InputError, match=r'^P_left must have the third row \(0, 0, w, 0\)'):
            StereoGeometry.from_projections(p_left, P_RIGHT)


def test_the_published_info_of_a_homogeneous_one_is_read_right_as_entries() -> None:
    # Was: K and P published with their w (2): a consumer reading fx and cx as entries (as
    # image_geometry does) got twice the focal length and principal point of the images.
    variant = VARIANTS['homogeneous-p-binning-roi']
    left, _ = variant.infos()
    left.k = (np.array(left.k) * 4.0).tolist()
    for factor in (1, 2):
        out = scale_camera_info(image_camera_info(left, WIDTH, HEIGHT), factor, Header())
        fx, cx = FX / factor, (CX + 0.5) / factor - 0.5
        for matrix in (np.array(out.p).reshape(3, 4), np.array(out.k).reshape(3, 3)):
            assert matrix[2, 2] == 1.0
            assert (matrix[0, 0], matrix[0, 2]) == (pytest.approx(fx), pytest.approx(cx))


def test_a_baseline_not_above_zero_names_both_tx() -> None:
    # Was: 'P_right[0, 3] < 0 for a right camera' for P_right[0, 3] = −10 < 0, the left
    # camera at Tx −30 (right of the right one): the value it asked for.
    p_left = P_LEFT.copy()
    p_left[0, 3] = -30.0
    with pytest.raises(
        InputError,
        match=r'^baseline \(P_left\[0, 3\] − P_right\[0, 3\]\) / fx must be > 0 .*got '
        r'P_left\[0, 3\] = -30 and P_right\[0, 3\] = -10, -0\.2$',
    ):
        StereoGeometry.from_projections(p_left, P_RIGHT)

"""Review 32 of ``camera_info.py`` (the REP 104 reading of a camera info) and ``ros/common.py``:
regressions of the faults found in the review."""

from __future__ import annotations

from node_test_utils import info_msgs
import pytest
from sensor_msgs.msg import CameraInfo

from cva_confidence_ros import camera_info
from cva_confidence_ros.errors import InputError
from cva_confidence_ros.ros.convert import camera_info_to_geometry


def _with_roi(info: CameraInfo, x_offset: int, y_offset: int, width: int, height: int) -> None:
    info.roi.x_offset, info.roi.y_offset = x_offset, y_offset
    info.roi.width, info.roi.height = width, height


@pytest.mark.parametrize(
    ('roi', 'size'),
    [((8, 4, 0, 0), '0×0 at \\(8, 4\\)'), ((10, 0, 80, 0), '80×0 at \\(10, 0\\)'),
     ((0, 0, 0, 40), '0×40 at \\(0, 0\\)')],
    ids=['offset-only', 'zero-height', 'zero-width'],
)
def test_a_roi_with_a_zero_side_that_is_not_all_zeros_is_refused(
    roi: tuple[int, int, int, int], size: str
) -> None:
    # Only an ROI of all zeros is the whole image (REP 104, image_geometry, which reads a zero
    # side as no pixels); a zero side was read as "to the edge": ROI (8, 4, 0, 0) of a 96×64
    # calibration gave 88×60 images with cx 40, and frames of 88×60 were matched with it.
    left, right = info_msgs(0)
    for info in (left, right):
        _with_roi(info, *roi)
    with pytest.raises(
        InputError,
        match=rf'^left camera info: roi {size} must be all zeros \(the whole image\) or have '
        r'a width and height > 0 \(REP 104\)$',
    ):
        camera_info.image_projection(left, 'left camera info')
    if roi == (8, 4, 0, 0):
        with pytest.raises(InputError, match=r'^left camera info: roi 0×0 at \(8, 4\) must be'):
            camera_info_to_geometry(left, right, 88, 60)
    # Images of the calibration size still take P as it is, whatever the ROI says.
    size_full, projection = camera_info.image_projection(left, 'left camera info', (96, 64))
    assert size_full == (96, 64)
    assert projection[0, 2] == pytest.approx(48.0)
    # All zeros and the full window are the whole image, binned as it says.
    left.binning_x = left.binning_y = 2
    for whole in ((0, 0, 0, 0), (0, 0, 96, 64)):
        _with_roi(left, *whole)
        size_binned, projection = camera_info.image_projection(left, 'left camera info')
        assert size_binned == (48, 32)
        assert (projection[0, 0], projection[0, 2], projection[1, 2]) == (50.0, 24.0, 16.0)


def test_an_unset_calibration_size_is_named_as_such() -> None:
    # An info of width and height 0 (no ROI) was refused as "roi 0×0 at (0, 0) must lie
    # within its calibration size 0×0", about an ROI it does not have.
    left, _ = info_msgs(0, height=0, width=0)
    for image_size in (None, (96, 64)):
        with pytest.raises(
            InputError,
            match=r'^left camera info: calibration size \(width × height\) must be > 0; got 0×0',
        ):
            camera_info.image_projection(left, 'left camera info', image_size)

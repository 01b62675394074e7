"""Review 36: the images and camera infos real stereo drivers publish (ZED, RealSense, OAK-D,
Nerian, industrial cameras through image_proc)."""

from __future__ import annotations

import re

from node_test_utils import info_msgs
import pytest
from sensor_msgs.msg import Image

from cva_confidence_ros.errors import InputError
from cva_confidence_ros.ros.convert import camera_info_to_geometry, image_to_array

FX, BASELINE = 500.0, 0.12


def _image(encoding: str, channels: int, width: int = 6, height: int = 4) -> Image:
    step = width * channels
    return Image(
        height=height, width=width, encoding=encoding, is_bigendian=0, step=step,
        data=bytes(step * height),
    )


@pytest.mark.parametrize('encoding', ['bayer_rggb8', 'bayer_grbg8', 'bayer_bggr16'])
def test_a_raw_bayer_image_says_to_debayer_and_rectify(encoding: str) -> None:
    # Was: only "encoding must be one of (...)": an industrial camera's raw output gave no hint
    # that it is neither debayered nor rectified (image_proc / stereo_image_proc do both).
    with pytest.raises(InputError, match=r"got '" + encoding + r"': a raw Bayer .*image_proc"):
        image_to_array(_image(encoding, 2 if encoding.endswith('16') else 1), 'left image')


@pytest.mark.parametrize('encoding', ['yuv422', 'yuv422_yuy2', 'uyvy', 'yuyv'])
def test_a_yuv_image_says_to_convert_with_image_proc(encoding: str) -> None:
    with pytest.raises(InputError, match=r'a YUV camera format .*image_proc'):
        image_to_array(_image(encoding, 2), 'left image')


@pytest.mark.parametrize(('encoding', 'channels'), [('8UC3', 3), ('8UC4', 4)])
def test_an_opencv_colour_type_asks_for_a_named_channel_order(
    encoding: str, channels: int
) -> None:
    # cv_bridge's cv2_to_imgmsg(bgr_image) without an encoding publishes 8UC3: BGR or RGB is
    # not in the message (image_proc refuses it for that reason too).
    with pytest.raises(InputError, match=re.escape('publish the image as bgr8')):
        image_to_array(_image(encoding, channels), 'left image')


def _infos() -> tuple:
    return info_msgs(0, height=48, width=64, fx=FX, baseline=BASELINE)


@pytest.mark.parametrize('case', ['left twice', 'right tx unset'])
def test_a_baseline_of_zero_is_named_not_a_swapped_pair(case: str) -> None:
    # Was: "… must be > 0 (…; left and right swapped?)" for the left info published on both
    # topics or a right info without Tx (RealSense infra2 once): nothing was swapped.
    left, right = _infos()
    if case == 'left twice':
        right = left
    else:
        right.p[3] = 0.0
    with pytest.raises(InputError, match=r'^left and right camera infos have the same Tx '
                       r'\(P\[0, 3\] = 0\): a baseline of 0'):
        camera_info_to_geometry(left, right, 64, 48)


def test_a_positive_tx_names_the_driver_convention() -> None:
    # OAK-D drivers have published +fx·B.
    left, right = _infos()
    right.p[3] = FX * BASELINE
    with pytest.raises(InputError, match=r'P\[0, 3\] = 60 above .*a driver that writes \+fx·B'):
        camera_info_to_geometry(left, right, 64, 48)


@pytest.mark.parametrize(('tx', 'baseline'), [(-BASELINE, 0.00024), (-FX * 120.0, 120.0)])
def test_a_tx_in_another_unit_is_refused(tx: float, baseline: float) -> None:
    # Was: accepted: Tx = −B (metres, not −fx·B) gave a baseline of 0.24 mm and every depth
    # fx = 500 times too small; −fx·B with B in millimetres every depth 1000 times too large.
    for kept in (0.004, 0.05, 0.12, 1.5):  # endoscope, RealSense, ZED, a vehicle rig
        left, right = info_msgs(0, height=48, width=64, fx=FX, baseline=kept)
        assert camera_info_to_geometry(left, right, 64, 48).baseline == pytest.approx(kept)
    left, right = _infos()
    right.p[3] = tx
    with pytest.raises(InputError, match=rf'/ fx = {baseline:g} m is outside \[0\.001, 10\] m'):
        camera_info_to_geometry(left, right, 64, 48)


@pytest.mark.parametrize('side', ['left', 'right'])
def test_an_uncalibrated_camera_info_is_named(side: str) -> None:
    # Was: "focal lengths must be > 0; got fx=0.0, fy=0.0" (or "P_right[0, 0] (fx) …"): an
    # all-zero P is an uncalibrated camera or a driver that leaves P unset (depthai-ros once).
    left, right = _infos()
    info = left if side == 'left' else right
    info.p = [0.0] * 12
    with pytest.raises(InputError, match=rf'^{side} camera info has an all-zero projection'):
        camera_info_to_geometry(left, right, 64, 48)

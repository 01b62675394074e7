"""Review 33 of ``ros/convert.scale_camera_info``: the camera info of the downsampled outputs,
read as ``image_geometry`` reads it (REP 104), for inputs with binning and a region of interest.

A consumer folds an info as ``image_geometry``'s ``PinholeCameraModel`` does: the ROI offset
moved out of the principal point of the full-resolution K and P, then rows 0 and 1 divided by
the binning; the images are the ROI (all zeros = the whole) divided by the binning. The
pipeline shrinks by cropping to a multiple of the factor and averaging blocks, so a pixel
``x`` of the input is ``(x + 0.5) / factor − 0.5`` of the output.
"""

from __future__ import annotations

import numpy as np
import pytest
from sensor_msgs.msg import CameraInfo, RegionOfInterest
from std_msgs.msg import Header

from cva_confidence_ros.errors import InputError
from cva_confidence_ros.ros.convert import (
    camera_info_to_geometry,
    image_camera_info,
    scale_camera_info,
)

FX, CX, CY, BASELINE = 400.0, 331.3, 247.7, 0.1
POINTS = np.array([[0.3, -0.2, 2.0, 1.0], [-0.5, 0.4, 3.5, 1.0], [0.0, 0.0, 1.0, 1.0]])


def _info(
    binning: tuple[int, int] = (1, 1),
    roi: tuple[int, int, int, int] = (0, 0, 0, 0),
    tx: float = 0.0,
    homogeneous: float = 1.0,
) -> CameraInfo:
    """A rectified 640×480 calibration; ``roi`` = (x_offset, y_offset, width, height)."""
    k = np.array([[FX, 0.0, CX], [0.0, FX, CY], [0.0, 0.0, 1.0]]) * homogeneous
    p = np.array([[FX, 0.0, CX, tx], [0.0, FX, CY, 0.0], [0.0, 0.0, 1.0, 0.0]]) * homogeneous
    x0, y0, width, height = roi
    return CameraInfo(
        width=640,
        height=480,
        k=k.ravel().tolist(),
        r=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        p=p.ravel().tolist(),
        binning_x=binning[0],
        binning_y=binning[1],
        roi=RegionOfInterest(x_offset=x0, y_offset=y0, width=width, height=height),
    )


def _consumer(info: CameraInfo) -> tuple[np.ndarray, tuple[int, int]]:
    """(P, (width, height)) of the images an info describes, as ``image_geometry`` has them."""
    binning_x, binning_y = max(info.binning_x, 1), max(info.binning_y, 1)
    roi = info.roi
    width, height = roi.width, roi.height
    if (roi.x_offset, roi.y_offset, width, height) == (0, 0, 0, 0):
        width, height = info.width, info.height
    p = np.array(info.p, dtype=np.float64).reshape(3, 4)
    p[0, 2] -= roi.x_offset
    p[1, 2] -= roi.y_offset
    p[0] /= binning_x
    p[1] /= binning_y
    return p, (width // binning_x, height // binning_y)


def _project(p: np.ndarray) -> np.ndarray:
    pixels = POINTS @ p.T
    return pixels[:, :2] / pixels[:, 2:]


@pytest.mark.parametrize(
    ('binning', 'roi'),
    [
        ((2, 2), (0, 0, 0, 0)),
        ((1, 1), (7, 5, 402, 302)),
        ((2, 2), (8, 4, 402, 302)),
        ((2, 2), (3, 1, 402, 302)),
        ((4, 2), (6, 3, 400, 301)),
    ],
    ids=['binning-2', 'odd-roi', 'binning-2-even-roi', 'binning-2-odd-roi', 'binning-4x2-roi'],
)
def test_a_consumer_reads_the_shrunk_info_at_the_block_centres(
    binning: tuple[int, int], roi: tuple[int, int, int, int]
) -> None:
    # Was: K and P scaled as if they were the images' own, binning and ROI (offset // factor)
    # passed on, so image_geometry projected points up to 0.75 px (odd ROI offset, factor 4)
    # or 0.1875 px (binning 2, factor 4) away from where the shrunk image has them.
    info = _info(binning, roi)
    p_in, size_in = _consumer(info)
    pixels_in = _project(p_in)
    for factor in (2, 4, 1):
        out = scale_camera_info(info, factor, Header(frame_id='out'))
        p_out, size_out = _consumer(out)
        expected_size = (size_in[0] // factor, size_in[1] // factor)
        assert size_out == expected_size, factor
        np.testing.assert_allclose(
            _project(p_out), (pixels_in + 0.5) / factor - 0.5, atol=1e-9, err_msg=f'{factor}'
        )
        # Binning and ROI folded in: the info's own size is the shrunk images'.
        assert (out.width, out.height) == expected_size
        roi_out = out.roi
        assert (roi_out.x_offset, roi_out.y_offset, roi_out.width, roi_out.height) == (0, 0, 0, 0)
        assert max(out.binning_x, out.binning_y) <= 1
        # K is folded and shrunk the same way.
        np.testing.assert_allclose(np.array(out.k).reshape(3, 3), p_out[:, :3], atol=1e-12)


@pytest.mark.parametrize(
    ('binning', 'roi'),
    [((2, 2), (0, 0, 0, 0)), ((1, 1), (7, 5, 402, 302)), ((2, 2), (3, 1, 402, 302))],
)
def test_the_node_reads_its_own_output_info_as_the_output_geometry(
    binning: tuple[int, int], roi: tuple[int, int, int, int]
) -> None:
    # Reading the published infos back (camera_info_to_geometry at the output size) gives the
    # geometry the node triangulates the outputs with (the input's, scaled by 1/factor). Was:
    # cx 0.125 … 0.75 px off, or the infos refused for their size.
    left, right = _info(binning, roi), _info(binning, roi, tx=-FX * BASELINE)
    _, size = _consumer(left)
    geometry = camera_info_to_geometry(left, right, *size)
    for factor in (2, 4):
        outs = [scale_camera_info(info, factor, Header()) for info in (left, right)]
        read = camera_info_to_geometry(outs[0], outs[1], size[0] // factor, size[1] // factor)
        expected = geometry.scaled(1.0 / factor)
        for name in ('fx', 'fy', 'cx', 'cy', 'cx_right', 'baseline'):
            assert getattr(read, name) == pytest.approx(getattr(expected, name), abs=1e-9), name
        # The node's own path (the info folded to the images first) publishes the same.
        node = scale_camera_info(image_camera_info(left, *size), factor, Header())
        np.testing.assert_allclose(node.p, outs[0].p, atol=1e-12)
        assert (node.width, node.height) == (outs[0].width, outs[0].height)


def test_an_roi_smaller_than_the_factor_is_refused() -> None:
    # Was: ROI 3×3 at (2, 1) shrunk by 4 became an all-zero ROI, which REP 104 reads as the
    # whole 160×120 sensor, for images of no pixel.
    with pytest.raises(InputError, match='3×3 px leaves no pixel when shrunk by 4'):
        scale_camera_info(_info(roi=(2, 1, 3, 3)), 4, Header())


def test_an_roi_outside_the_calibration_is_refused() -> None:
    # Was: shrunk and published as it was (ROI 320×120 at (200, 0) of a 320×240 calibration).
    with pytest.raises(InputError, match=r'roi 640×240 at \(400, 0\) must lie within'):
        scale_camera_info(_info(roi=(400, 0, 640, 240)), 2, Header())


def test_a_homogeneously_scaled_projection_is_shrunk_exactly() -> None:
    # P and K are homogeneous: 2·P projects as P does. Was: the half-pixel shift added to
    # P[0, 2] unweighted, 0.125 px off at factor 2 for a P whose third row is (0, 0, 2, 0).
    info = _info(homogeneous=2.0)
    expected = (_project(_consumer(info)[0]) + 0.5) / 2 - 0.5
    out = scale_camera_info(info, 2, Header())
    np.testing.assert_allclose(_project(_consumer(out)[0]), expected, atol=1e-9)

"""REP 104 reading of a rectified camera info, shared by the node and the bag tools.

A ``sensor_msgs/CameraInfo`` gives the calibration (full sensor) size as ``width`` ×
``height``, the window that was read as ``roi`` (all zeros = the whole) and the binning of
that window as ``binning_x`` × ``binning_y`` (0 and 1 = none); the images are the window
divided by the binning. P (and K) are for the full resolution, so they are folded as
``image_geometry`` (and so ``stereo_image_proc``) folds them: the ROI offset moved out of the
principal point, then rows 0 and 1 divided by the binning. ``roi.do_rectify`` does not change
that (``image_geometry`` shifts P by the raw ROI either way).

Only message fields are read, so rclpy and ``rosbags`` messages both work; nothing here
imports ROS.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from cva_confidence_ros.errors import InputError
from cva_confidence_ros.pointcloud import FX_TOLERANCE, unit_projection

#: Largest difference of cy between the left and right projection matrices, pixels: a
#: rectified pair has one cy; this only absorbs float and text round-off.
CY_TOLERANCE_PX = 0.1


def _projection(values: Any, name: str) -> np.ndarray:
    """``values`` as a 3×4 float64 projection matrix; ``name`` says whose in the error."""
    array = np.array(values, dtype=np.float64)
    if array.size != 12:
        raise InputError(f'{name} must be a 3×4 projection matrix (12 values); got {array.size}')
    return array.reshape(3, 4)


def fold(matrix: np.ndarray, info: Any) -> np.ndarray:
    """K (3×3) or P (3×4) of ``info`` with its ROI offset moved out of the principal point and
    rows 0 and 1 divided by its binning (``image_geometry``'s rule), in place."""
    matrix[0, 2] -= int(info.roi.x_offset) * matrix[2, 2]
    matrix[1, 2] -= int(info.roi.y_offset) * matrix[2, 2]
    matrix[0] /= max(int(info.binning_x), 1)
    matrix[1] /= max(int(info.binning_y), 1)
    return matrix


def image_projection(
    info: Any, name: str, image_size: tuple[int, int] | None = None
) -> tuple[tuple[int, int], np.ndarray]:
    """``((width, height), P)`` of the images a camera info describes, P folded (3×4) and,
    homogeneous, scaled to ``P[2, 2] = 1`` where its third row is ``(0, 0, w > 0, 0)``.

    Images of the info's own calibration size (``image_size`` = (width, height), when known)
    take P as it is, whatever binning and ROI say: P is always for the full resolution
    (REP 104), so that reading is right either way, and drivers that fill the ROI with the
    valid rectified area of full-size images keep working (``image_geometry`` would shift
    their points by the ROI offset). Any other size must be the one binning and ROI describe.

    Raises:
        InputError: A P that is not 12 values, a calibration size of 0, an ROI that is
            neither all zeros nor of a width and height > 0 or that does not lie within the
            calibration size, a binning that leaves no pixels of it, or (``image_size`` given)
            images that are not the size the info describes; ``name`` says whose info.
    """
    full_w, full_h = int(info.width), int(info.height)
    projection = _projection(info.p, f'{name} p')
    if image_size is not None and tuple(image_size) == (full_w, full_h):
        return (full_w, full_h), unit_projection(projection)
    if full_w <= 0 or full_h <= 0:
        raise InputError(
            f'{name}: calibration size (width × height) must be > 0; got {full_w}×{full_h} '
            '(an unset camera info?)'
        )
    binning_x, binning_y = max(int(info.binning_x), 1), max(int(info.binning_y), 1)
    roi = info.roi
    x0, y0 = int(roi.x_offset), int(roi.y_offset)
    crop_w, crop_h = int(roi.width), int(roi.height)
    if (x0, y0, crop_w, crop_h) == (0, 0, 0, 0):
        crop_w, crop_h = full_w, full_h
    elif crop_w <= 0 or crop_h <= 0:
        # Only an ROI of all zeros is the whole (REP 104, image_geometry): a zero width or
        # height in any other is a window of no pixels, not one "to the edge".
        raise InputError(
            f'{name}: roi {crop_w}×{crop_h} at ({x0}, {y0}) must be all zeros (the whole '
            'image) or have a width and height > 0 (REP 104)'
        )
    whole = (binning_x, binning_y, x0, y0, crop_w, crop_h) == (1, 1, 0, 0, full_w, full_h)
    if image_size is not None and whole:
        width, height = image_size
        raise InputError(f'{name} must be for {width}×{height} images; got {full_w}×{full_h}')
    if x0 + crop_w > full_w or y0 + crop_h > full_h:
        raise InputError(
            f'{name}: roi {int(roi.width)}×{int(roi.height)} at ({x0}, {y0}) must lie within '
            f'its calibration size {full_w}×{full_h} (REP 104)'
        )
    size = (crop_w // binning_x, crop_h // binning_y)
    if 0 in size:
        raise InputError(
            f'{name}: binning {binning_x}×{binning_y} leaves no pixels of its {crop_w}×{crop_h} '
            f'region of interest (images of {size[0]}×{size[1]})'
        )
    if image_size is not None and size != tuple(image_size):
        width, height = image_size
        raise InputError(
            f'{name} must be for {width}×{height} images; got {size[0]}×{size[1]} (binning '
            f'{info.binning_x}×{info.binning_y} and region of interest {roi.width}×'
            f'{roi.height} at ({x0}, {y0}) of its {full_w}×{full_h})'
        )
    return size, unit_projection(fold(projection, info))


def check_rows(p_left: Any, p_right: Any) -> None:
    """Refuse projection matrices (3×4 or 12 values) whose rows do not correspond: a
    rectified pair shares fy and cy and has no vertical baseline (``P[1, 3]``, Ty, the same
    on both: 0 for a horizontal pair), or the matcher compares the wrong rows.

    Raises:
        InputError: Not 12 values, values that are not finite, or rows that do not correspond.
    """
    left = unit_projection(_projection(p_left, 'P_left'))
    right = unit_projection(_projection(p_right, 'P_right'))
    if not (np.all(np.isfinite(left)) and np.all(np.isfinite(right))):
        raise InputError(
            f'projection matrices must be finite; got P_left = {left.tolist()} and '
            f'P_right = {right.tolist()}'
        )
    fy_left, fy_right = float(left[1, 1]), float(right[1, 1])
    if fy_left > 0 and abs(fy_right - fy_left) > FX_TOLERANCE * fy_left:
        raise InputError(
            'left and right projection matrices must share fy (a rectified pair); got '
            f'P_left[1, 1] = {fy_left:g} and P_right[1, 1] = {fy_right:g}'
        )
    cy_left, cy_right = float(left[1, 2]), float(right[1, 2])
    if abs(cy_right - cy_left) > CY_TOLERANCE_PX:
        raise InputError(
            'left and right projection matrices must share cy (a rectified pair: row v of '
            f'one image is row v of the other); got P_left[1, 2] = {cy_left:g} and '
            f'P_right[1, 2] = {cy_right:g}'
        )
    # A point at depth Z is (Ty_right − Ty_left) / Z rows lower in the right image, at the
    # disparity (Tx_left − Tx_right) / Z: refuse a row shift over 0.1 px per 100 px of it.
    ty_left, ty_right = float(left[1, 3]), float(right[1, 3])
    tx_span = abs(float(left[0, 3]) - float(right[0, 3]))
    if abs(ty_right - ty_left) > FX_TOLERANCE * tx_span:
        raise InputError(
            'left and right projection matrices must share Ty (a horizontal rectified pair: '
            'no vertical baseline, P[1, 3] = 0); got P_left[1, 3] = '
            f'{ty_left:g} and P_right[1, 3] = {ty_right:g}'
        )

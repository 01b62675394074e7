"""README claims from "Run it on a robot" to "What a confidence of 0.8 means", against the code.

Each test pins a sentence that said something the code does not do, next to the behaviour the
corrected sentence describes.
"""

from __future__ import annotations

from pathlib import Path
import re

import cv2
import numpy as np
from std_msgs.msg import Header

from cva_confidence_ros.mask import load_mask
from cva_confidence_ros.pointcloud import StereoGeometry
from cva_confidence_ros.ros.convert import depth_to_image
from cva_confidence_ros.ros.transport import (
    compressed_depth_to_array,
    depth_image_to_compressed_depth,
)
from cva_confidence_ros.scan import ScanConfig, disparity_to_scan

README = Path(__file__).resolve().parent.parent / 'README.md'


def _readme() -> str:
    """The README with its line breaks and runs of spaces as single spaces."""
    return re.sub(r'\s+', ' ', README.read_text(encoding='utf-8'))


def test_scan_beam_with_points_too_near_and_too_far_is_minus_inf():
    # One beam (the centre column) sees a point nearer than range_min and one beyond
    # range_max, none in range: −inf (too close), which the README called "all nearer".
    geometry = StereoGeometry(fx=100.0, fy=100.0, cx=1.5, cy=0.0, cx_right=1.5, baseline=0.1)
    disparity = np.full((2, 4), np.nan, np.float32)
    disparity[0, 2] = 10.0 / 0.05  # z = fx·B / d = 0.05 m, nearer than range_min 0.1
    disparity[1, 2] = 10.0 / 30.0  # z = 30 m (0.3 m below the camera), beyond range_max 20
    scan = disparity_to_scan(disparity, geometry, config=ScanConfig(min_height=-1, max_height=1))
    assert np.isneginf(scan.ranges).sum() == 1
    assert not np.isposinf(scan.ranges).any()
    text = _readme()
    assert '−inf where all are nearer than `scan_range_min`' not in text
    assert '−inf where none is in range and one or more are nearer than `scan_range_min`' in text


def test_compressed_depth_error_is_about_not_within_the_readme_bound():
    # Truncating A / z + B to an integer code returns up to z² / (A − z), a little more than
    # z² / A: 0.09 % over it near 10 m, so the README's bound is "about", not "within".
    q = 100.0
    a = q * (q + 1.0)
    depth = np.linspace(9.0, 9.99, 20000, dtype=np.float32)[None]
    message = depth_image_to_compressed_depth(depth_to_image(depth, Header(), '32FC1'))
    error = np.abs(compressed_depth_to_array(message).astype(np.float64) - depth)
    z = depth.astype(np.float64)
    assert (error > z**2 / a).any()
    assert (error <= z**2 / (a - z) * (1 + 1e-6)).all()
    text = _readme()
    assert 'comes back within about z² / (q·(q + 1)) m' in text
    assert 'comes back within z² / (q·(q + 1)) m' not in text


def test_mask_opaque_black_rgba_pixel_is_ignored(tmp_path):
    # An image editor's black in an RGBA PNG is (0, 0, 0, 255): not 0 in every channel, yet
    # ignored, since the alpha channel is not looked at.
    image = np.full((4, 6, 4), 255, np.uint8)
    image[0, 0] = (0, 0, 0, 255)
    image[1, 1] = (0, 0, 0, 0)
    image[2, 2] = (0, 0, 255, 0)  # a colour, transparent: judged
    path = tmp_path / 'mask.png'
    assert cv2.imwrite(str(path), image)
    keep = load_mask(path)
    assert not keep[0, 0] and not keep[1, 1] and keep[2, 2]
    assert int((~keep).sum()) == 2
    text = _readme()
    assert 'black (0 in every channel)' not in text
    assert 'black (0 in every colour channel, alpha aside)' in text

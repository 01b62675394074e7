"""The numba kernel of :func:`cva_confidence_ros.scan.disparity_to_scan`, apart so that the
parameter checks (``ScanConfig``, imported by ``cva-node --help``) do not load numba."""

from __future__ import annotations

import math

from numba import njit
import numpy as np

__all__ = ['scan_kernel']


# One pass over the pixels. ``state`` per beam: 0 nothing, 1 a point beyond range_max, 2 a
# point nearer than range_min (wins over 1), 3 a point in range (``best`` holds the nearest).
@njit(cache=True)
def scan_kernel(
    disparity: np.ndarray,
    keep: np.ndarray,
    confidence: np.ndarray,
    params: np.ndarray,
    best: np.ndarray,
    intensity: np.ndarray,
    state: np.ndarray,
) -> None:
    fx, fy, cx, cy, offset, depth_scale = (
        params[0], params[1], params[2], params[3], params[4], params[5]
    )
    sin_p, cos_p, min_h, max_h, r_min, r_max = (
        params[6], params[7], params[8], params[9], params[10], params[11]
    )
    angle_min, inverse_increment = params[12], params[13]
    beams = best.shape[0]
    height, width = disparity.shape
    for v in range(height):
        for u in range(width):
            if not keep[v, u]:
                continue
            shifted = disparity[v, u] + offset
            if not shifted > 0.0:  # NaN too
                continue
            z = depth_scale / shifted
            x = (u - cx) * z / fx
            y = (v - cy) * z / fy
            y_level = y * cos_p + z * sin_p
            z_level = z * cos_p - y * sin_p
            up = -y_level
            if up < min_h or up > max_h or not z_level > 0.0:
                continue
            beam = int(math.floor((math.atan2(-x, z_level) - angle_min) * inverse_increment + 0.5))
            if beam < 0 or beam >= beams:
                continue
            distance = math.sqrt(x * x + z_level * z_level)
            if distance > r_max:
                if state[beam] == 0:
                    state[beam] = 1
            elif distance < r_min:
                if state[beam] < 2:
                    state[beam] = 2
            elif distance < best[beam]:
                best[beam] = distance
                intensity[beam] = confidence[v, u]
                state[beam] = 3

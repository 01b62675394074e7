"""Review 35: the node's outputs as mapping and navigation consumers read them."""

from __future__ import annotations

import numpy as np
import pytest

from cva_confidence_ros.errors import InputError
from cva_confidence_ros.pointcloud import filter_cloud

_XYZ = [('x', '<f4'), ('y', '<f4'), ('z', '<f4')]


def test_filter_cloud_refuses_a_confidence_in_percent() -> None:
    # Another producer's confidence in [0, 100]: every point passed threshold 0.8, silently.
    cloud = np.zeros(4, np.dtype([*_XYZ, ('confidence', '<f4')]))
    cloud['z'] = 1.0
    cloud['confidence'] = [12.5, 87.0, 99.0, 3.0]
    with pytest.raises(InputError, match=r"'confidence'.*\[0, 1\].*4 points.*3 to 99.*percent"):
        filter_cloud(cloud, 0.8, organized=False)


def test_filter_cloud_refuses_a_negative_confidence_but_not_at_dropped_points() -> None:
    cloud = np.zeros(3, np.dtype([*_XYZ, ('confidence', 'i1')]))
    cloud['z'] = [1.0, np.nan, 1.0]
    cloud['confidence'] = [127, -128, 64]  # -128 lies at a point without x, y, z: no matter
    assert filter_cloud(cloud, 0.5, organized=False)['confidence'].tolist() == [127, 64]
    cloud['confidence'][2] = -1
    with pytest.raises(InputError, match=r'\[0, 1\].*1 points'):
        filter_cloud(cloud, 0.0)
    # NaN stays allowed: never kept, as before.
    floats = np.zeros(2, np.dtype([*_XYZ, ('confidence', '<f4')]))
    floats['confidence'] = [np.nan, 1.0]
    assert filter_cloud(floats, 0.0, organized=False)['confidence'].tolist() == [1.0]

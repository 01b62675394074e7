"""Review 32 of datasets.synthetic and datasets.io: depth of unknown disparities, what
write_pfm accepts."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cva_confidence_ros.datasets.io import Calibration, read_pfm, write_pfm
from cva_confidence_ros.errors import DataError


def test_depth_of_an_infinite_disparity_is_unknown() -> None:
    # Middlebury PFMs store inf for unknown disparities (read_pfm returns them as stored):
    # fx * baseline / inf gave a depth of 0 m, a point on the camera, instead of NaN.
    calib = Calibration(fx=100.0, fy=100.0, cx=0.0, cy=0.0, baseline=0.1, doffs=2.0)
    depth = calib.depth(np.array([np.inf, -np.inf, np.nan, 8.0, -2.0], np.float32))
    assert depth.dtype == np.float32
    np.testing.assert_array_equal(depth, [np.nan, np.nan, np.nan, 1.0, np.nan])


@pytest.mark.parametrize(
    'array',
    [np.full((2, 3), 1 + 2j), np.array([['a', 'b']]), np.array([[1.0, None]], dtype=object)],
)
def test_write_pfm_refuses_arrays_that_are_not_real_numbers(tmp_path: Path, array) -> None:
    # A complex map lost its imaginary part (a ComplexWarning only) and was written; strings
    # and objects raised a bare ValueError / TypeError instead of DataError.
    with pytest.raises(DataError, match=f'PFM holds real numbers; got dtype {array.dtype}'):
        write_pfm(tmp_path / 'x.pfm', array)
    assert not (tmp_path / 'x.pfm').exists()


def test_write_pfm_refuses_finite_values_beyond_float32(tmp_path: Path) -> None:
    # 1e300 (float64) was written as inf, which reads back as 'unknown', with a RuntimeWarning.
    with pytest.raises(DataError, match=r'1 finite value\(s\) beyond .* \(largest 1e\+300\)'):
        write_pfm(tmp_path / 'x.pfm', np.array([[1.0, -1e300], [np.inf, 2.0]]))
    assert not (tmp_path / 'x.pfm').exists()
    # NaN and ±inf themselves are written as they are, as are ints and bools.
    stored = np.array([[np.nan, np.inf], [-np.inf, 3.4e38]])
    write_pfm(tmp_path / 'y.pfm', stored)
    np.testing.assert_array_equal(read_pfm(tmp_path / 'y.pfm'), stored.astype(np.float32))
    write_pfm(tmp_path / 'z.pfm', np.array([[True, False, True]]))
    np.testing.assert_array_equal(read_pfm(tmp_path / 'z.pfm'), [[1.0, 0.0, 1.0]])


@pytest.mark.parametrize('scale', ['1', None, True, [1.0]])
def test_write_pfm_scale_of_the_wrong_type_is_a_data_error(tmp_path: Path, scale) -> None:
    # '1' and None raised a bare TypeError from the comparison; True wrote the header '-1'.
    with pytest.raises(DataError, match='PFM scale must be finite and > 0; got '):
        write_pfm(tmp_path / 'x.pfm', np.ones((2, 2)), scale)
    assert not (tmp_path / 'x.pfm').exists()
    write_pfm(tmp_path / 'y.pfm', np.ones((2, 2)), np.float32(0.5))
    assert (tmp_path / 'y.pfm').read_bytes().startswith(b'Pf\n2 2\n-0.5\n')

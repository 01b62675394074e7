"""Review 32: reliability bins of float32 / float16 confidences at the edges, masks of
expected_error that are no bool or number."""

from __future__ import annotations

import numpy as np
import pytest

from cva_confidence_ros.calibration import ReliabilityTable, expected_error, reliability
from cva_confidence_ros.errors import InputError


@pytest.mark.parametrize(
    ('dtype', 'low', 'high'), [(np.float32, 0.7, 0.9), (np.float16, 0.1, 0.9)]
)
def test_a_low_precision_confidence_at_an_edge_is_in_the_bin_the_node_keeps(
    dtype, low, high
) -> None:
    # float32(0.7) and float32(0.9) lie a little below 0.7 and 0.9: they were binned into
    # [0.6, 0.7) and [0.8, 0.9), and kept_at(0.7) said no pixel is kept, while the node
    # (confidence >= np.float32(threshold)) keeps both at 0.7 and one at 0.9.
    confidence = np.array([low, high, 0.3], dtype=dtype)
    assert float(confidence[0]) < low and float(confidence[1]) < high
    table = reliability(confidence, np.array([True, False, True]))
    expected = np.zeros(10, np.int64)
    np.add.at(expected, [round(low * 10), round(high * 10), 3], 1)
    assert table.counts.tolist() == expected.tolist()
    for threshold in (low, high):
        kept = float(np.mean(confidence >= dtype(threshold)))
        assert table.kept_at(threshold)[0] == pytest.approx(kept)
    # The bin's mean lies just below its edge; the JSON form still reads back.
    again = ReliabilityTable.from_dict(table.as_dict())
    assert again.counts.tolist() == table.counts.tolist()
    assert again.ece == pytest.approx(table.ece)
    # float64 confidences keep their bins: 0.5 and 0.7 start theirs, 1.0 is in the last one.
    table = reliability(np.array([0.5, 0.7, 1.0, 0.0]), np.array([True, True, False, False]))
    assert table.counts.tolist() == [1, 0, 0, 0, 0, 1, 0, 1, 0, 1]


@pytest.mark.parametrize(
    'mask',
    [np.array(['True', 'False']), np.array([None, 1], dtype=object), np.array([1j, 0j])],
)
def test_expected_error_refuses_a_mask_that_is_no_bool_or_number(mask) -> None:
    # Cast to bool, the string 'False' selected its pixel: 0.85 instead of 0.9.
    with pytest.raises(InputError, match=rf'mask must be a bool array; got dtype {mask.dtype}'):
        expected_error(np.array([0.1, 0.2]), mask)
    assert expected_error(np.array([0.1, 0.2]), np.array([1, 0], np.uint8)) == pytest.approx(0.9)

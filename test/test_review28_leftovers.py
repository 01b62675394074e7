"""Review 28: leftovers of the earlier reviews (each a regression test of a fault found there):
the synchroniser's reset counts what it lets go, plots of 16-bit images and NaN error maps,
NaN in an expected-error mask, one string as Table 1's method columns, a whole float as the
count of synthetic pairs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cva_confidence_ros.calibration import expected_error
from cva_confidence_ros.errors import InputError
from cva_confidence_ros.evaluation.records import EvalRecord, format_table
from cva_confidence_ros.plots import CORRECT_RGB, WRONG_RGB, save_correctness_overlay
from cva_confidence_ros.sync import StampSynchronizer


def test_reset_counts_the_messages_it_lets_go() -> None:
    # reset() forgot the waiting messages without counting them: 3 received, 0 matched,
    # 0 dropped, none waiting.
    sync = StampSynchronizer(('left', 'right'), record_drops=True)
    sync.add('left', 10, 'a')
    sync.add('left', 20, 'b')
    sync.add('right', 30, 'c')
    sync.reset()
    assert sync.pending() == {'left': 0, 'right': 0}
    assert (sync.matched, sync.dropped) == (0, 3)
    assert [(d.key, d.stamp_ns, d.kind) for d in sync.take_drops()] == [
        ('left', 10, 'unmatched'), ('left', 20, 'unmatched'), ('right', 30, 'unmatched')
    ]
    # Forgotten stamps: an older pair is matched afresh, not refused as late.
    assert len(sync.add('left', 5, 'd')) == 0
    assert [m.stamp_ns for m in sync.add('right', 5, 'e')] == [5]
    assert (sync.matched, sync.dropped) == (1, 3)


def _read_png(path: Path) -> np.ndarray:
    from matplotlib.image import imread

    return np.round(imread(path)[..., :3] * 255).astype(np.uint8)


def test_a_16_bit_background_is_scaled_not_clipped(tmp_path: Path) -> None:
    # A mono16 image (12 bits used) clipped at 255: a uniform grey sheet under the classes.
    ramp = np.tile(np.linspace(0, 4095, 8).astype(np.uint16), (4, 1))
    confidence = np.full((4, 8), 0.9)
    mask = np.zeros((4, 8), bool)
    path = save_correctness_overlay(confidence, np.zeros((4, 8), bool), tmp_path / 'o.png',
                                    image=ramp, mask=mask)
    gray = _read_png(path)[0, :, 0]
    assert gray[0] == 0 and gray[-1] == 127  # dimmed to half: 255 * 0.5, truncated
    assert np.all(np.diff(gray.astype(int)) > 0)
    # A float image beyond 255 the same way; uint8 and [0, 1] floats as before.
    as_float = _read_png(save_correctness_overlay(
        confidence, np.zeros((4, 8), bool), tmp_path / 'f.png', image=ramp.astype(float),
        mask=mask))[0, :, 0]
    np.testing.assert_array_equal(as_float, gray)
    eight = _read_png(save_correctness_overlay(
        confidence, np.zeros((4, 8), bool), tmp_path / 'u8.png',
        image=np.full((4, 8), 200, np.uint8), mask=mask))
    assert np.all(eight == 100)


def test_nan_in_a_float_error_map_is_not_judged(tmp_path: Path) -> None:
    # NaN cast to bool is True: an unjudged pixel was drawn as a wrong disparity.
    confidence = np.array([[0.9, 0.9, 0.1]])
    error = np.array([[0.0, np.nan, 1.0]])
    rgb = _read_png(save_correctness_overlay(confidence, error, tmp_path / 'o.png'))
    assert tuple(rgb[0, 0]) == tuple(CORRECT_RGB)
    assert tuple(rgb[0, 1]) == (0, 0, 0)  # background: no image
    assert tuple(rgb[0, 2]) == tuple(CORRECT_RGB)  # wrong and not confident
    flipped = _read_png(save_correctness_overlay(1 - confidence, error, tmp_path / 'p.png'))
    assert tuple(flipped[0, 0]) == tuple(WRONG_RGB)
    assert tuple(flipped[0, 1]) == (0, 0, 0)


def test_expected_error_refuses_nan_in_its_mask() -> None:
    confidence = np.array([0.9, 0.5, 0.1])
    # NaN was cast to True: the pixel counted as selected.
    with pytest.raises(InputError, match='^mask must be a bool array; got NaN in a float mask$'):
        expected_error(confidence, np.array([1.0, np.nan, 0.0]))
    assert expected_error(confidence, np.array([1.0, 0.0, 1.0])) == pytest.approx(0.5)
    assert expected_error(confidence, np.array([True, False, False])) == pytest.approx(0.1)


def test_format_table_refuses_one_string_as_its_methods() -> None:
    record = EvalRecord(dataset='kitti2012', scene='000000', matcher='census_bm',
                        method='mlm', auc=0.05, auc_opt=0.02, error_rate=0.2, n_pixels=100)
    # 'mlm' made the columns m, l, m (all '–').
    with pytest.raises(InputError, match="^methods must be a sequence of method names; got 'mlm'"):
        format_table([record], methods='mlm')
    with pytest.raises(InputError, match='must be a sequence of method names'):
        format_table([record], methods=['mlm', 3])  # type: ignore[list-item]
    assert '| mlm |' in format_table([record], methods=['mlm'])


def test_synthetic_pairs_takes_a_whole_float_and_refuses_other_counts() -> None:
    # synthetic_pairs(2.0) raised a bare TypeError from range(); '2' and True passed the check.
    from cva_confidence_ros.datasets.synthetic import synthetic_pairs
    from cva_confidence_ros.errors import ConfigError

    assert len(synthetic_pairs(2.0, height=32, width=48, max_disparity=8)) == 2
    assert len(synthetic_pairs(np.int64(1), height=32, width=48, max_disparity=8)) == 1
    for bad in (1.5, float('nan'), -1, '2', True):
        with pytest.raises(ConfigError, match='^count must be a whole number >= 0; got '):
            synthetic_pairs(bad)  # type: ignore[arg-type]

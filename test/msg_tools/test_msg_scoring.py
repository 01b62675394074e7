"""The replay report's per-frame statistics that need no ground truth, and its plot spacing."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cva_confidence_ros.errors import InputError
from msg_tools.scoring import FRAME_KEYS, ReplayReport, ReportWriter, score_frame


def _frame() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    disparity = np.full((4, 5), 3.0, np.float32)
    disparity[0, :] = np.nan  # no disparity: left out of the mean confidence
    confidence = np.linspace(0.0, 1.0, 20, dtype=np.float32).reshape(4, 5)
    kept = np.isfinite(disparity) & (confidence >= 0.5)
    return disparity, confidence, kept


def test_a_frame_without_ground_truth_has_the_diagnostics_numbers() -> None:
    disparity, confidence, kept = _frame()
    score = score_frame(7, 11, disparity, confidence, kept, None, probabilistic=True)
    assert score.note == 'no ground truth' and score.auc is None and score.n_pixels == 0
    assert score.kept_fraction == pytest.approx(kept.mean())
    assert score.mean_confidence == pytest.approx(confidence[1:].mean())
    assert score.predicted_kept_error == pytest.approx(1.0 - confidence[kept].mean())
    record = score.as_dict()
    assert all(key in record for key in FRAME_KEYS)
    # A method whose values are no probability predicts nothing.
    score = score_frame(7, 11, disparity, confidence, kept, None)
    assert score.predicted_kept_error is None and score.kept_fraction == pytest.approx(0.5)
    # Nothing kept: no prediction, a share of 0; nothing with a disparity: no mean.
    score = score_frame(0, 0, np.full((4, 5), np.nan, np.float32), confidence,
                        np.zeros((4, 5), bool), None, probabilistic=True)
    assert (score.kept_fraction, score.predicted_kept_error, score.mean_confidence) == (
        0.0, None, None)


def test_shapes_are_checked_without_ground_truth_too() -> None:
    disparity, confidence, kept = _frame()
    with pytest.raises(InputError, match=r'kept must have the disparity shape \(4, 5\)'):
        score_frame(0, 0, disparity, confidence, kept[:, :3], None)


def test_the_extreme_frames_are_the_earliest_of_equal_ones() -> None:
    disparity, confidence, kept = _frame()
    report = ReplayReport()
    for frame, share in enumerate((0.6, 0.2, 0.9, 0.2)):
        mask = np.zeros(20, bool)
        mask[: round(20 * share)] = True
        report.frames.append(score_frame(frame, frame, disparity, confidence,
                                         mask.reshape(4, 5), None, probabilistic=True))
    summary = report.summary()
    assert (summary['min_kept_fraction'], summary['min_kept_fraction_frame']) == (0.2, 1)
    assert report.least_kept() is report.frames[1]
    # Keeping the first rows (low confidence) predicts the most error with the fewest pixels.
    assert summary['max_predicted_kept_error_frame'] == 1
    assert summary['kept_fraction'] == pytest.approx(np.mean([0.6, 0.2, 0.9, 0.2]))


@pytest.mark.parametrize(('expected', 'max_plots', 'drawn'), [
    (25, 10, list(range(0, 25, 3))),  # every third frame spans the bag
    (5, 10, [0, 1, 2, 3, 4]),
    (0, 3, [0, 1, 2]),  # length unknown: the first ones
    (100, 0, []),
])
def test_plots_are_spread_over_the_bag(
    tmp_path: Path, expected: int, max_plots: int, drawn: list[int]
) -> None:
    writer = ReportWriter(tmp_path / 'r', max_plots, expected)
    disparity, confidence, kept = _frame()
    image = np.full((4, 5), 90, np.uint8)
    for frame in range(expected or 10):
        score = score_frame(frame, frame, disparity, confidence, kept, None)
        writer.frame_plots(score, confidence, 'test', kept=kept, image=lambda: image)
    assert sorted(int(p.stem.split('_')[1]) for p in (tmp_path / 'r').glob('overlay_*.png')) \
        == drawn
    assert len(list((tmp_path / 'r').glob('confidence_0*.png'))) == len(drawn)

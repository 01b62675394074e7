"""Review 32: scoring of replayed frames (``msg_tools.scoring``) and Ctrl-C (``progress``)."""

from __future__ import annotations

import os
from pathlib import Path
import signal

import numpy as np
import pytest

from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.evaluation import score_confidence
from msg_tools.progress import GracefulInterrupt
from msg_tools.scoring import (
    ReplayReport,
    ReportWriter,
    check_report_folder,
    clear_report,
    score_frame,
)


def _frame(height: int = 4, width: int = 5) -> tuple[np.ndarray, ...]:
    gt = np.full((height, width), 10.0, dtype=np.float32)
    confidence = np.full((height, width), 0.5, dtype=np.float32)
    kept = np.ones((height, width), dtype=bool)
    return gt.copy(), confidence, kept, gt


def test_a_report_file_name_that_is_a_link_is_refused(tmp_path: Path) -> None:
    # A link named report.csv was neither the report's (not deleted) nor refused: with
    # --overwrite the new report.csv was written through it, into another run's file.
    other = tmp_path / 'other_run'
    other.mkdir()
    (other / 'report.csv').write_text('precious\n', encoding='utf-8')
    folder = tmp_path / 'report'
    folder.mkdir()
    (folder / 'report.json').write_text('{}\n', encoding='utf-8')
    os.symlink(other / 'report.csv', folder / 'report.csv')
    with pytest.raises(ConfigError, match=r'holds report\.csv, which is a symbolic link; a '
                                          r'report writes a file of that name'):
        check_report_folder(folder, overwrite=True)
    assert (other / 'report.csv').read_text(encoding='utf-8') == 'precious\n'
    # A link named report.json alone was "no report.json; it has report.json".
    lone = tmp_path / 'lone'
    lone.mkdir()
    os.symlink(other / 'report.csv', lone / 'report.json')
    with pytest.raises(ConfigError, match=r'holds report\.json, which is a symbolic link'):
        check_report_folder(lone, overwrite=True)


def test_a_folder_of_a_report_file_name_is_refused_before_the_run(tmp_path: Path) -> None:
    # It was accepted with --overwrite, and the report failed to write at the end of the run.
    folder = tmp_path / 'report'
    (folder / 'summary.md').mkdir(parents=True)
    (folder / 'report.json').write_text('{}\n', encoding='utf-8')
    with pytest.raises(ConfigError, match=r'holds summary\.md, which is not a file'):
        check_report_folder(folder, overwrite=True)
    # A plain earlier report is still replaced.
    (folder / 'summary.md').rmdir()
    (folder / 'summary.md').write_text('old\n', encoding='utf-8')
    check_report_folder(folder, overwrite=True)
    assert {p.name for p in clear_report(folder)} == {'report.json', 'summary.md'}
    ReportWriter(folder, max_plots=0).write(ReplayReport())
    assert (folder / 'summary.md').read_text(encoding='utf-8').startswith('# Bag replay')


@pytest.mark.parametrize('shape', [(4, 5, 1), (20,)])
def test_a_disparity_that_is_no_2d_map_is_an_input_error(shape: tuple[int, ...]) -> None:
    # A bare ValueError (too many / not enough values to unpack), which the replay does not
    # catch as a frame it cannot score.
    _, confidence, kept, gt = _frame()
    disparity = np.zeros(shape, dtype=np.float32)
    with pytest.raises(InputError, match=rf'disparity must be an \(h, w\) map of numbers; got '
                                         rf'shape \({shape[0]},'):
        score_frame(0, 0, disparity, confidence, kept, gt)


def test_the_confidence_is_ranked_in_its_own_dtype() -> None:
    # Cast to float32, float64 values that differ beyond its 7 digits all tied: the frame's
    # AUC was that of a constant map, not what score_confidence (cva-evaluate) gives.
    disparity, _, kept, gt = _frame()
    disparity[0, :3] = np.nan  # wrong, and the least confident below
    confidence = 0.5 + np.arange(20, dtype=np.float64).reshape(4, 5) * 1e-10
    error = np.isnan(disparity)
    expected = score_confidence(confidence, error)
    assert expected.auc < 0.02  # a perfect ranking (a constant map: the error rate, 0.15)
    score = score_frame(0, 0, disparity, confidence, kept, gt)
    assert score.auc == expected.auc and score.auc_opt == expected.auc_opt
    assert score.error_rate == pytest.approx(3 / 20)


def test_a_bool_confidence_is_refused_as_score_confidence_refuses_it() -> None:
    # It was read as 0 / 1 and scored.
    disparity, confidence, kept, gt = _frame()
    with pytest.raises(InputError, match=r'confidence must hold real numbers \(float or int\); '
                                         r'got dtype bool'):
        score_frame(0, 0, disparity, confidence > 0.2, kept, gt)


@pytest.mark.parametrize('name', ['kept', 'region'])
def test_kept_and_region_must_be_bool_masks(name: str) -> None:
    # The filtered disparity given as ``kept`` counted its NaN pixels as kept (NaN cast to
    # bool is True): kept_fraction 1.0 for a frame that kept 3 pixels of 20.
    disparity, confidence, kept, gt = _frame()
    filtered = np.full(disparity.shape, np.nan, dtype=np.float32)
    filtered[0, :3] = 10.0
    arguments = {'kept': kept, 'region': None, name: filtered}
    with pytest.raises(InputError, match=rf'{name} must be an \(h, w\) bool mask; got dtype '
                                         r'float32'):
        score_frame(0, 0, disparity, confidence, arguments['kept'], gt,
                    region=arguments['region'])
    # The masks themselves still score.
    score = score_frame(0, 0, disparity, confidence, np.isfinite(filtered), gt,
                        region=np.ones(disparity.shape, dtype=bool))
    assert score.kept_fraction == pytest.approx(3 / 20)


def test_a_first_signal_in_a_critical_section_is_announced(
    capsys: pytest.CaptureFixture[str],
) -> None:
    # It was noted without a word (and so was a second one), though the run stops after it.
    original = signal.getsignal(signal.SIGINT)
    with GracefulInterrupt(notice='stopping after this frame') as interrupts:
        with interrupts.critical():
            os.kill(os.getpid(), signal.SIGINT)
            os.kill(os.getpid(), signal.SIGINT)  # still not raised inside the section
        with pytest.raises(KeyboardInterrupt):
            interrupts.check()
        interrupts.closing()
        os.kill(os.getpid(), signal.SIGTERM)  # while the outputs are closed: no line
    err = capsys.readouterr().err
    assert err.count('stopping after this frame (Ctrl-C again to stop at once)') == 1
    assert signal.getsignal(signal.SIGINT) is original

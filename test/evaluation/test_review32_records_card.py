"""Review regressions (32): the Table-1 Markdown of evaluation records, the calibration
report's rows over all data sets, model cards."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from cva_confidence_ros.calibration import reliability
from cva_confidence_ros.errors import InputError
from cva_confidence_ros.evaluation.records import EvalRecord, format_table
from cva_confidence_ros.evaluation.reliability import pooled, write_calibration
from cva_confidence_ros.metrics import auc_scores
from cva_confidence_ros.training.card import write_model_card


def _rec(scene: str, method: str, auc: float, auc_opt: float = 0.005) -> EvalRecord:
    return EvalRecord('d', scene, 'm', method, auc, auc_opt, 0.1, 100)


# --- evaluation/records.py -------------------------------------------------------------------


def test_a_method_without_some_scenes_of_its_row_takes_no_bold() -> None:
    # b has only s1 (2.00) where a and Opt. average s1 and s2: b's mean was bold as the best.
    records = [_rec('s1', 'a', 0.05), _rec('s2', 'a', 0.05), _rec('s1', 'b', 0.02)]
    table = format_table(records)
    assert table.split('\n')[2] == '| d | m | 0.50 | **5.00** | 2.00 |'
    assert 'b in d m (1 of 2 scenes)' in table.split('\n\n')[1]
    # Every method on every scene: no note, the best is bold as before.
    full = [*records, _rec('s2', 'b', 0.06)]
    assert format_table(full).split('\n')[2:] == ['| d | m | 0.50 | 5.00 | **4.00** |', '']


def test_an_auc_below_what_a_perfect_confidence_can_score_is_refused() -> None:
    rng = np.random.default_rng(0)
    error = rng.random(1000) < 0.3
    scores = auc_scores(rng.random(1000), error)  # a random map: auc ≈ 0.3, auc_opt ≈ 0.05
    swapped = {**scores, 'auc': scores['auc_opt'], 'auc_opt': scores['auc']}
    record = EvalRecord('d', 's', 'm', 'a', **swapped)  # type: ignore[arg-type]
    with pytest.raises(InputError, match=r'd/s m a: auc 0\.0.* is below auc_opt 0\.[23]'):
        format_table([record])
    # A perfect map's AUC (trapezoid over 5 % samples) lies below Eq. (1): 0.125 < 0.153
    # for 2 pixels, 0.00513 < 0.00518 for 1000; those are kept.
    for n, wrong in ((2, 1), (1000, 100), (37, 30)):
        error = np.arange(n) < wrong
        perfect = auc_scores(np.where(error, 0.0, 1.0), error)
        assert perfect['auc'] < perfect['auc_opt']
        format_table([EvalRecord('d', 's', 'm', 'a', **perfect)])  # type: ignore[arg-type]


# --- evaluation/reliability.py ---------------------------------------------------------------


def test_a_row_over_all_data_sets_is_not_made_of_some_of_them(tmp_path: Path) -> None:
    # lite had tables of mid only: its 'all' row pooled 2 pixels beside cva_net's 52.
    kitti = reliability(np.full(50, 0.95), np.ones(50, bool))
    mid = reliability(np.array([0.1, 0.3]), np.array([False, True]))
    tables = {('kitti', 'sgm', 'cva_net'): kitti, ('mid', 'sgm', 'cva_net'): mid,
              ('mid', 'sgm', 'lite'): mid}
    message = r"sgm lite .*tables of \['mid'\] only, none of \['kitti'\]"
    with pytest.raises(InputError, match=message):
        pooled(tables)
    with pytest.raises(InputError, match=message):
        write_calibration(tables, tmp_path / 'out')
    assert not (tmp_path / 'out').exists()
    del tables[('mid', 'sgm', 'lite')]
    assert ('all', 'sgm', 'cva_net') in pooled(tables)


# --- training/card.py ------------------------------------------------------------------------


def _facts(**changes: object) -> dict[str, object]:
    facts: dict[str, object] = {
        'arch': 'cvanet',
        'matcher': 'census_bm',
        'max_disparity': 16,
        'epochs': 1,
        'epochs_low_lr': 0,
        'lr': 1e-4,
        'lr_low': 1e-5,
        'command': "cva-train --out 'my run'",
        'final_train_loss': 0.5,
        'history': [{'epoch': 1, 'lr': 1e-4, 'train_loss': 0.5, 'samples_per_s': 10.0}],
    }
    facts.update(changes)
    return facts


@pytest.mark.parametrize('command', ['', None])
def test_a_card_without_a_command_line_says_so(tmp_path: Path, command: object) -> None:
    # train(config) records command '': the card showed '``' (two backticks), or '`None`'.
    md_path, _ = write_model_card(tmp_path / 'w.pt', _facts(command=command))
    assert '- command: —\n' in md_path.read_text()
    md_path, _ = write_model_card(tmp_path / 'v.pt', _facts())
    assert "- command: `cva-train --out 'my run'`\n" in md_path.read_text()


def test_a_card_of_numpy_numbers_is_written(tmp_path: Path) -> None:
    # json.dumps raised 'TypeError: Object of type float32 is not JSON serializable'.
    facts = _facts(final_val_auc=np.float32(0.125), val_pixels=np.int64(40),
                   final_train_loss=np.float32('nan'))
    md_path, json_path = write_model_card(tmp_path / 'w.pt', facts)
    card = json.loads(json_path.read_text())
    assert card['final_val_auc'] == 0.125 and card['val_pixels'] == 40
    assert card['final_train_loss'] is None
    assert '- validation AUC: 0.125 (' in md_path.read_text()


def test_a_card_shows_no_python_none(tmp_path: Path) -> None:
    # Settings missing from the facts were written 'None' ('- seed: None').
    md_path, _ = write_model_card(tmp_path / 'w.pt', _facts(max_disparity=None, epochs=None))
    text = md_path.read_text()
    assert 'None' not in text
    assert '- seed: —\n' in text and '- mode: —\n' in text
    assert '- epochs: — at lr 0.0001 + 0 at lr 1e-05\n' in text
    assert '- cost-volume depth D: — (' in text

"""Review 33 of the model card: what 'samples per epoch' means in dense mode."""

from __future__ import annotations

from pathlib import Path

from cva_confidence_ros.training.card import write_model_card


def _facts(mode: str) -> dict[str, object]:
    return {
        'arch': 'cvanet', 'matcher': 'census_bm', 'max_disparity': 16, 'mode': mode,
        'crop_size': 8, 'epochs': 2, 'epochs_low_lr': 0, 'lr': 1e-4, 'lr_low': 1e-5,
        'batch_size': 4, 'samples_per_epoch': 100, 'samples_seen': 230,
        'history': [{'epoch': 1, 'lr': 1e-4, 'train_loss': 0.5, 'samples_per_s': 10.0}],
    }


def test_dense_cards_say_the_epoch_count_is_a_minimum(tmp_path: Path) -> None:
    # Dense crops are whole: 2 epochs of 100 asked saw 230. The card read as if an epoch were
    # exactly 100 samples, beside a 'samples seen' that says otherwise.
    md_path, _ = write_model_card(tmp_path / 'dense.pt', _facts('dense'))
    assert '- batch size: 4, samples per epoch: at least 100, samples seen: 230' in (
        md_path.read_text())
    md_path, _ = write_model_card(tmp_path / 'patch.pt', _facts('patch'))
    assert '- batch size: 4, samples per epoch: 100, samples seen: 230' in md_path.read_text()

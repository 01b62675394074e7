"""Review regressions (30): evaluation records' table, model cards, the hub's ``predict``."""

from __future__ import annotations

import json
from pathlib import Path
import shlex

import numpy as np
import pytest

from cva_confidence_ros.errors import DataError, InputError
from cva_confidence_ros.evaluation.records import EvalRecord, format_table
from cva_confidence_ros.training.card import write_model_card


def _rec(scene: str, method: str, auc: float, dataset: str = 'd', matcher: str = 'm',
         n_pixels: int = 100) -> EvalRecord:
    return EvalRecord(dataset, scene, matcher, method, auc, 0.01, 0.1, n_pixels)


def _cells(table: str) -> list[list[str]]:
    """Cells split at unescaped pipes, as a Markdown renderer splits them."""
    rows = []
    for line in table.strip().split('\n'):
        parts = line.strip().replace('\\|', '\0').strip('|').split('|')
        rows.append([part.strip().replace('\0', '|') for part in parts])
    return rows


def _strict_json(text: str) -> object:
    def refuse(constant: str) -> None:
        raise ValueError(f'not JSON: {constant}')

    return json.loads(text, parse_constant=refuse)


# --- evaluation/records.py -------------------------------------------------------------------


def test_a_record_given_twice_counts_once_in_the_scene_mean() -> None:
    # s1 given twice weighed double: (10 + 10 + 40) / 3 = 20.00, not the mean over the two
    # scenes (10 + 40) / 2 = 25.00.
    records = [_rec('s1', 'a', 0.10), _rec('s1', 'a', 0.10), _rec('s2', 'a', 0.40)]
    assert _cells(format_table(records))[2] == ['d', 'm', '1.00', '**25.00**']


def test_two_different_records_of_one_scene_are_refused() -> None:
    # They were averaged into one cell: 20.00 from a scene scored 10 and 30.
    records = [_rec('s1', 'a', 0.10), _rec('s1', 'a', 0.30, n_pixels=50)]
    with pytest.raises(InputError, match='two different evaluation records of d/s1 m a: auc 0.1 '
                                         'and 0.3'):
        format_table(records)


def test_a_pipe_in_a_name_stays_in_its_cell() -> None:
    # 'x|y' and 'a|b' split their cells: a row of 6 cells under a header of 5.
    table = format_table([_rec('s1', 'a|b', 0.10, dataset='x|y'), _rec('s1', 'c', 0.2,
                                                                       dataset='x|y')])
    rows = _cells(table)
    assert rows[0] == ['data set', 'matcher', 'Opt.', 'a|b', 'c']
    assert rows[2] == ['x|y', 'm', '1.00', '**10.00**', '20.00']
    assert {len(row) for row in rows} == {5}


@pytest.mark.parametrize('decimals', [-1, 2.5, True, '2'])
def test_decimals_that_are_no_count_of_digits_are_refused(decimals: object) -> None:
    # -1 and 2.5 were 'ValueError: Format specifier missing precision' from inside the format.
    with pytest.raises(InputError, match=f'decimals must be an integer ≥ 0; got {decimals!r}'):
        format_table([_rec('s1', 'a', 0.1)], decimals=decimals)  # type: ignore[arg-type]
    assert format_table([_rec('s1', 'a', 0.1)], decimals=np.int64(1)).count('**10.0**') == 1


def test_a_method_named_twice_is_refused() -> None:
    # It gave two identical columns, both bold.
    with pytest.raises(InputError, match="each method once; got \\['a', 'a'\\]"):
        format_table([_rec('s1', 'a', 0.1)], methods=['a', 'a'])


# --- training/card.py ------------------------------------------------------------------------


def _facts(**changes: object) -> dict[str, object]:
    facts: dict[str, object] = {
        'arch': 'cvanet',
        'matcher': 'census_bm',
        'max_disparity': 16,
        'epochs': 1,
        'epochs_low_lr': 1,
        'lr': 1e-4,
        'lr_low': 1e-4 * 0.1,
        'command': 'cva-train --matcher census_bm',
        'final_train_loss': 0.5,
        'history': [{'epoch': 1, 'lr': 1e-4, 'train_loss': 0.5, 'samples_per_s': 10.0}],
    }
    facts.update(changes)
    return facts


def test_a_diverged_run_writes_a_card_that_is_json(tmp_path: Path) -> None:
    # json.dumps wrote NaN / Infinity, which strict JSON readers refuse.
    history = [{'epoch': 1, 'lr': 1e-4, 'train_loss': float('nan'), 'samples_per_s': 10.0}]
    facts = _facts(final_train_loss=float('nan'), wall_time_s=float('inf'), history=history)
    md_path, json_path = write_model_card(tmp_path / 'w.pt', facts)
    card = _strict_json(json_path.read_text())
    assert isinstance(card, dict)
    assert card['final_train_loss'] is None and card['wall_time_s'] is None
    assert card['history'][0]['train_loss'] is None and card['lr'] == 1e-4
    text = md_path.read_text()
    assert '- final train loss: nan' in text and '- wall time: inf s' in text


def test_a_command_with_a_backtick_stays_one_code_span(tmp_path: Path) -> None:
    # `cva-train --out 'a`b'`: the span ended at the backtick inside the command.
    command = "cva-train --out 'a`b'"
    md_path, _ = write_model_card(tmp_path / 'w.pt', _facts(command=command))
    assert f'- command: ``{command}``\n' in md_path.read_text()
    md_path, _ = write_model_card(tmp_path / 'v.pt', _facts())
    assert '- command: `cva-train --matcher census_bm`\n' in md_path.read_text()


def test_a_crash_while_writing_the_card_leaves_the_old_one(tmp_path: Path, monkeypatch) -> None:
    md_path, json_path = write_model_card(tmp_path / 'w.pt', _facts())
    old_json, old_md = json_path.read_text(), md_path.read_text()
    import builtins

    from cva_confidence_ros import outputs

    class HalfThenFullDisk:
        """A text file that takes half of what is written, then reports a full disk."""

        def __init__(self, *args: object, **kwargs: object) -> None:
            self.file = builtins.open(*args, **kwargs)

        def __enter__(self) -> HalfThenFullDisk:
            return self

        def __exit__(self, *exc: object) -> None:
            self.file.close()

        def write(self, data: str) -> int:
            self.file.write(data[: len(data) // 2])
            raise OSError(28, 'No space left on device')

    # The card's files are written through outputs.write_text_atomic's open().
    monkeypatch.setattr(outputs, 'open', HalfThenFullDisk, raising=False)
    with pytest.raises(DataError, match='cannot write model card .*w.json: OSError: .*No space '
                                        'left.*left as it was'):
        write_model_card(tmp_path / 'w.pt', _facts(final_train_loss=0.25))
    monkeypatch.undo()
    # The half-written card used to replace the good one: json.loads failed on it.
    assert json_path.read_text() == old_json and md_path.read_text() == old_md
    assert sorted(p.name for p in tmp_path.iterdir()) == ['w.json', 'w.md']


def test_the_card_states_the_settings_of_a_real_run_in_full(tmp_path: Path) -> None:
    # --lr 0.00012345 was 'lr 0.0001234' on the card (4 significant digits), not what was run.
    from cva_confidence_ros.training.cli import PROG, build_parser, config_from_args
    from cva_confidence_ros.training.trainer import train

    weights = tmp_path / 'cvanet_census_bm_d16.pt'
    argv = [
        '--matcher', 'census_bm', '--max-disparity', '16', '--synthetic', '2',
        '--synthetic-size', '24x40', '--val-synthetic', '1', '--val-pixels', '40',
        '--batch-size', '16', '--samples-per-epoch', '16', '--seed', '7', '--threads', '1',
        '--no-progress', '--epochs', '1', '--epochs-low-lr', '1', '--lr', '0.00012345',
        '--low-lr-factor', '0.3', '--out', str(tmp_path / 'run'), '--weights-out', str(weights),
    ]  # fmt: skip
    config = config_from_args(build_parser().parse_args(argv))
    command = shlex.join([PROG, *argv])
    summary = train(config, command=command)
    text = weights.with_suffix('.md').read_text()
    card = _strict_json(weights.with_suffix('.json').read_text())
    assert isinstance(card, dict)
    assert card['lr'] == config.lr == 0.00012345
    assert card['lr_low'] == pytest.approx(config.lr * config.low_lr_factor, rel=1e-15)
    assert card['command'] == summary['command'] == command
    lr_low = f'{config.lr * config.low_lr_factor:.12g}'
    assert lr_low == '3.7035e-05'
    assert (config.epochs, config.epochs_low_lr) == (1, 1)
    assert f'- epochs: 1 at lr 0.00012345 + 1 at lr {lr_low}\n' in text
    assert f'- batch size: {config.batch_size}, samples per epoch: 16, samples seen: 32' in text
    assert f'- command: `{command}`\n' in text
    assert f'- matcher: `{config.matcher}`' in text and f'- seed: {config.seed}\n' in text
    assert '| 1 | 0.00012345 |' in text and f'| 2 | {lr_low} |' in text


# --- model/hub.py ----------------------------------------------------------------------------


def test_hub_predict_takes_the_device_by_position() -> None:
    # predict(volume, 'cpu') was 'TypeError: predict_confidence() got multiple values for
    # argument device': the default device was added as a keyword beside it.
    from cva_confidence_ros.model import CVANet, predict_confidence
    from cva_confidence_ros.model.hub import HubPredict

    net = CVANet(16).eval()
    predict = HubPredict(net, baseline=False)
    volume = np.random.default_rng(0).uniform(0.0, 1.0, (16, 5, 6)).astype(np.float32)
    expected = predict_confidence(net, volume)
    np.testing.assert_array_equal(predict(volume, 'cpu'), expected)
    np.testing.assert_array_equal(predict(volume, device='cpu'), expected)
    np.testing.assert_array_equal(predict(volume), expected)


def test_hub_predict_of_a_baseline_takes_the_device_by_position() -> None:
    from cva_confidence_ros.model import ARCHITECTURES
    from cva_confidence_ros.model.baselines import predict_disparity_confidence
    from cva_confidence_ros.model.hub import HubPredict

    net = ARCHITECTURES.get('ccnn')({'arch': 'ccnn', 'matcher': 'census_bm',
                                     'max_disparity': 16}).eval()
    rng = np.random.default_rng(1)
    disparity = rng.uniform(0.0, 15.0, (12, 14)).astype(np.float32)
    image = rng.integers(0, 256, (12, 14), dtype=np.uint8)
    expected = predict_disparity_confidence(net, disparity, image)
    np.testing.assert_array_equal(HubPredict(net, True)(disparity, image, 'cpu'), expected)
    np.testing.assert_array_equal(HubPredict(net, True)(disparity, image), expected)

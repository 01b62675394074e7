"""Reliability tables, ECE and the error rate a probabilistic confidence predicts."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cva_confidence_ros.calibration import ReliabilityTable, expected_error, reliability
from cva_confidence_ros.errors import InputError


def test_a_small_table_by_hand() -> None:
    confidence = np.array([0.05, 0.15, 0.95, 0.95, 0.95, 0.85, 1.0, 0.5])
    correct = np.array([False, True, True, True, False, True, True, False])
    table = reliability(confidence, correct, bins=10)
    assert table.bins == 10 and table.n_pixels == 8
    # 1.0 falls into the last bin; 0.5 opens bin 5.
    assert table.counts.tolist() == [1, 1, 0, 0, 0, 1, 0, 0, 1, 4]
    assert table.mean_confidence[9] == pytest.approx((0.95 * 3 + 1.0) / 4)
    assert table.accuracy[9] == pytest.approx(3 / 4)
    assert np.isnan(table.accuracy[2]) and np.isnan(table.mean_confidence[2])
    gaps = [0.05, 0.85, 0.5, 0.15, abs(0.9625 - 0.75) * 4]
    assert table.ece == pytest.approx(sum(gaps) / 8)
    assert table.max_gap == pytest.approx(0.85)
    assert table.brier == pytest.approx(np.mean((confidence - correct) ** 2))
    assert table.overall_confidence == pytest.approx(confidence.mean())
    assert table.overall_accuracy == pytest.approx(5 / 8)
    np.testing.assert_allclose(table.edges, np.linspace(0, 1, 11))


def test_calibrated_and_over_confident_draws() -> None:
    rng = np.random.default_rng(0)
    confidence = rng.uniform(0.0, 1.0, 200_000)
    calibrated = reliability(confidence, rng.uniform(size=confidence.size) < confidence)
    assert calibrated.ece < 0.01 and calibrated.max_gap < 0.02
    # Right half as often as it claims: ECE = E[c / 2] = 0.25.
    over = reliability(confidence, rng.uniform(size=confidence.size) < confidence / 2)
    assert over.ece == pytest.approx(0.25, abs=0.01)
    assert np.all(over.accuracy < over.mean_confidence)


def test_kept_at_a_threshold() -> None:
    confidence = np.array([0.1, 0.45, 0.5, 0.7, 0.9, 0.95])
    correct = np.array([False, False, False, True, True, True])
    table = reliability(confidence, correct)
    kept, measured, predicted = table.kept_at(0.5)
    assert kept == pytest.approx(4 / 6)
    assert measured == pytest.approx(1 / 4)
    assert predicted == pytest.approx(1 - np.mean([0.5, 0.7, 0.9, 0.95]))
    assert table.kept_at(0.0)[0] == 1.0
    assert table.kept_at(0.9) == (pytest.approx(2 / 6), 0.0, pytest.approx(0.075))
    with pytest.raises(InputError, match='threshold 1 cannot be answered'):
        table.kept_at(1.0)
    with pytest.raises(InputError, match='bin edge'):
        table.kept_at(0.55)


def test_merge_equals_the_table_of_all_pixels_and_json_round_trip() -> None:
    rng = np.random.default_rng(1)
    confidence = rng.uniform(size=500)
    correct = rng.uniform(size=500) < confidence
    whole = reliability(confidence, correct)
    parts = ReliabilityTable.combine([
        reliability(confidence[:120], correct[:120]),
        reliability(confidence[120:], correct[120:]),
    ])
    assert parts.counts.tolist() == whole.counts.tolist()
    np.testing.assert_allclose(parts.confidence_sums, whole.confidence_sums)
    np.testing.assert_allclose(parts.correct_sums, whole.correct_sums)
    assert parts.brier == pytest.approx(whole.brier) and parts.ece == pytest.approx(whole.ece)
    again = ReliabilityTable.from_dict(json.loads(json.dumps(whole.as_dict())))
    assert again.ece == pytest.approx(whole.ece)
    assert again.brier == pytest.approx(whole.brier)
    assert again.counts.tolist() == whole.counts.tolist()
    with pytest.raises(InputError, match='merge'):
        whole.merge(reliability(confidence, correct, bins=5))
    with pytest.raises(InputError, match='no reliability tables'):
        ReliabilityTable.combine([])
    with pytest.raises(InputError, match='not a reliability table'):
        ReliabilityTable.from_dict({'bins': {}})


@pytest.mark.parametrize(
    ('confidence', 'correct', 'bins', 'message'),
    [
        ([0.5, np.nan], [True, False], 10, 'NaN'),
        ([0.5, 1.2], [True, False], 10, r'in \[0, 1\]'),
        ([0.5, 0.2], [1, 0], 10, 'bool'),
        ([0.5, 0.2], [True], 10, 'same size'),
        ([0.5], [True], 0, 'bins'),
    ],
)
def test_bad_input_is_refused(confidence, correct, bins, message) -> None:
    with pytest.raises(InputError, match=message):
        reliability(np.array(confidence), np.array(correct), bins=bins)


def test_an_empty_table_says_so() -> None:
    table = reliability(np.zeros(0), np.zeros(0, dtype=bool))
    assert table.n_pixels == 0
    with pytest.raises(InputError, match='no pixels'):
        _ = table.ece


def test_expected_error() -> None:
    confidence = np.array([[0.9, 0.6], [np.nan, 0.2]])
    assert expected_error(confidence) == pytest.approx(1 - np.mean([0.9, 0.6, 0.2]))
    mask = np.array([[True, True], [True, False]])
    assert expected_error(confidence, mask) == pytest.approx(0.25)
    assert expected_error(confidence, np.zeros((2, 2), dtype=bool)) is None
    with pytest.raises(InputError, match='shape'):
        expected_error(confidence, np.ones(3, dtype=bool))
    with pytest.raises(InputError, match='probability'):
        expected_error(np.array([1.5]))


def test_reliability_diagram_png(tmp_path) -> None:
    import cv2

    from cva_confidence_ros.plots import save_reliability_diagram

    rng = np.random.default_rng(2)
    confidence = rng.uniform(size=1000)
    tables = {
        'calibrated': reliability(confidence, rng.uniform(size=1000) < confidence),
        'over': reliability(confidence, rng.uniform(size=1000) < confidence / 2),
    }
    path = save_reliability_diagram(tables, tmp_path / 'sub' / 'rel.png', title='t')
    image = cv2.imread(str(path))
    assert image is not None and image.shape[0] > 300 and image.shape[1] > 300
    assert len(np.unique(image.reshape(-1, 3), axis=0)) > 10  # more than a blank canvas
    with pytest.raises(InputError, match='no reliability'):
        save_reliability_diagram({}, tmp_path / 'x.png')
    with pytest.raises(InputError, match='no pixels'):
        save_reliability_diagram(
            {'none': reliability(np.zeros(0), np.zeros(0, dtype=bool))}, tmp_path / 'x.png'
        )


def test_only_the_networks_are_probabilistic() -> None:
    from cva_confidence_ros.confidence import CONFIDENCE_METHODS, is_probabilistic
    from cva_confidence_ros.errors import ConfigError

    networks = {'cva_net', 'cva_net_fast', 'cva_net_lite', 'ccnn', 'lfn', 'lgc_net'}
    assert {name for name in CONFIDENCE_METHODS.names() if is_probabilistic(name)} == networks
    with pytest.raises(ConfigError):
        is_probabilistic('magic')


def test_report_pools_the_data_sets_and_writes_its_files(tmp_path) -> None:
    from cva_confidence_ros.evaluation.reliability import (
        format_calibration_table,
        pooled,
        write_calibration,
    )

    rng = np.random.default_rng(3)
    tables = {}
    for dataset, size in (('kitti2015', 300), ('middlebury2003', 700)):
        confidence = rng.uniform(size=size)
        tables[(dataset, 'census_bm', 'cva_net')] = reliability(
            confidence, rng.uniform(size=size) < confidence
        )
    rows = pooled(tables)
    assert list(rows) == [
        ('kitti2015', 'census_bm', 'cva_net'),
        ('middlebury2003', 'census_bm', 'cva_net'),
        ('all', 'census_bm', 'cva_net'),
    ]
    whole = rows[('all', 'census_bm', 'cva_net')]
    assert whole.n_pixels == 1000
    assert whole.ece == pytest.approx(ReliabilityTable.combine(tables.values()).ece)

    text = format_calibration_table(tables)
    lines = text.strip().split('\n')
    assert len(lines) == 2 + 3
    kept, measured, predicted = whole.kept_at(0.8)
    assert lines[-1].startswith('| all | census_bm | cva_net | 1000 |')
    assert f'| {100 * kept:.1f} | {100 * measured:.2f} | {100 * predicted:.2f} |' in lines[-1]

    written = write_calibration(tables, tmp_path / 'out')
    names = sorted(p.name for p in written)
    assert names == sorted([
        'calibration.json', 'calibration.md', 'reliability_all_census_bm.png',
        'reliability_kitti2015_census_bm.png', 'reliability_middlebury2003_census_bm.png',
    ])
    records = json.loads((tmp_path / 'out' / 'calibration.json').read_text())
    assert [r['dataset'] for r in records] == ['kitti2015', 'middlebury2003', 'all']
    assert records[-1]['n_pixels'] == 1000
    assert write_calibration({}, tmp_path / 'none') == []


@pytest.mark.parametrize('threshold', [float('nan'), float('inf'), -float('inf'), 'high', None])
def test_kept_at_a_threshold_that_is_no_number_names_it(threshold) -> None:
    table = reliability(np.array([0.2, 0.9]), np.array([False, True]))
    with pytest.raises(InputError, match=rf'bin edge .*got {threshold!r}'):
        table.kept_at(threshold)
    assert table.kept_at(0.5) == (0.5, 0.0, pytest.approx(0.1))

"""``cva-demo`` end to end on the embedded Motorcycle pair (fast methods only)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from cva_confidence_ros.demo import main


@pytest.mark.timeout(300)
def test_demo_matches_bags_and_replays(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / 'demo'
    code = main([
        '--out', str(out), '--matchers', 'census_bm', '--methods', 'pkrn,score',
        '--downsample', '4',
    ])
    assert code == 0
    printed = capsys.readouterr().out
    assert '| census_bm | pkrn |' in printed and '| census_bm | score |' in printed
    summary = json.loads((out / 'cost_volume_summary.json').read_text())
    assert {row['matcher'] for row in summary} == {'census_bm'}  # the matchers asked for
    for row in summary:
        assert 0.0 <= row['cost_min'] <= row['cost_mean'] <= row['cost_max'] <= 1.0
        assert 0.0 < row['error_rate'] < 0.6
        assert row['png'] == f"disparity_{row['matcher']}.png"  # beside the summary
        assert (out / row['png']).stat().st_size > 0
    report = json.loads((out / 'replay' / 'census_bm__pkrn' / 'report.json').read_text())
    assert len(report['frames']) == 1
    assert report['summary']['auc'] >= report['summary']['auc_opt'] > 0
    assert (out / 'motorcycle_bag').is_dir()



def _exit_code(argv: list[str]) -> int:
    try:
        return main(argv)
    except SystemExit as exc:  # argparse's error exit
        return int(exc.code)


@pytest.mark.parametrize(
    ('args', 'message'),
    [
        (['--downsample', '3'], '--downsample must be 1, 2 or 4; got 3'),
        (['--max-disparity', '0'], '--max-disparity must be in [1, 1024]'),
        (['--matchers', 'nope'], "unknown matcher 'nope'"),
        (['--methods', 'pkrn,magic'], "'magic'"),
        (['--max-disparity', '1000'], 'max_disparity must be smaller than the image width'),
    ],
)
def test_bad_options_exit_2_with_one_line(tmp_path, capsys, args, message) -> None:
    out = tmp_path / 'demo'
    assert _exit_code(['--out', str(out), '--matchers', 'census_bm', '--methods', 'pkrn',
                       *args]) == 2
    err = capsys.readouterr().err
    assert message in err.splitlines()[-1] and 'Traceback' not in err
    assert not (out / 'motorcycle_bag').exists()


def test_out_that_is_a_file(tmp_path, capsys) -> None:
    afile = tmp_path / 'afile'
    afile.write_text('not a folder')
    assert _exit_code(['--out', str(afile), '--methods', 'pkrn']) == 2
    assert 'is a file; expected a folder' in capsys.readouterr().err


def test_missing_weights_are_refused_before_the_first_step(tmp_path, capsys) -> None:
    # No CVA-Net-Fast weights are shipped for D = 32: say so before matching and writing the
    # bag, not in step 3 after them.
    out = tmp_path / 'demo'
    assert _exit_code(['--out', str(out), '--matchers', 'census_bm', '--methods',
                       'pkrn,cva_net_fast', '--max-disparity', '32']) == 2
    err = capsys.readouterr().err
    last = err.splitlines()[-1]
    assert last.startswith('cva-demo: error: no shipped cvanet_fast weights '
                           'cvanet_fast_census_bm_d32.pt') and 'Traceback' not in err
    assert '[demo] step' not in err and not out.exists()

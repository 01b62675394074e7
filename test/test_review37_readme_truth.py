"""Review 37: what README and ``--help`` now say about today's features, held by the code."""

from __future__ import annotations

import argparse
from pathlib import Path
import re

import numpy as np
from PIL import Image


def _options(parser: argparse.ArgumentParser) -> set[str]:
    return {flag for action in parser._actions for flag in action.option_strings}


def _help(parser: argparse.ArgumentParser, dest: str) -> str:
    return next(action.help or '' for action in parser._actions if action.dest == dest)


def test_help_texts_name_options_that_exist() -> None:
    # Each help text changed today names other options of its own command: they must be
    # there under those names.
    from cva_confidence_ros.training.cli import build_parser as train_parser
    from msg_tools.bag_replay import build_parser as replay_parser

    for parser, dests in (
        (train_parser(), ('volume_cache', 'out', 'no_progress')),
        (replay_parser(), ('report', 'overwrite')),
    ):
        for dest in dests:
            named = set(re.findall(r'--[a-z][a-z-]*', _help(parser, dest)))
            assert named <= _options(parser), (dest, named - _options(parser))
    assert '--resume' in _help(train_parser(), 'volume_cache')
    assert '--overwrite' in _help(replay_parser(), 'report')


def test_mask_tool_help_says_the_name_it_takes(tmp_path: Path, capsys) -> None:
    from msg_tools.mask_tool import build_parser, main

    assert '.png' in _help(build_parser(), 'out')
    assert main([str(tmp_path / 'mask.jpg'), '--size', '32x24', '--below', '20']) == 2
    assert 'must be named .png' in capsys.readouterr().err
    assert main([str(tmp_path / 'mask.png'), '--size', '32x24', '--below', '20']) == 0


def test_confidence_png_ranges_are_those_the_readme_names(tmp_path: Path) -> None:
    # README: over [0, 1] where every value lies in it (the networks, MLM), else over the
    # map's own 1st–99th percentile (PKRN, LRD, LRC, Score); it said "percentile for a
    # hand-crafted measure", which MLM is not drawn over.
    from cva_confidence_ros.evaluation.cli import main
    from cva_confidence_ros.evaluation.scene import FIXED_RANGE, PERCENTILE_RANGE

    rng = np.random.default_rng(0)
    scene = tmp_path / 'data' / 's1'
    scene.mkdir(parents=True)
    texture = rng.integers(0, 256, (40, 72), dtype=np.uint8)
    Image.fromarray(texture[:, :64]).save(scene / 'left.png')  # left x = right x − 8
    Image.fromarray(texture[:, 8:]).save(scene / 'right.png')
    np.save(scene / 'disparity.npy', np.full((40, 64), 8.0, np.float32))
    methods = {'mlm': FIXED_RANGE, 'pkrn': PERCENTILE_RANGE, 'lrd': PERCENTILE_RANGE,
               'lrc': PERCENTILE_RANGE, 'score': PERCENTILE_RANGE}
    out = tmp_path / 'out'
    assert main(['--data-root', str(tmp_path / 'data'), '--dataset', 'stereo_folder',
                 '--matchers', 'census_bm', '--methods', ','.join(methods),
                 '--max-disparity', '16', '--json', str(tmp_path / 'r.json'),
                 '--out', str(out)]) == 0
    for method, how in methods.items():
        with Image.open(out / 'stereo_folder' / 's1' / 'census_bm' /
                        f'confidence_{method}.png') as png:
            assert f'({how})' in png.text['Description'], (method, png.text)

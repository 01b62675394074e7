"""Every shipped weights file loads for what its name says and has a complete model card."""

from __future__ import annotations

import json
from pathlib import Path
import re

import pytest
import yaml

from cva_confidence_ros.matching import MATCHERS
from cva_confidence_ros.model import ARCHITECTURES, load_weights, weights_file_name

MODELS = Path(__file__).resolve().parents[2] / 'models'
SHIPPED = sorted(MODELS.glob('*.pt'))
NAME = re.compile(
    f'^(?P<arch>{"|".join(ARCHITECTURES.names())})_(?P<matcher>{"|".join(MATCHERS.names())})'
    r'_d(?P<d>\d+)$'
)
MACHINE_PATH = re.compile(r'(?<![\w.])/(?:tmp|home|work|root|Users|mnt)/')


def test_weights_are_shipped():
    assert len(SHIPPED) >= 3, f'no shipped weights in {MODELS}'


@pytest.mark.parametrize('path', SHIPPED, ids=[p.stem for p in SHIPPED])
def test_weights_load_for_their_name(path):
    parts = NAME.match(path.stem)
    assert parts, f'{path.name} is not <arch>_<matcher>_d<D>.pt'
    arch, matcher, depth = parts['arch'], parts['matcher'], int(parts['d'])
    assert weights_file_name(matcher, depth, arch) == path.name
    net, meta = load_weights(path, matcher=matcher, max_disparity=depth, arch=arch)
    assert (meta['arch'], meta['matcher'], meta['max_disparity']) == (arch, matcher, depth)
    assert not net.training
    assert meta['samples_seen'] > 0
    assert meta['command'].startswith('cva-train ')
    assert f'--matcher {matcher}' in meta['command']
    assert not MACHINE_PATH.search(json.dumps(meta, default=str)), meta['command']


@pytest.mark.parametrize('path', SHIPPED, ids=[p.stem for p in SHIPPED])
def test_model_card_is_complete(path):
    texts = {suffix: path.with_suffix(suffix).read_text() for suffix in ('.md', '.json', '.yaml')}
    card = json.loads(texts['.json'])
    summary = yaml.safe_load(texts['.yaml'])
    details = texts['.md']
    assert summary['weights'] == path.name
    assert (
        card['matcher'] == summary['matcher'] and card['max_disparity'] == summary['max_disparity']
    )
    assert card['wall_time_s'] > 0 and card['hardware']['device'] in ('cpu', 'cuda')
    assert card['samples_seen'] == summary['training']['samples_seen']
    # How it was made and what it scores on the develop split.
    for heading in ('## Training data', '## Procedure', '## Hardware and time', '## Evaluation'):
        assert heading in details, f'{path.with_suffix(".md").name} lacks {heading!r}'
    assert card['command'] in details
    keys = [key for key in ('develop_evaluation', 'develop_evaluation_all_pixels') if key in card]
    assert keys and all(card[key]['records'] for key in keys), 'no develop records'
    for suffix, text in texts.items():
        assert not MACHINE_PATH.search(text), f'a machine path in {path.stem}{suffix}'

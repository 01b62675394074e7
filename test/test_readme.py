"""The README's *Python API* examples run as written, on a small real stereo pair.

The blocks are taken from the README itself, so an API change that breaks them fails here
rather than in a user's first session. Only the placeholders are filled in: ``left``,
``right`` and ``gt`` (the scikit-image Middlebury 2014 Motorcycle pair at 1/4 resolution) and
the checkout path of the ``torch.hub`` block.
"""

from __future__ import annotations

from pathlib import Path
import re

import numpy as np
import pytest

from cva_confidence_ros.datasets import load_scene, resize_sample

ROOT = Path(__file__).resolve().parents[1]


def _api_blocks() -> list[str]:
    text = (ROOT / 'README.md').read_text(encoding='utf-8')
    section = text.split('\n## Python API\n', 1)[1].split('\n## ', 1)[0]
    return re.findall(r'```python\n(.*?)```', section, re.S)


@pytest.fixture(scope='module')
def namespace() -> dict:
    scene = resize_sample(load_scene('motorcycle', None, 'motorcycle'), 4)
    return {'np': np, 'left': scene.left, 'right': scene.right, 'gt': scene.disparity}


def test_readme_has_the_two_api_blocks() -> None:
    blocks = _api_blocks()
    assert len(blocks) == 2
    assert 'compute_cost_volume' in blocks[0] and 'torch.hub.load' in blocks[1]


def test_readme_api_block_runs(namespace: dict, monkeypatch: pytest.MonkeyPatch,
                               capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.chdir(ROOT)  # the block loads 'models/…' relative to the checkout
    exec(_api_blocks()[0], namespace)  # noqa: S102 - the README's own code
    left, volume = namespace['left'], namespace['volume']
    height, width = left.shape[:2]
    assert volume.shape == (64, height, width)
    assert namespace['confidence'].shape == (height, width)
    auc, auc_opt = (float(value) for value in capsys.readouterr().out.split())
    # The printed AUC is a real one of this pair: above the optimum, below random ranking.
    error_rate = namespace['wrong'][np.isfinite(namespace['gt'])].mean()
    assert 0 < auc_opt < auc < error_rate
    result = namespace['result']
    assert result.confidence.shape == (height, width)


def test_readme_torch_hub_block_runs(namespace: dict) -> None:
    pytest.importorskip('torch')
    block = _api_blocks()[1].replace("'path/to/cva_confidence_ros'", repr(str(ROOT)))
    volume = np.random.default_rng(0).random((64, 20, 30), dtype=np.float32)
    scope = {**namespace, 'torch': __import__('torch'), 'volume': volume}
    exec(block, scope)  # noqa: S102 - the README's own code
    assert scope['confidence'].shape == (20, 30)
    assert scope['net'].meta['matcher'] == 'census_sgm'
    assert scope['pipeline'].config.matcher == 'census_bm'

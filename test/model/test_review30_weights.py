"""Review 30: weights whose meta contradicts their tensors."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from cva_confidence_ros.errors import ModelError
from cva_confidence_ros.model import CVANet
from cva_confidence_ros.model.weights import load_weights, save_weights


@pytest.mark.parametrize('depth', [24, 10**12])
def test_a_meta_depth_that_contradicts_the_tensors_is_refused_before_building(
    tmp_path: Path, depth: int
):
    path = tmp_path / 'w.pt'
    save_weights(CVANet(16), path, {'matcher': 'census_bm'})
    blob = torch.load(path, weights_only=False)
    blob['meta']['max_disparity'] = depth
    torch.save(blob, path)
    with pytest.raises(ModelError) as caught:
        load_weights(path)
    message = str(caught.value)
    # The stored shape is compared with a shape-only build: no (16, 32, D - 12, 1) tensor
    # of 10**12 elements is ever allocated, and the message names both shapes.
    assert 'classification.fc1.weight has shape (16, 32, 4, 1)' in message
    assert f'(16, 32, {depth - 12}, 1)' in message

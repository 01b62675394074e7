"""Review 28: tiled inference at odd sizes, and hand-crafted measures at the edges of their
input contract (costs in the rounding slack below 0, a right volume of another shape)."""

from __future__ import annotations

from light_net_test_utils import with_data_bn
import numpy as np
import pytest
import torch

from cva_confidence_ros.confidence import ConfidenceInputs, compute_confidence
from cva_confidence_ros.confidence.handcrafted import left_right_difference_map
from cva_confidence_ros.errors import InputError
from cva_confidence_ros.model import CVANet, predict_confidence, tile_shape

DEPTH = 14

pytestmark = pytest.mark.usefixtures('one_torch_thread')


def _inputs(volume: np.ndarray) -> ConfidenceInputs:
    disparity = np.argmin(volume, axis=0).astype(np.float32)
    image = np.zeros(volume.shape[1:], dtype=np.uint8)
    # A crop away from the image's column 0 (which the hand-crafted measures rate lowest).
    return ConfidenceInputs(volume, disparity, image, cost_volume_right=volume, first_column=1)


@pytest.mark.parametrize('eps', [1e-3, 5e-5, 1e-5])
def test_pkrn_reads_slightly_negative_costs_as_zero(eps: float) -> None:
    # ConfidenceInputs accepts costs down to -1e-4; an eps below |c1| used to give inf (c1 + eps
    # = 0) or a negative PKRN, the least confident value for the best match.
    volume = np.array([-5e-5, 0.5, 0.2], dtype=np.float32).reshape(3, 1, 1)
    with np.errstate(divide='raise', invalid='raise'):
        result = compute_confidence('pkrn', _inputs(volume), eps=eps)
    np.testing.assert_allclose(result, [[(0.2 + eps) / eps]], rtol=1e-5)


@pytest.mark.parametrize('right_width', [3, 9])
def test_lrd_map_rejects_right_volume_of_other_shape(right_width: int) -> None:
    volume = np.random.default_rng(0).random((3, 2, 4)).astype(np.float32)
    right = np.zeros((3, 2, right_width), dtype=np.float32)
    with pytest.raises(InputError, match=r'volume_right must have the shape of volume'):
        left_right_difference_map(volume, right, 1e-3)


@pytest.fixture(scope='module')
def net() -> CVANet:
    torch.manual_seed(0)
    volume = np.random.default_rng(1).random((DEPTH, 16, 16)).astype(np.float32)
    return with_data_bn(CVANet(DEPTH), [volume])


@pytest.mark.parametrize(('height', 'width'), [(1, 7), (5, 1), (3, 17), (14, 15)])
@pytest.mark.parametrize('budget', [0.5, 2.0, 3.0])
def test_tiled_equals_whole_at_odd_sizes(net: CVANet, height: int, width: int, budget: float):
    volume = np.random.default_rng(height * width).random((DEPTH, height, width))
    whole = predict_confidence(net, volume.astype(np.float32), tile_budget_mb=1e4)
    assert tile_shape(height, width, DEPTH, 1e4) == (height, width)
    tiled = predict_confidence(net, volume.astype(np.float32), tile_budget_mb=budget)
    assert tiled.shape == (height, width) and tiled.dtype == np.float32
    np.testing.assert_allclose(tiled, whole, atol=1e-5, rtol=0)

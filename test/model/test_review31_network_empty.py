"""Review 31: CVA-Net takes an empty batch as its folded form and the other networks do."""

from __future__ import annotations

import pytest
import torch

from cva_confidence_ros.model import CVANet


@pytest.mark.parametrize('train', [False, True])
@pytest.mark.parametrize('size', [(13, 13), (20, 31)])
def test_cva_net_takes_an_empty_batch(train: bool, size: tuple[int, int]) -> None:
    # Before: RuntimeError 'Calculated padded input size per channel: (11 x 0)' from the
    # first depth convolution.
    torch.manual_seed(0)
    net = CVANet(16).train(train)
    out = net(torch.zeros((0, 1, 16, *size)))
    assert out.shape == (0, size[0] - 12, size[1] - 12) and out.dtype == torch.float32
    with torch.no_grad():
        assert net(torch.rand((2, 1, 16, *size))).shape == (2, size[0] - 12, size[1] - 12)

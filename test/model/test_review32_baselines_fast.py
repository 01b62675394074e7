"""Review 32: the disparity-based baselines (CCNN, LFN, LGC-Net): sizes and input dtypes."""

from __future__ import annotations

import pytest
import torch

from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.model.baselines import (
    CCNN,
    LFN,
    ConfNet,
    LGCNet,
)

ARCHS = [CCNN, LFN, LGCNet]


@pytest.mark.parametrize('cls', ARCHS)
@pytest.mark.parametrize('depth', [16.7, 64.0, True, '64', 0, -3, None])
def test_a_depth_that_is_not_a_whole_number_of_at_least_one_is_refused(cls, depth):
    # int() truncated 16.7 to 16 (disparities then divided by 16, not 16.7), took True as 1 and
    # parsed '64'; a depth of 0 failed only at the first image, as an InputError.
    with pytest.raises(ConfigError, match=r'max_disparity must be an integer >= 1; got '):
        cls(depth)


@pytest.mark.parametrize('width', [0, -1, 2.5])
def test_a_confnet_width_that_is_not_a_whole_number_of_at_least_one_is_refused(width):
    # A width of 0 was built and stopped in the first convolution, -1 raised a bare
    # RuntimeError, 2.5 became 2.
    with pytest.raises(ConfigError, match='ConfNet width must be an integer >= 1'):
        ConfNet(width)
    with pytest.raises(ConfigError, match='ConfNet width must be an integer >= 1'):
        LGCNet(16, width)


def _planes(height: int = 11, width: int = 13) -> tuple[torch.Tensor, torch.Tensor]:
    generator = torch.Generator().manual_seed(3)
    return (
        torch.rand(1, 1, height, width, generator=generator),
        torch.rand(1, 1, height, width, generator=generator),
    )


def _net(cls):
    torch.manual_seed(0)
    return (LGCNet(16, 4) if cls is LGCNet else cls(16)).eval()


@pytest.mark.parametrize('cls', ARCHS)
@pytest.mark.parametrize('dtype', [torch.float64, torch.float16])
def test_dense_confidence_runs_floating_inputs_of_another_dtype_in_the_weights_dtype(cls, dtype):
    # Stopped at the first convolution: "Input type (double) and bias type (float) should be
    # the same"; CVA-Net-Fast converts its volume to the weights' dtype, so do these now.
    net = _net(cls)
    disparity, image = _planes()
    with torch.no_grad():
        expected = net.dense_confidence(disparity.to(dtype).float(), image.to(dtype).float())
        got = net.dense_confidence(disparity.to(dtype), image.to(dtype))
    assert got.dtype == torch.float32
    assert torch.allclose(got, expected, atol=1e-6)


@pytest.mark.parametrize('cls', [CCNN, LFN])
def test_forward_logits_of_float64_patches_equal_float32(cls):
    net = _net(cls)
    disparity, image = _planes(9, 9)
    with torch.no_grad():
        expected = net.forward_logits(disparity, image)
        got = net.forward_logits(disparity.double(), image.double())
    assert torch.allclose(got, expected, atol=1e-6)


def test_confnet_takes_a_float64_input():
    torch.manual_seed(0)
    net = ConfNet(4).eval()
    disparity, image = _planes(16, 16)
    with torch.no_grad():
        expected = net.forward_logits(disparity, image)
        got = net.forward_logits(disparity.double(), image.double())
    assert torch.allclose(got, expected, atol=1e-6)


@pytest.mark.parametrize('cls', ARCHS)
@pytest.mark.parametrize('which', ['disparity', 'image'])
def test_integer_inputs_are_refused_by_name(cls, which):
    # A raw pixel disparity or a uint8 image is not the normalised input: it stopped with a bare
    # RuntimeError in the first convolution.
    net = _net(cls)
    disparity, image = _planes()
    if which == 'disparity':
        disparity = (disparity * 16).long()
    else:
        image = (image * 255).to(torch.uint8)
    with pytest.raises(InputError, match=rf'floating-point {which} .*got torch\.'):
        net.dense_confidence(disparity, image)

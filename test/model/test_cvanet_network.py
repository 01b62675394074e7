"""CVA-Net layers, parameter count, shapes, initialisation and one training step."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch import nn
import torch.nn.functional as F

from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.model import (
    CVANet,
    CVANetFast,
    CVANetLite,
    expected_parameter_count,
    keras_parameter_count,
)
from cva_confidence_ros.model.network import CONV_INIT_STD, DEPTH_KERNELS, pad_depth

pytestmark = pytest.mark.usefixtures('one_torch_thread')


def test_parameter_count_matches_paper():
    assert keras_parameter_count(CVANet(256)) == 782_725
    assert expected_parameter_count(256) == 782_725


@pytest.mark.parametrize('depth', [13, 16, 64, 128])
def test_parameter_count_follows_table_2(depth):
    # Only the first fully-connected layer depends on D: (D - 12) * 32 * 16 weights.
    assert keras_parameter_count(CVANet(depth)) == expected_parameter_count(depth)
    assert expected_parameter_count(depth + 1) - expected_parameter_count(depth) == 32 * 16


def test_layers_as_table_2():
    net = CVANet(64)
    assert [c.kernel_size for c in net.fusion.convs] == [(3, 3, 3)] * 6
    assert [c.padding for c in net.fusion.convs] == [(0, 0, 0)] * 6
    assert [c.out_channels for c in net.fusion.convs] == [32] * 6
    assert [c.kernel_size[0] for c in net.depth.convs] == list(DEPTH_KERNELS)
    assert list(DEPTH_KERNELS) == [8, 16, 32] + [64] * 7
    assert net.classification.fc1.kernel_size == (52, 1)
    assert net.classification.fc1.out_channels == 16
    assert net.classification.fc2.out_channels == 1
    assert net.classification.dropout.p == 0.5
    assert all(c.bias is not None for c in net.modules() if isinstance(c, nn.modules.conv._ConvNd))


@pytest.mark.parametrize('batch', [1, 3])
def test_patch_and_image_shapes(batch):
    net = CVANet(16).eval()
    with torch.no_grad():
        assert net(torch.rand(batch, 1, 16, 13, 13)).shape == (batch, 1, 1)
        out = net(torch.rand(batch, 1, 16, 20 + 12, 24 + 12))
    assert out.shape == (batch, 20, 24)
    assert torch.all((out > 0) & (out < 1))


def test_logits_are_pre_sigmoid():
    net = CVANet(16).eval()
    x = torch.rand(2, 1, 16, 15, 14)
    with torch.no_grad():
        torch.testing.assert_close(torch.sigmoid(net.forward_logits(x)), net(x))


@pytest.mark.filterwarnings('ignore:Using padding=.same')
def test_depth_padding_keeps_depth_and_matches_same_padding():
    # PyTorch's padding='same' puts k/2 - 1 zeros before and k/2 after for an even kernel;
    # ours must do the same so that weights port to and from 'same' convolutions.
    net = CVANet(20).eval()
    conv, norm = net.depth.convs[0], net.depth.norms[0]
    assert conv.kernel_size == (8, 1)
    x = torch.randn(1, 32, 8, 5)
    with torch.no_grad():
        ours = conv(pad_depth(x, 8))
        same = F.conv2d(x, conv.weight, conv.bias, padding='same')
        torch.testing.assert_close(ours, same)
        assert net.depth(x).shape == x.shape
    assert pad_depth(x, 8).shape == (1, 32, 15, 5)
    assert torch.all(pad_depth(x, 8)[:, :, :3] == 0) and torch.all(pad_depth(x, 8)[:, :, -4:] == 0)
    assert norm.num_features == 32


def test_wrong_input_raises():
    net = CVANet(16)
    with pytest.raises(InputError, match='depth D = 16'):
        net(torch.rand(1, 1, 17, 13, 13))
    with pytest.raises(InputError, match=r'\(B, 1, D'):
        net(torch.rand(1, 16, 13, 13))
    with pytest.raises(InputError, match='at least 13'):
        net(torch.rand(1, 1, 16, 12, 13))
    with pytest.raises(ConfigError, match='>= 13'):
        CVANet(12)


NETWORKS = [CVANet, CVANetLite, CVANetFast]


@pytest.mark.parametrize('cls', NETWORKS)
@pytest.mark.parametrize(
    'depth', [float('nan'), float('inf'), None, 16.0, 16.7, True, '16'], ids=repr
)
def test_depth_must_be_an_integer(cls, depth):
    with pytest.raises(ConfigError, match='max_disparity must be an integer'):
        cls(depth)


@pytest.mark.parametrize('cls', NETWORKS)
@pytest.mark.parametrize('dropout', ['x', None, float('nan'), True, -0.1, 1.0], ids=repr)
def test_dropout_must_be_a_real_in_unit_interval(cls, dropout):
    with pytest.raises(ConfigError, match=r'dropout must be a real number in \[0, 1\)'):
        cls(16, dropout=dropout)


@pytest.mark.parametrize('cls', NETWORKS)
def test_numpy_depth_and_dropout_are_accepted(cls):
    net = cls(np.int64(16), dropout=np.float32(0.25))
    assert net.max_disparity == 16 and type(net.max_disparity) is int


def test_initialisation_statistics():
    torch.manual_seed(0)
    net = CVANet(256)
    weights = torch.cat([c.weight.flatten() for c in (*net.fusion.convs, *net.depth.convs)])
    assert weights.numel() > 600_000
    assert abs(weights.mean().item()) < 1e-3
    assert weights.std().item() == pytest.approx(CONV_INIT_STD, rel=0.01)
    fc1 = net.classification.fc1.weight
    limit = math.sqrt(6.0 / (244 * 32 + 16))
    assert fc1.abs().max().item() <= limit
    # Uniform on [-a, a] has standard deviation a / sqrt(3).
    assert fc1.std().item() == pytest.approx(limit / math.sqrt(3), rel=0.02)
    fc2 = net.classification.fc2.weight
    assert fc2.abs().max().item() <= math.sqrt(6.0 / 17)
    for module in net.modules():
        if isinstance(module, nn.modules.conv._ConvNd):
            assert torch.count_nonzero(module.bias) == 0
        if isinstance(module, nn.modules.batchnorm._BatchNorm):
            assert torch.all(module.weight == 1) and torch.all(module.bias == 0)


def test_one_adam_step_lowers_the_loss():
    torch.manual_seed(1)
    net = CVANet(16)
    # Separable toy task: a clear minimum at the true disparity = correct.
    volume = torch.rand(32, 1, 16, 13, 13) * 0.2 + 0.8
    labels = torch.zeros(32)
    volume[:16, :, 5] = 0.0
    labels[:16] = 1.0
    optimiser = torch.optim.Adam(net.parameters(), lr=1e-3, betas=(0.9, 0.999))
    net.classification.dropout.p = 0.0

    def loss() -> torch.Tensor:
        return F.binary_cross_entropy_with_logits(net.forward_logits(volume)[:, 0, 0], labels)

    before = loss()
    optimiser.zero_grad()
    before.backward()
    optimiser.step()
    with torch.no_grad():
        after = loss()
    assert after.item() < before.item()

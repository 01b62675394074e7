"""Review of model/network.py (CVA-Net) and model/fast.py (CVA-Net-Fast): input handling."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cva_confidence_ros.errors import InputError
from cva_confidence_ros.model.fast import CVANetFast
from cva_confidence_ros.model.lite import CVANetLite
from cva_confidence_ros.model.network import CVANet

DEPTH = 13


def _network(kind: str) -> torch.nn.Module:
    torch.manual_seed(0)
    name, _, folded = kind.partition('_')
    net = {'cvanet': CVANet, 'fast': CVANetFast, 'lite': CVANetLite}[name](DEPTH).eval()
    return net.fold_batchnorm() if folded else net


# (the Lite and folded CVA-Net cases: the same faults, mended in lite.py and inference.py)
KINDS = ['cvanet', 'cvanet_folded', 'fast', 'fast_folded', 'lite', 'lite_folded']


@pytest.mark.parametrize('kind', KINDS)
@pytest.mark.parametrize('dtype', [torch.float64, torch.float16])
def test_a_floating_point_volume_of_another_dtype_runs_as_float32(kind: str, dtype) -> None:
    # check_input accepts any floating-point volume, but a float64 or float16 one stopped in the
    # first layer: "mixed dtype (CPU)" / "Input type (double) and bias type (float)".
    net = _network(kind)
    volume = torch.rand(2, 1, DEPTH, 14, 15, generator=torch.Generator().manual_seed(1))
    volume = volume.to(dtype)
    with torch.no_grad():
        expected = net(volume.float())
        got = net(volume)
    assert got.shape == (2, 2, 3)
    assert got.dtype == torch.float32
    torch.testing.assert_close(got, expected, rtol=0, atol=1e-6)


@pytest.mark.parametrize('kind', KINDS)
def test_a_numpy_volume_is_refused_by_name(kind: str) -> None:
    # An ndarray passed the shape checks and failed on an AttributeError about
    # 'numpy.dtypes.Float32DType' ... 'is_floating_point'.
    net = _network(kind)
    volume = np.zeros((1, 1, DEPTH, 13, 13), np.float32)
    with pytest.raises(InputError, match=r'torch\.Tensor.*got ndarray'):
        net(volume)

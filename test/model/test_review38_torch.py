"""Review 38, PyTorch users: CVA-Net-Fast under forward-mode autograd, and load_weights naming
the class of another architecture's weights."""

from __future__ import annotations

import pytest
import torch
import torch.autograd.forward_ad as fwAD

from cva_confidence_ros.errors import ModelError
from cva_confidence_ros.model import CVANetFast, load_weights, save_weights
from cva_confidence_ros.model.fast import aligned_curve

DEPTH = 16


def _volume_and_tangent() -> tuple[torch.Tensor, torch.Tensor]:
    generator = torch.Generator().manual_seed(3)
    volume = torch.rand((2, 1, DEPTH, 15, 14), generator=generator)
    return volume, torch.rand(volume.shape, generator=generator)


@pytest.mark.parametrize('folded', [False, True])
def test_forward_mode_ad_keeps_the_tangent_of_a_float32_volume(folded: bool) -> None:
    # The compiled aligned-curve kernel took the dual tensor as a plain one: the output had
    # no tangent (None), where a float64 network gave it.
    torch.manual_seed(0)
    net = CVANetFast(DEPTH).eval()
    model = net.fold_batchnorm() if folded else net
    volume, tangent = _volume_and_tangent()
    _, expected = torch.func.jvp(net, (volume,), (tangent,))
    with fwAD.dual_level():
        out = model(fwAD.make_dual(volume, tangent))
        got = fwAD.unpack_dual(out).tangent
    assert got is not None
    torch.testing.assert_close(got, expected, rtol=1e-4, atol=1e-5)


def test_aligned_curve_of_a_dual_tensor_carries_the_tangent() -> None:
    volume, tangent = _volume_and_tangent()
    costs, direction = volume[:, 0], tangent[:, 0]
    plain = aligned_curve(costs)
    with fwAD.dual_level():
        primal, got = fwAD.unpack_dual(aligned_curve(fwAD.make_dual(costs, direction)))
    assert got is not None
    assert torch.equal(primal, plain)
    # The tangent of the nine costs is the volume's tangent at the same disparities.
    wta = costs.argmin(1, keepdim=True)
    assert torch.equal(got[:, 4:5], direction.gather(1, wta))


def test_load_weights_of_another_architecture_names_its_class(tmp_path) -> None:
    path = save_weights(CVANetFast(DEPTH), tmp_path / 'fast.pt', {'matcher': 'census_bm'})
    with pytest.raises(
        ModelError,
        match=r"arch 'cvanet_fast'; expected 'cvanet' \(they are CVANetFast weights: load them "
        r"with arch='cvanet_fast', or arch=None",
    ):
        load_weights(path)
    net, _ = load_weights(path, arch=None)
    assert isinstance(net, CVANetFast)

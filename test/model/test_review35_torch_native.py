"""Review 35: the networks as a PyTorch user handles them (torch.func, reset_parameters,
torch.compile)."""

from __future__ import annotations

from typing import cast

import pytest
import torch
from torch import nn

from cva_confidence_ros.model import (
    CVANet,
    CVANetFast,
    CVANetLite,
    architecture_of,
    load_weights,
    save_weights,
)


def test_fast_network_runs_under_vmap_and_per_sample_gradients() -> None:
    # The CPU kernel of aligned_curve read the tensor through .numpy(), which a vmap-batched
    # tensor has not: "Cannot access data pointer of Tensor that doesn't have storage".
    torch.manual_seed(0)
    net = CVANetFast(16).eval()
    volume = torch.rand(3, 1, 16, 14, 14)
    with torch.no_grad():
        expected = net(volume)
    out = torch.func.vmap(net)(volume[:, None])[:, 0]
    torch.testing.assert_close(out, expected, atol=1e-6, rtol=0)

    params = {name: p.detach() for name, p in net.named_parameters()}
    buffers = dict(net.named_buffers())

    def loss(weights: dict[str, torch.Tensor], one: torch.Tensor) -> torch.Tensor:
        return torch.func.functional_call(net, (weights, buffers), (one[None],)).sum()

    per_sample = torch.func.vmap(torch.func.grad(loss), in_dims=(None, 0))(params, volume)
    first = torch.func.grad(loss)(params, volume[0])
    for name, grad in first.items():
        torch.testing.assert_close(per_sample[name][0], grad, atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize('cls', [CVANet, CVANetLite, CVANetFast])
def test_reset_parameters_resets_batch_normalisation(cls: type[nn.Module]) -> None:
    # A reset of loaded weights drew fresh convolutions but kept the trained BN statistics
    # and affine parameters (running variances up to 183 in the shipped CVA-Net).
    torch.manual_seed(1)
    trained = cls(16)
    for module in trained.modules():
        if isinstance(module, nn.modules.batchnorm._BatchNorm):
            assert module.running_var is not None
            module.running_var.fill_(5.0)
            module.running_mean.fill_(0.3)  # type: ignore[union-attr]
            with torch.no_grad():
                module.weight.fill_(2.0)
                module.bias.fill_(-0.5)
            module.num_batches_tracked.fill_(7)  # type: ignore[union-attr]
    fresh = cls(16)
    torch.manual_seed(2)
    fresh.reset_parameters()  # type: ignore[operator]
    torch.manual_seed(2)
    trained.reset_parameters()  # type: ignore[operator]
    got, want = trained.state_dict(), fresh.state_dict()
    assert got.keys() == want.keys()
    for name in want:
        assert torch.equal(got[name], want[name]), name


def test_save_weights_takes_a_compiled_network(tmp_path) -> None:
    # save_weights refused a torch.compile'd network: "got OptimizedModule".
    torch.manual_seed(3)
    net = CVANetFast(16)
    compiled = cast(nn.Module, torch.compile(net))  # wrapping only: nothing compiled until run
    assert architecture_of(compiled) == 'cvanet_fast'
    path = save_weights(compiled, tmp_path / 'fine_tuned.pt', {'matcher': 'census_bm'})
    loaded, meta = load_weights(path, arch='cvanet_fast')
    assert meta['max_disparity'] == 16
    for name, tensor in net.state_dict().items():
        assert torch.equal(loaded.state_dict()[name], tensor), name


def _hubconf() -> object:
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / 'hubconf.py'
    spec = importlib.util.spec_from_file_location('review35_hubconf', path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize(
    ('entry', 'side', 'documented', 'out_side'),
    [
        ('ccnn', 17, '(B, 1, h + 8, w + 8) → (B, 1, h, w)', 9),
        ('lfn', 17, '(B, 1, h + 8, w + 8) → (B, 1, h, w)', 9),
        ('lgcnet', 12, '(B, 1, H, W) images → (B, 1, H, W)', 12),
    ],
)
def test_baseline_hub_help_states_the_module_shapes(
    entry: str, side: int, documented: str, out_side: int
) -> None:
    # Their help said "otherwise as cvanet": a (B, 1, D, H + 12, W + 12) volume → (B, H, W).
    build = getattr(_hubconf(), entry)
    assert documented in ' '.join(build.__doc__.split())
    net = build(pretrained=False, max_disparity=16)
    plane = torch.rand(2, 1, side, side)
    with torch.no_grad():
        assert tuple(net(plane, plane).shape) == (2, 1, out_side, out_side)

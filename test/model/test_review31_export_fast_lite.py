"""Review 31 of the ONNX export, the MAC counts and the light networks (CVA-Net-Lite and
CVA-Net-Fast): regression tests for what it found."""

from __future__ import annotations

from pathlib import Path

from light_net_test_utils import trained_like
import numpy as np
import pytest
import torch
from torch import nn

from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.model import (
    CVANet,
    CVANetFast,
    CVANetLite,
    dense_macs,
    macs_per_pixel,
    predict_confidence,
    save_weights,
)
from cva_confidence_ros.model.export import check_onnx, export_onnx, main

D = 16
ARCHS = [CVANet, CVANetLite, CVANetFast]

pytestmark = pytest.mark.usefixtures('one_torch_thread')


@pytest.mark.parametrize('size', [(0, 5), (5, -1), (5,), (2.5, 3), (True, 4), 'ab', None])
def test_export_and_check_refuse_a_size_that_is_not_two_positive_integers(
    ort, tmp_path: Path, size
) -> None:
    # Was: an InputError about a 12×17 padded volume for (0, 5), a TypeError from torch.rand
    # for (2.5, 3), a RuntimeError for a negative side, a ValueError from numpy in the check.
    net = CVANetFast(D).eval()
    with pytest.raises(ConfigError, match=r'example_size must be \(H, W\), two integers >= 1'):
        export_onnx(net, tmp_path / 'a.onnx', example_size=size)
    assert not (tmp_path / 'a.onnx').exists()
    path = export_onnx(net, tmp_path / 'b.onnx')
    with pytest.raises(ConfigError, match=r'size must be \(H, W\), two integers >= 1.*got'):
        check_onnx(path, net, size, repeat=1)


@pytest.mark.parametrize('cls', ARCHS)
def test_a_folded_network_is_exported_as_it_is(ort, tmp_path: Path, cls: type) -> None:
    # Was: ModelError "expected a network of a registered architecture ...; got
    # FoldedCVANetFast", though the folded form is the one the graph holds.
    net = trained_like(cls, D, 1)
    folded = net.fold_batchnorm()
    path = export_onnx(folded, tmp_path / 'folded.onnx', example_size=(3, 4))
    session = ort.InferenceSession(str(path), providers=['CPUExecutionProvider'])
    volume = np.random.default_rng(2).random((1, D, 5, 9), dtype=np.float32)
    (out,) = session.run(None, {'cost_volume': volume})
    np.testing.assert_allclose(out[0], predict_confidence(net, volume[0]), atol=1e-5)
    assert check_onnx(path, folded, (4, 6), repeat=1)['max_abs_diff'] < 1e-5
    assert all(p.dtype == torch.float32 for p in folded.parameters())  # left as it was


def test_an_opset_the_exporter_fails_at_leaves_stdout_clean(ort, tmp_path: Path, capfd) -> None:
    # CVA-Net-Fast's gather has no ONNX form before opset 9. Was: torch's exporter printed
    # the whole TorchScript graph (~100 lines) on stdout before the one-line error.
    weights = tmp_path / 'w.pt'
    save_weights(trained_like(CVANetFast, D, 3), weights, {'matcher': 'census_bm'})
    out = tmp_path / 'opset7.onnx'
    assert main([str(weights), '--out', str(out), '--opset', '7', '--no-check']) == 2
    captured = capfd.readouterr()
    assert captured.out == ''
    assert captured.err.count('\n') == 1
    assert captured.err.startswith('cva-export: error: cannot export to ONNX at opset 7')
    assert not out.exists()
    # Output that is not the graph dump still comes through, and a good export stays quiet.
    print('before', flush=True)
    assert main([str(weights), '--out', str(tmp_path / 'ok.onnx'), '--no-check']) == 0
    assert capfd.readouterr().out == 'before\n'


@pytest.mark.parametrize('threads', [-2, 2.5, '2', True])
def test_the_onnxruntime_net_refuses_a_bad_thread_count(ort, threads) -> None:
    # Was: -2 and True accepted without a word, 2.5 and '2' a TypeError from ONNX Runtime.
    from cva_confidence_ros.model.export import OnnxRuntimeNet

    net = trained_like(CVANetFast, D, 4).fold_batchnorm()
    with pytest.raises(ConfigError, match=r'threads must be None or an integer >= 0.*got'):
        OnnxRuntimeNet(net, threads=threads)
    # 0 (as None) is torch's thread count, as before.
    padded = torch.rand(1, 1, D, 14, 15)
    with torch.no_grad():
        expected = net(padded)
    got = OnnxRuntimeNet(net, threads=0)(padded)
    torch.testing.assert_close(got, expected, atol=1e-5, rtol=0)


@pytest.mark.parametrize('cls', ARCHS)
def test_mac_counts_take_a_wrapped_network_as_export_does(cls: type) -> None:
    # Was: ConfigError "expected a CVA-Net ... got DataParallel".
    wrapped = nn.DataParallel(cls(D))
    arch = cls.arch
    assert macs_per_pixel(wrapped) == macs_per_pixel(arch, D)
    assert dense_macs(wrapped, None, 3, 5) == dense_macs(arch, D, 3, 5)
    with pytest.raises(ConfigError, match='built for D = 16'):
        macs_per_pixel(wrapped, 32)


@pytest.mark.parametrize('folded', [False, True])
def test_cva_net_lite_takes_an_empty_batch_as_the_other_networks_do(folded: bool) -> None:
    # Was: RuntimeError from the depth convolution (trained form) and "cannot reshape tensor
    # of 0 elements" (folded form); CVA-Net-Fast and the folded CVA-Net give (0, H, W).
    net = trained_like(CVANetLite, D, 5)
    model = net.fold_batchnorm() if folded else net
    with torch.no_grad():
        out = model(torch.rand(0, 1, D, 15, 17))
    assert out.shape == (0, 3, 5)
    if folded:
        assert model.head_logits(torch.rand(0, 16, 3)).shape == (0,)
    # A non-empty batch is unchanged.
    volume = torch.rand(2, 1, D, 15, 17)
    with torch.no_grad():
        torch.testing.assert_close(model(volume), net(volume), atol=1e-5, rtol=0)


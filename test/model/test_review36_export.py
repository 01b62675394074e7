"""Review 36: taking the networks out of Python (ONNX, torch.compile, reduced precision) and
the errors around the shipped weights."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from cva_confidence_ros.errors import ModelError
from cva_confidence_ros.model import (
    CVANet,
    CVANetFast,
    CVANetLite,
    default_weights_path,
    load_weights,
    save_weights,
)
from cva_confidence_ros.model import weights as weights_module
from cva_confidence_ros.model.export import OnnxRuntimeNet, export_onnx, main


def _last_bias(net: nn.Module, value: float) -> nn.Module:
    """``net`` with the bias of its last layer set to ``value`` (confidence near 1)."""
    layers = [m for m in net.modules() if isinstance(m, (nn.Conv2d, nn.Conv3d, nn.Linear))]
    assert layers[-1].bias is not None
    with torch.no_grad():
        layers[-1].bias.fill_(value)
    return net


def test_a_compiled_folded_network_is_exported(tmp_path: Path) -> None:
    # Refused before: "expected a network of a registered architecture ...; got
    # FoldedCVANetFast" (the compiled wrapper hid the folded class); a compiled network that
    # was not folded went through.
    ort = pytest.importorskip('onnxruntime')
    pytest.importorskip('onnx')
    torch.manual_seed(0)
    folded = CVANetFast(16).eval().fold_batchnorm()
    path = export_onnx(torch.compile(folded), tmp_path / 'net.onnx', example_size=(8, 10))
    volume = np.random.default_rng(0).random((2, 16, 11, 9), dtype=np.float32)
    session = ort.InferenceSession(str(path), providers=['CPUExecutionProvider'])
    (out,) = session.run(None, {'cost_volume': volume})
    with torch.no_grad():
        expected = folded(torch.nn.functional.pad(torch.from_numpy(volume), (6,) * 4)[:, None])
    np.testing.assert_allclose(out, expected.numpy(), atol=1e-5)


def test_the_onnxruntime_backend_takes_a_compiled_network() -> None:
    # Before: "cannot export to ONNX at opset 17 (RuntimeError: Detected that you are using FX
    # to torch.jit.trace a dynamo-optimized function)" (SparseEvaluator(torch.compile(folded),
    # backend='onnxruntime') the same).
    pytest.importorskip('onnxruntime')
    pytest.importorskip('onnx')
    torch.manual_seed(0)
    folded = CVANetFast(16).eval().fold_batchnorm()
    run = OnnxRuntimeNet(torch.compile(folded), threads=1)
    padded = torch.rand(2, 1, 16, 15, 17)
    with torch.no_grad():
        torch.testing.assert_close(run(padded), folded(padded), atol=1e-5, rtol=0)


def test_the_graph_says_what_it_is_for(tmp_path: Path) -> None:
    # The graph alone (what goes onto the robot, often without the .json card) did not say
    # the matcher or D it was made for: its metadata_props were empty.
    onnx = pytest.importorskip('onnx')
    torch.manual_seed(0)
    weights = save_weights(CVANetFast(16), tmp_path / 'fast.pt', {'matcher': 'census_sgm'})
    out = tmp_path / 'fast.onnx'
    assert main([str(weights), '--out', str(out), '--no-check']) == 0
    props = {p.key: p.value for p in onnx.load(str(out)).metadata_props}
    assert props == {'arch': 'cvanet_fast', 'max_disparity': '16', 'matcher': 'census_sgm',
                     'weights': 'fast.pt'}
    export_onnx(CVANetLite(16), tmp_path / 'lite.onnx', example_size=(4, 4))
    props = {p.key: p.value for p in onnx.load(str(tmp_path / 'lite.onnx')).metadata_props}
    assert props == {'arch': 'cvanet_lite', 'max_disparity': '16'}


# (Folded CVA-Net-Lite already gave float32 under autocast.)
@pytest.mark.parametrize(('cls', 'folded'), [
    (CVANet, False), (CVANet, True), (CVANetLite, False), (CVANetFast, False), (CVANetFast, True),
])
def test_bf16_autocast_does_not_round_confidence_to_one(cls: type, folded: bool) -> None:
    # The sigmoid ran in bfloat16 under autocast (cva_precision: bf16): every confidence above
    # 0.998 came out as exactly 1.0 (on a real 160x120 census_bm volume 54 % of the pixels of
    # the shipped CVA-Net-Fast, AUC 0.0147 against 0.0120 in float32; now 0.0120).
    torch.manual_seed(0)
    net = _last_bias(cls(16).eval(), 7.0)
    if folded:
        net = net.fold_batchnorm()
    volume = torch.rand(2, 1, 16, 15, 16)
    with torch.no_grad():
        exact = net(volume)
        with torch.autocast('cpu', dtype=torch.bfloat16):
            reduced = net(volume)
    assert reduced.dtype == torch.float32
    assert float(reduced.max()) < 1.0
    torch.testing.assert_close(reduced, exact, atol=2e-3, rtol=0)


def test_missing_weights_name_the_shipped_ones(tmp_path: Path, monkeypatch) -> None:
    # Only a training command was named, although weights for another D were shipped.
    for name in ('cvanet_census_bm_d64.pt', 'cvanet_census_bm_d256.pt',
                 'cvanet_fast_census_bm_d128.pt', 'cvanet_census_sgm_d64.pt'):
        (tmp_path / name).write_bytes(b'x')
    monkeypatch.setattr(weights_module, 'weights_search_dirs', lambda: [tmp_path])
    with pytest.raises(ModelError, match=r'cvanet weights there: census_bm D = 64, 256; '
                                         r'census_sgm D = 64\. Train them with: cva-train'):
        default_weights_path('census_bm', 128, 'cvanet')
    with pytest.raises(ModelError, match='cvanet_lite weights there: none'):
        default_weights_path('census_bm', 64, 'cvanet_lite')


def test_an_onnx_graph_given_as_weights_is_named(tmp_path: Path) -> None:
    # Before: "cannot read weights file ... (UnpicklingError: Weights only load failed)".
    graph = tmp_path / 'cvanet_fast.onnx'
    graph.write_bytes(b'\x08\x08\x12\x07pytorch')  # the start of an ONNX protobuf
    with pytest.raises(ModelError, match=r'is an ONNX graph, not a weights file: give the \.pt'):
        load_weights(graph, arch=None)

"""Review 32 of the ONNX export and CVA-Net-Lite: regression tests for what it found."""

from __future__ import annotations

import json
from pathlib import Path

from light_net_test_utils import trained_like
import numpy as np
import pytest
import torch

from cva_confidence_ros.errors import InputError, ModelError
from cva_confidence_ros.model import (
    CVANetFast,
    CVANetLite,
    predict_confidence,
    save_weights,
)
from cva_confidence_ros.model.export import (
    CostVolumeModel,
    OnnxRuntimeNet,
    export_onnx,
    main,
)

D = 16

pytestmark = pytest.mark.usefixtures('one_torch_thread')


@pytest.fixture
def onnx_package() -> None:
    """Writing a graph needs the onnx package (running it needs ONNX Runtime: ``ort``)."""
    pytest.importorskip('onnx')


def test_the_lite_graph_takes_an_empty_batch_as_the_other_graphs_do(ort, tmp_path: Path):
    # The folded Lite head reshaped (N, 16, D'') to (N, C·D''), traced as Reshape(N, -1):
    # ONNX Runtime failed on B = 0 ("The input tensor cannot be reshaped to the requested
    # shape. Input shape:{0,16,3}, requested shape:{0,-1}"), in the exported graph and in
    # OnnxRuntimeNet; PyTorch and the CVA-Net and CVA-Net-Fast graphs give (0, H, W).
    net = trained_like(CVANetLite, D, 7)
    path = export_onnx(net, tmp_path / 'lite.onnx', example_size=(3, 4))
    session = ort.InferenceSession(str(path), providers=['CPUExecutionProvider'])
    (out,) = session.run(None, {'cost_volume': np.zeros((0, D, 3, 5), np.float32)})
    assert out.shape == (0, 3, 5)
    runner = OnnxRuntimeNet(net.fold_batchnorm())
    assert runner(torch.rand(0, 1, D, 15, 17)).shape == (0, 3, 5)
    # Other batches and sizes than the traced one still give the network (dynamic axes).
    volumes = np.random.default_rng(8).random((3, D, 7, 11), dtype=np.float32)
    (out,) = session.run(None, {'cost_volume': volumes})
    for index in range(3):
        np.testing.assert_allclose(out[index], predict_confidence(net, volumes[index]), atol=1e-5)


def test_export_onnx_leaves_an_older_graph_when_the_write_fails(
    onnx_package, tmp_path: Path, file_size_limit
):
    # The graph was written straight to path: a full disk truncated the good graph of an
    # earlier export to the 2000 bytes written (and an opset failure after it kept them).
    path = export_onnx(trained_like(CVANetLite, D, 1), tmp_path / 'net.onnx', example_size=(3, 4))
    good = path.read_bytes()
    with file_size_limit(2000), pytest.raises(
        ModelError, match=r'cannot write the ONNX graph to .*net\.onnx: .*File too large'
    ):
        export_onnx(trained_like(CVANetFast, D, 2), path, example_size=(3, 4))
    assert path.read_bytes() == good
    with pytest.raises(ModelError, match='cannot export to ONNX at opset 7'):
        export_onnx(trained_like(CVANetFast, D, 2), path, opset=7, example_size=(3, 4))
    assert path.read_bytes() == good
    assert [p.name for p in tmp_path.iterdir()] == ['net.onnx']  # no partial file left


@pytest.mark.parametrize(
    ('option', 'message'),
    [
        (['--max-disparity', '32'], r"matcher 'census_bm' and D = 16; asked for D = 32"),
        (['--matcher', 'census_sgm'], r"asked for matcher 'census_sgm'"),
        (['--arch', 'cvanet_fast'], r"arch 'cvanet_lite'; expected 'cvanet_fast'"),
    ],
)
def test_cva_export_checks_the_options_given_with_weights(
    onnx_package, tmp_path: Path, capsys, option: list[str], message: str
):
    # With WEIGHTS, --max-disparity, --matcher and --arch were ignored: exit 0 and a graph of
    # D = 16 for census_bm (its card saying so) where D = 32 for census_sgm was asked for.
    import re

    weights = save_weights(trained_like(CVANetLite, D, 3), tmp_path / 'w.pt',
                           {'matcher': 'census_bm'})
    out = tmp_path / 'lite.onnx'
    assert main([str(weights), '--out', str(out), '--no-check', *option]) == 2
    err = capsys.readouterr().err
    assert err.startswith('cva-export: error: ') and re.search(message, err), err
    assert not out.exists() and not out.with_suffix('.json').exists()
    # Options that agree with the file are taken.
    agreeing = ['--max-disparity', '16', '--matcher', 'census_bm', '--arch', 'cvanet_lite']
    assert main([str(weights), '--out', str(out), '--no-check', *agreeing]) == 0
    card = json.loads(out.with_suffix('.json').read_text(encoding='utf-8'))
    facts = (card['arch'], card['matcher'], card['max_disparity'])
    assert facts == ('cvanet_lite', 'census_bm', D)


def test_cva_export_keeps_the_graph_from_before_when_its_card_cannot_be_written(
    onnx_package, tmp_path: Path, capsys
):
    # The card (.json) was written after the new graph had replaced the old one: when it could
    # not be written (here a folder in its place) the command exited 1 with the old graph gone
    # and a new one without its card (and on a full disk, beside the old graph's card).
    out = export_onnx(trained_like(CVANetFast, D, 4), tmp_path / 'net.onnx', example_size=(3, 4))
    before = out.read_bytes()
    (tmp_path / 'net.json').mkdir()
    weights = save_weights(trained_like(CVANetLite, D, 5), tmp_path / 'w.pt',
                           {'matcher': 'census_bm'})
    assert main([str(weights), '--out', str(out), '--no-check']) == 2
    err = capsys.readouterr().err
    assert 'net.json is a folder' in err and err.count('\n') == 1
    assert out.read_bytes() == before
    # With the folder gone, graph and card are written together, the card whole.
    (tmp_path / 'net.json').rmdir()
    assert main([str(weights), '--out', str(out), '--no-check']) == 0
    assert out.read_bytes() != before
    card = json.loads((tmp_path / 'net.json').read_text(encoding='utf-8'))
    assert (card['arch'], card['max_disparity']) == ('cvanet_lite', D)
    assert sorted(p.name for p in tmp_path.iterdir()) == ['net.json', 'net.onnx', 'w.pt']


@pytest.mark.parametrize(
    ('volume', 'given'),
    [
        (torch.rand(D, 6, 7), r'Tensor of shape \(16, 6, 7\)'),
        (torch.rand(1, 1, D, 6, 7), r'Tensor of shape \(1, 1, 16, 6, 7\)'),
        (torch.rand(1, D, 0, 7), r'Tensor of shape \(1, 16, 0, 7\)'),
        (np.zeros((1, D, 6, 7), np.float32), r'ndarray of shape \(1, 16, 6, 7\)'),
    ],
)
def test_the_exported_model_names_the_volume_it_was_given(volume, given: str):
    # The (B, D, H, W) model padded and unsqueezed first: a (D, H, W) volume was refused as
    # "shape (B, 1, D, H + 12, W + 12); got (16, 1, 18, 19)", a shape the caller never
    # passed, an empty image as "at least 13×13 ...; got 12×19", an array with a TypeError.
    model = CostVolumeModel(trained_like(CVANetLite, D, 6).fold_batchnorm())
    with pytest.raises(InputError, match=r'shape \(B, D, H, W\), H and W >= 1.*got ' + given):
        model(volume)
    volumes = torch.rand(2, D, 6, 7)
    with torch.no_grad():
        out = model(volumes)
    expected = predict_confidence(trained_like(CVANetLite, D, 6), volumes[1].numpy())
    np.testing.assert_allclose(out[1].numpy(), expected, atol=1e-5)

"""ONNX export of the cost-volume networks: the graph ONNX Runtime runs is the network."""

from __future__ import annotations

import json
from pathlib import Path

from light_net_test_utils import trained_like
import numpy as np
import pytest
import torch

from cva_confidence_ros.errors import ModelError
from cva_confidence_ros.model import (
    CVANet,
    CVANetFast,
    CVANetLite,
    predict_confidence,
    save_weights,
)
from cva_confidence_ros.model.baselines import CCNN
from cva_confidence_ros.model.export import check_onnx, export_onnx, main

pytest.importorskip('onnx')
onnxruntime = pytest.importorskip('onnxruntime')

D = 16


@pytest.mark.parametrize('cls', [CVANet, CVANetLite, CVANetFast])
def test_onnx_runtime_gives_the_network_at_any_size(tmp_path: Path, cls: type) -> None:
    net = trained_like(cls, D, 0)
    path = export_onnx(net, tmp_path / 'net.onnx', example_size=(20, 24))
    session = onnxruntime.InferenceSession(str(path), providers=['CPUExecutionProvider'])
    (feed,) = session.get_inputs()
    assert feed.name == 'cost_volume' and feed.shape[1] == D
    rng = np.random.default_rng(1)
    for height, width in ((20, 24), (17, 41)):  # the traced size and another
        volumes = rng.random((2, D, height, width), dtype=np.float32)
        (out,) = session.run(None, {'cost_volume': volumes})
        assert out.shape == (2, height, width)
        for index in range(2):
            expected = predict_confidence(net, volumes[index])
            np.testing.assert_allclose(out[index], expected, atol=1e-5)
    assert check_onnx(path, net, (12, 30), repeat=1)['max_abs_diff'] < 1e-5


def test_the_command_writes_the_graph_and_its_card(tmp_path: Path, capsys) -> None:
    weights = tmp_path / 'cvanet_fast_census_sgm_d16.pt'
    save_weights(trained_like(CVANetFast, D, 2), weights, {'matcher': 'census_sgm'})
    out = tmp_path / 'exported' / 'fast.onnx'
    assert main([str(weights), '--out', str(out), '--check-size', '24x40']) == 0
    err = capsys.readouterr().err
    # 24x40 as given (HxW): it was printed as 40x24.
    assert 'ONNX Runtime vs PyTorch at 24x40 (HxW, as --check-size): max |difference|' in err
    card = json.loads(out.with_suffix('.json').read_text())
    facts = (card['arch'], card['matcher'], card['max_disparity'])
    assert facts == ('cvanet_fast', 'census_sgm', D)
    assert card['input']['shape'] == ['batch', D, 'height', 'width']
    assert card['check']['size'] == [24, 40] and card['check']['max_abs_diff'] < 1e-5


def test_what_cannot_be_exported_is_refused(tmp_path: Path, capsys) -> None:
    torch.manual_seed(0)
    baseline = tmp_path / 'ccnn_census_bm_d16.pt'
    save_weights(CCNN(D), baseline, {'matcher': 'census_bm'})
    assert main([str(baseline), '--out', str(tmp_path / 'c.onnx'), '--no-check']) == 2
    assert 'ONNX export covers the cost-volume networks' in capsys.readouterr().err
    with pytest.raises(ModelError, match='cost-volume networks'):
        export_onnx(CCNN(D), tmp_path / 'c.onnx')
    weights = tmp_path / 'w.pt'
    save_weights(trained_like(CVANetFast, D, 3), weights, {'matcher': 'census_bm'})
    assert main([str(weights), '--out', str(tmp_path / 'w.txt'), '--no-check']) == 2
    assert 'must name a .onnx file' in capsys.readouterr().err
    assert not (tmp_path / 'c.onnx').exists()


@pytest.mark.parametrize('cls', [CVANet, CVANetLite, CVANetFast])
def test_the_onnxruntime_backend_gives_the_torch_values(cls: type) -> None:
    from cva_confidence_ros.model import SparseConfig, SparseEvaluator

    net = trained_like(cls, D, 4)
    volume = np.random.default_rng(5).random((D, 23, 37), dtype=np.float32)
    torch_eval = SparseEvaluator(net)
    ort_eval = SparseEvaluator(net, backend='onnxruntime')
    np.testing.assert_allclose(ort_eval(volume), torch_eval(volume), atol=1e-5)
    # A few pixels: 13×13 extracts, batched, through the same graph.
    ys, xs = np.array([0, 5, 22]), np.array([36, 0, 17])
    np.testing.assert_allclose(ort_eval.at(volume, ys, xs), torch_eval(volume)[ys, xs], atol=1e-5)
    assert ort_eval.path_counts['extracts'] == 1 and ort_eval.path_counts['fused'] == 0
    # The sparse fast paths sit above the network and work with either.
    image = np.random.default_rng(6).integers(0, 256, (23, 37), dtype=np.uint8)
    disparity = volume.argmin(axis=0).astype(np.float32)
    sparse = SparseConfig(stride=2)
    np.testing.assert_allclose(
        ort_eval.confidence(volume, image, disparity, sparse).confidence,
        torch_eval.confidence(volume, image, disparity, sparse).confidence,
        atol=1e-4,
    )


def test_backend_options_that_cannot_work_are_refused() -> None:
    from cva_confidence_ros.errors import ConfigError
    from cva_confidence_ros.model.sparse import check_backend
    from cva_confidence_ros.pipeline import PipelineConfig

    cpu = torch.device('cpu')
    with pytest.raises(ConfigError, match="cva_backend must be one of .* got 'tensorrt'"):
        check_backend('tensorrt', cpu, 'fp32')
    with pytest.raises(ConfigError, match='runs the network on the CPU; got device cuda'):
        check_backend('onnxruntime', torch.device('cuda'), 'fp32')
    with pytest.raises(ConfigError, match="float32 network; got cva_precision 'bf16'"):
        check_backend('onnxruntime', cpu, 'bf16')
    with pytest.raises(ConfigError, match='cva_backend must be one of'):
        PipelineConfig(cva_backend='tensorrt')


def test_the_pipeline_with_onnxruntime_matches_torch() -> None:
    from cva_confidence_ros.pipeline import PipelineConfig, StereoPipeline

    rng = np.random.default_rng(7)
    texture = rng.integers(0, 256, (48, 128 + 6), dtype=np.uint8)
    left, right = texture[:, 6:].copy(), texture[:, :-6].copy()
    results = {
        backend: StereoPipeline(
            PipelineConfig(matcher='census_bm', max_disparity=64, device='cpu',
                           confidence_method='cva_net_fast', cva_backend=backend)
        ).process(left, right)
        for backend in ('torch', 'onnxruntime')
    }
    np.testing.assert_allclose(
        results['onnxruntime'].raw_confidence, results['torch'].raw_confidence, atol=1e-5
    )


def test_an_opset_the_exporter_cannot_write_exits_2_with_one_line(tmp_path: Path,
                                                                  capsys) -> None:
    weights = tmp_path / 'w.pt'
    save_weights(trained_like(CVANetFast, D, 4), weights, {'matcher': 'census_bm'})
    for opset in ('0', '-1', '99'):
        out = tmp_path / f'opset{opset}.onnx'
        assert main([str(weights), '--out', str(out), '--opset', opset, '--no-check']) == 2
        err = capsys.readouterr().err
        assert err.count('\n') == 1 and err.startswith('cva-export: error: ONNX opset must be')
        assert f'got {opset}' in err and not out.exists()
    with pytest.raises(ModelError, match=r'ONNX opset must be an integer in \[\d+, \d+\].*got 1'):
        export_onnx(trained_like(CVANetFast, D, 4), tmp_path / 'x.onnx', opset=1)

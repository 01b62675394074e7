"""Review 29 of the light networks, their weights files and the ONNX export: regression tests
for what it found (all in the export and the weights-file messages)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

from light_net_test_utils import trained_like
import numpy as np
import pytest
import torch
from torch import nn

from cva_confidence_ros.errors import InputError, ModelError
from cva_confidence_ros.model import (
    CVANet,
    CVANetFast,
    CVANetLite,
    save_weights,
)

D = 16
ARCHS = [CVANet, CVANetLite, CVANetFast]

pytestmark = pytest.mark.usefixtures('one_torch_thread')


@pytest.fixture
def float64_default() -> Iterator[None]:
    previous = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    try:
        yield
    finally:
        torch.set_default_dtype(previous)


def test_check_onnx_reports_a_graph_that_does_not_run_as_a_model_error(ort, tmp_path: Path):
    # The docstring promised ModelError when "the graph does not run"; a graph of another D
    # raised onnxruntime's own InvalidArgument from session.run.
    from cva_confidence_ros.model.export import check_onnx, export_onnx

    path = export_onnx(trained_like(CVANetFast, D), tmp_path / 'd16.onnx', example_size=(14, 14))
    with pytest.raises(ModelError, match=r'ONNX Runtime cannot run .*d16\.onnx.*\(1, 24, 8, 9\)'):
        check_onnx(path, CVANetFast(24).eval(), (8, 9), repeat=1)


@pytest.mark.parametrize('cls', ARCHS)
def test_the_onnxruntime_backend_runs_a_float64_folded_network(ort, cls: type):
    # Review 26 made a folded network after .double() run every torch way; the onnxruntime
    # backend traced it with a float32 example: "cannot export to ONNX at opset 17
    # (RuntimeError: Input type (float) and bias type (double) should be the same)".
    from cva_confidence_ros.model.sparse import SparseEvaluator

    folded = trained_like(cls, D, 1).fold_batchnorm().double()
    volume = np.random.default_rng(2).random((D, 5, 7), dtype=np.float32)
    expected = SparseEvaluator(folded)(volume)
    evaluator = SparseEvaluator(folded, backend='onnxruntime')
    np.testing.assert_allclose(evaluator(volume), expected, atol=1e-5)
    assert next(folded.parameters()).dtype == torch.float64  # the caller's copy untouched


@pytest.mark.parametrize('cls', [CVANetLite, CVANetFast])
def test_export_under_a_float64_default_dtype_writes_the_float32_graph(
    ort, float64_default, tmp_path: Path, cls: type
):
    # The folded layers are built in the default dtype and the traced example was torch.rand
    # in it: the graph came out float64 (input tensor(double)), which ONNX Runtime could not
    # even load ("Could not find an implementation for Conv(11)"), against the documented
    # float32 input; OnnxRuntimeNet failed the same way.
    import onnx

    from cva_confidence_ros.model.export import OnnxRuntimeNet, check_onnx, export_onnx

    net = trained_like(cls, D, 3)
    path = export_onnx(net, tmp_path / 'net.onnx', example_size=(14, 14))
    graph = onnx.load(str(path))
    assert graph.graph.input[0].type.tensor_type.elem_type == onnx.TensorProto.FLOAT
    assert check_onnx(path, net, (6, 9), repeat=1)['max_abs_diff'] < 1e-5
    padded = torch.rand(1, 1, D, 15, 16, dtype=torch.float32)
    with torch.no_grad():
        expected = net(padded.double()).float()
    runner = OnnxRuntimeNet(net.fold_batchnorm())
    torch.testing.assert_close(runner(padded), expected, atol=1e-5, rtol=0)


def test_export_and_check_leave_the_network_in_training_mode(ort, tmp_path: Path):
    # _deployable called net.eval() on the caller's network: exporting a checkpoint in the
    # middle of a training run switched off its dropout and BN updates for the rest of it.
    from cva_confidence_ros.model.export import check_onnx, export_onnx

    net = trained_like(CVANetFast, D, 4).train()
    path = export_onnx(net, tmp_path / 'net.onnx', example_size=(14, 14))
    assert net.training and all(module.training for module in net.modules())
    # The graph is still the eval-mode network (folded BN statistics, no dropout).
    assert check_onnx(path, net, (6, 9), repeat=1)['max_abs_diff'] < 1e-5
    assert net.training


@pytest.mark.parametrize('cls', [CVANet, CVANetFast])
def test_export_takes_a_wrapped_network_as_save_weights_does(ort, tmp_path: Path, cls: type):
    # architecture_of unwraps (Distributed)DataParallel, but _deployable then called
    # fold_batchnorm on the wrapper: "expected a CVANet; got DataParallel" / AttributeError.
    from cva_confidence_ros.model.export import check_onnx, export_onnx

    net = trained_like(cls, D, 5)
    wrapped = nn.DataParallel(net)
    save_weights(wrapped, tmp_path / 'w.pt', {'matcher': 'census_bm'})  # accepted there
    path = export_onnx(wrapped, tmp_path / 'net.onnx', example_size=(14, 14))
    assert check_onnx(path, net, (5, 6), repeat=1)['max_abs_diff'] < 1e-5


def test_the_onnxruntime_net_checks_its_input_as_the_network_does(ort):
    # OnnxRuntimeNet cast an integer volume to float32 without a word (CVA-Net-Fast gave
    # confidence 1.0 for a uint8 volume, which the network refuses since review 26) and left
    # a wrong depth or size to ONNX Runtime's InvalidArgument.
    from cva_confidence_ros.model.export import OnnxRuntimeNet

    runner = OnnxRuntimeNet(trained_like(CVANetFast, D, 6).fold_batchnorm())
    volume = torch.randint(0, 256, (1, 1, D, 13, 13), dtype=torch.uint8)
    with pytest.raises(InputError, match='floating-point.*uint8'):
        runner(volume)
    with pytest.raises(InputError, match='depth D = 16; got depth 17'):
        runner(torch.rand(1, 1, D + 1, 13, 13))
    with pytest.raises(InputError, match='at least 13×13'):
        runner(torch.rand(1, 1, D, 12, 13))
    assert runner(torch.rand(2, 1, D, 13, 14)).shape == (2, 1, 2)


def test_a_depth_of_another_type_is_named_as_it_is(tmp_path: Path):
    # "meta['max_disparity'] = 16 contradicts the network's D = 16" for the string '16'.
    with pytest.raises(ModelError, match=r"= '16' contradicts the network's D = 16"):
        save_weights(CVANetLite(D), tmp_path / 'w.pt', {'matcher': 'm', 'max_disparity': '16'})
    assert not (tmp_path / 'w.pt').exists()


def test_cva_export_leaves_no_graph_that_failed_its_check(tmp_path, capsys, monkeypatch):
    # The .onnx was written before the check and stayed when the check failed (exit 2), over
    # any good graph from before: a deploy script looking for the file took it.
    from cva_confidence_ros.model import CVANetFast, save_weights
    import cva_confidence_ros.model.export as export

    torch.manual_seed(0)
    weights = tmp_path / 'cvanet_fast_census_sgm_d16.pt'
    save_weights(CVANetFast(16).eval(), weights, {'matcher': 'census_sgm'})
    out = tmp_path / 'fast.onnx'
    assert export.main([str(weights), '--out', str(out), '--check-size', '24x40']) == 0
    good = out.read_bytes()
    capsys.readouterr()

    def failing(path, net, size, repeat=3):
        return {'max_abs_diff': 0.5, 'onnxruntime_ms': 1.0, 'torch_ms': 1.0}

    monkeypatch.setattr(export, 'check_onnx', failing)
    assert export.main([str(weights), '--out', str(out), '--check-size', '24x40']) == 2
    assert f'differs from PyTorch by 5.00e-01 (more than 1e-4); {out} not written' in (
        capsys.readouterr().err
    )
    assert out.read_bytes() == good
    assert not list(tmp_path.glob('.*unchecked*'))  # the graph that failed is gone


def test_export_onnx_makes_its_folders_and_names_a_place_it_cannot_write(tmp_path):
    # A missing folder gave FileNotFoundError and a folder IsADirectoryError (save_weights
    # makes its folders and raises ModelError).
    from cva_confidence_ros.model import CVANetFast
    from cva_confidence_ros.model.export import export_onnx

    net = CVANetFast(16).eval()
    path = export_onnx(net, tmp_path / 'a' / 'b' / 'fast.onnx', example_size=(16, 20))
    assert path.stat().st_size > 1000
    with pytest.raises(ModelError, match='/a/b: it is a folder'):
        export_onnx(net, tmp_path / 'a' / 'b', example_size=(16, 20))
    (tmp_path / 'file').write_text('x')
    with pytest.raises(ModelError, match='cannot write the ONNX graph to .*file/x.onnx'):
        export_onnx(net, tmp_path / 'file' / 'x.onnx', example_size=(16, 20))


def test_weights_of_another_kind_of_tensor_or_meta_key_are_refused_by_name(tmp_path):
    # A complex tensor loaded as its real part and a float counter as an integer, without a
    # word; a tuple key in meta raised json's TypeError.
    from cva_confidence_ros.model import CVANetFast, load_weights, save_weights

    net = CVANetFast(16)
    with pytest.raises(ModelError, match='meta must hold plain values under text keys'):
        save_weights(net, tmp_path / 'k.pt', {'matcher': 'census_bm', (1, 2): 'x'})
    path = save_weights(net, tmp_path / 'w.pt', {'matcher': 'census_bm'})
    blob = torch.load(path, weights_only=True)
    name = next(k for k, v in blob['state_dict'].items() if v.is_floating_point())
    counter = next(k for k, v in blob['state_dict'].items() if not v.is_floating_point())
    for key, value in ((name, blob['state_dict'][name].to(torch.complex64)),
                       (counter, blob['state_dict'][counter].double())):
        broken = {**blob, 'state_dict': {**blob['state_dict'], key: value}}
        torch.save(broken, tmp_path / 'broken.pt')
        with pytest.raises(ModelError, match=rf'do not fit .*{key} is torch\.'):
            load_weights(tmp_path / 'broken.pt', arch=None)
    assert load_weights(path, arch=None)[1]['arch'] == 'cvanet_fast'

"""CCNN, LFN and LGC-Net: shapes, parameter counts, a training step, weights, dense vs patch."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from cva_confidence_ros.confidence import CONFIDENCE_METHODS, ConfidenceInputs
from cva_confidence_ros.errors import InputError, ModelError
from cva_confidence_ros.model import ARCHITECTURES, load_weights, save_weights
from cva_confidence_ros.model.baselines import (
    CCNN,
    LFN,
    ConfNet,
    LGCNet,
    ccnn_parameter_count,
    confnet_parameter_count,
    fusion_parameter_count,
    lfn_parameter_count,
    lgcnet_parameter_count,
    network_inputs,
    predict_disparity_confidence,
)

D = 16
ARCHS = ('ccnn', 'lfn', 'lgcnet')


def _count(net: torch.nn.Module) -> int:
    return sum(p.numel() for p in net.parameters())


def _net(arch: str, seed: int = 0) -> torch.nn.Module:
    torch.manual_seed(seed)
    return ARCHITECTURES.get(arch)({'max_disparity': D})


def _planes(height: int, width: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    return (
        torch.rand((1, 1, height, width), generator=gen),
        torch.rand((1, 1, height, width), generator=gen),
    )


def test_parameter_counts_follow_the_architectures():
    # CCNN by hand: conv 1→64 (640) + 3 × conv 64→64 (36,928) + 1×1 64→100 (6,500)
    # + 1×1 100→100 (10,100) + 1×1 100→1 (101).
    assert ccnn_parameter_count() == 640 + 3 * 36_928 + 6_500 + 10_100 + 101 == 128_125
    # LFN: two towers, then 1×1 128→100 (12,900), 100→100, 100→1.
    assert lfn_parameter_count() == 2 * (640 + 3 * 36_928) + 12_900 + 10_100 + 101
    # ConfNet (width 32): input convs 2 × 320, encoders 64/128/256/512, four decoders.
    encoders = 36_928 + 73_856 + 295_168 + 1_180_160
    decoders = (1_179_904 + 1_769_728) + (295_040 + 442_496) + (73_792 + 110_656) + (
        18_464 + 27_680
    )
    assert confnet_parameter_count() == 2 * 320 + encoders + decoders + 289
    assert fusion_parameter_count() == 3 * (640 + 3 * 36_928) + 19_300 + 10_100 + 101
    counts = {arch: _count(_net(arch)) for arch in ARCHS}
    print('parameters:', counts, 'ConfNet', _count(ConfNet()))
    assert counts == {
        'ccnn': ccnn_parameter_count(),
        'lfn': lfn_parameter_count(),
        'lgcnet': lgcnet_parameter_count(),
    }
    assert _count(ConfNet()) == confnet_parameter_count()
    assert _count(ConfNet(8)) == confnet_parameter_count(8)


@pytest.mark.parametrize('arch', ['ccnn', 'lfn'])
@pytest.mark.parametrize('batch', [1, 3])
def test_local_network_shapes(arch, batch):
    net = _net(arch)
    disparity, image = torch.rand(batch, 1, 9 + 5, 9 + 7), torch.rand(batch, 1, 14, 16)
    assert net.forward_logits(disparity, image).shape == (batch, 1, 6, 8)
    out = net.dense_confidence(disparity, image)
    assert out.shape == (batch, 1, 14, 16)
    assert bool(((out > 0) & (out < 1)).all())


@pytest.mark.parametrize('size', [(16, 32), (21, 37), (5, 3)])
def test_confnet_and_lgcnet_any_size(size):
    net = _net('lgcnet')
    disparity, image = _planes(*size)
    out = net.dense_confidence(disparity, image)
    assert out.shape == (1, 1, *size)
    assert net.confnet.dense_confidence(disparity, image).shape == (1, 1, *size)
    with pytest.raises(InputError, match='multiples of 16'):
        net.confnet.forward_logits(*_planes(20, 32))


@pytest.mark.parametrize('arch', ['ccnn', 'lfn'])
def test_dense_equals_patch(arch):
    """The whole-image map at a pixel equals the network applied to that pixel's 9×9 patch."""
    net = _net(arch).eval()
    disparity, image = _planes(13, 17, seed=1)
    with torch.no_grad():
        dense = net.dense_confidence(disparity, image)[0, 0]
        padded = [F.pad(t, (4, 4, 4, 4), mode='replicate') for t in (disparity, image)]
        for y, x in [(0, 0), (6, 8), (12, 16), (3, 15)]:
            patch = [t[:, :, y : y + 9, x : x + 9] for t in padded]
            single = net(*patch)
            assert single.shape == (1, 1, 1, 1)
            assert float(single) == pytest.approx(float(dense[y, x]), abs=1e-6)


def test_lgcnet_dense_equals_fusion_on_patches_of_its_parts():
    net = _net('lgcnet').eval()
    disparity, image = _planes(19, 23, seed=2)
    with torch.no_grad():
        dense = net(disparity, image)[0, 0]
        parts = net.parts(disparity, image)
        assert all(p.shape == (1, 1, 27, 31) for p in parts)
        for y, x in [(0, 0), (9, 11), (18, 22)]:
            patch = [p[:, :, y : y + 9, x : x + 9] for p in parts]
            value = torch.sigmoid(net.fusion.forward_logits(*patch))
            assert float(value) == pytest.approx(float(dense[y, x]), abs=1e-6)


@pytest.mark.parametrize('arch', ARCHS)
def test_one_training_step_lowers_the_loss(arch):
    net = _net(arch, seed=3)
    disparity, image = _planes(32, 32, seed=4)
    # Target: the disparity is "correct" where it is smooth (an easy, learnable rule).
    target = (disparity[0, 0] > 0.5).float()[None]
    if arch == 'lgcnet':
        params = list(net.local.parameters()) + list(net.confnet.parameters()) + list(
            net.fusion.parameters()
        )

        def loss_fn() -> torch.Tensor:
            out = net(disparity, image)[:, 0].clamp(1e-6, 1 - 1e-6)
            return F.binary_cross_entropy(out, target)
    else:
        params = list(net.parameters())
        padded = [F.pad(t, (4, 4, 4, 4), mode='replicate') for t in (disparity, image)]

        def loss_fn() -> torch.Tensor:
            return F.binary_cross_entropy_with_logits(net.forward_logits(*padded)[:, 0], target)

    optimiser = torch.optim.Adam(params, lr=1e-3)
    before = loss_fn()
    optimiser.zero_grad()
    before.backward()
    optimiser.step()
    with torch.no_grad():
        after = loss_fn()
    assert float(after) < float(before.detach())


@pytest.mark.parametrize('arch', ARCHS)
def test_save_load_round_trip(tmp_path, arch):
    net = _net(arch, seed=5).eval()
    stored = net.half() if arch == 'lgcnet' else net  # LGC-Net ships as float16
    path = save_weights(stored, tmp_path / f'{arch}.pt', {'matcher': 'census_sgm'})
    loaded, meta = load_weights(path, matcher='census_sgm', max_disparity=D, arch=arch)
    assert meta['arch'] == arch and type(loaded) is type(net)
    assert all(p.dtype == torch.float32 for p in loaded.parameters())
    for key, value in stored.state_dict().items():
        assert torch.equal(loaded.state_dict()[key], value.float()), key
    with pytest.raises(ModelError, match=f"arch '{arch}'; expected 'cvanet'"):
        load_weights(path)
    with pytest.raises(ModelError, match='asked for D = 32'):
        load_weights(path, max_disparity=32, arch=arch)


def test_network_inputs_fill_and_grey():
    disparity = np.array([[0.0, 8.0], [np.nan, np.inf]], np.float32)
    rgb = np.zeros((2, 2, 3), np.uint8)
    rgb[0, 0] = (255, 0, 0)
    d, i = network_inputs(disparity, rgb, 16)
    np.testing.assert_allclose(d, [[0.0, 0.5], [0.0, 0.0]])
    assert i[0, 0] == pytest.approx(0.299) and i[1, 1] == 0.0
    with pytest.raises(InputError, match='image must be'):
        network_inputs(disparity, np.zeros((3, 2), np.uint8), 16)


@pytest.fixture(scope='module')
def shipped_like(tmp_path_factory):
    folder = tmp_path_factory.mktemp('w')
    paths = {}
    for arch in ARCHS:
        paths[arch] = save_weights(_net(arch), folder / f'{arch}.pt', {'matcher': 'census_bm'})
    return paths


def _inputs(depth: int = D, matcher: str = 'census_bm') -> ConfidenceInputs:
    rng = np.random.default_rng(0)
    volume = rng.random((depth, 14, 15), dtype=np.float32)
    disparity = volume.argmin(axis=0).astype(np.float32)
    disparity[0, 0] = np.nan
    return ConfidenceInputs(
        cost_volume=volume,
        disparity=disparity,
        image=rng.integers(0, 255, (14, 15, 3), dtype=np.uint8),
        matcher=matcher,
    )


@pytest.mark.parametrize(('method', 'arch'), [('ccnn', 'ccnn'), ('lfn', 'lfn'),
                                              ('lgc_net', 'lgcnet')])
def test_registered_methods(shipped_like, method, arch):
    factory = CONFIDENCE_METHODS.get(method)
    built = factory(matcher='census_bm', max_disparity=D, weights=str(shipped_like[arch]),
                    device='cpu', tile_budget_mb=64.0)
    inputs = _inputs()
    confidence = built(inputs)
    assert confidence.shape == (14, 15) and confidence.dtype == np.float32
    assert np.isfinite(confidence).all() and ((confidence > 0) & (confidence < 1)).all()
    expected = predict_disparity_confidence(built.net, inputs.disparity, inputs.image)
    np.testing.assert_array_equal(confidence, expected)
    with pytest.raises(InputError, match='D = 16; got a cost volume of depth 20'):
        built(_inputs(depth=20))
    with pytest.raises(InputError, match="for matcher 'census_bm'; got inputs of 'mccnn_fast'"):
        built(_inputs(matcher='mccnn_fast'))
    with pytest.raises(ModelError, match="asked for matcher 'census_sgm'"):
        factory(matcher='census_sgm', max_disparity=D, weights=str(shipped_like[arch]))
    other = 'ccnn' if arch != 'ccnn' else 'lfn'
    with pytest.raises(ModelError, match=f"arch '{other}'; expected '{arch}'"):
        factory(matcher='census_bm', max_disparity=D, weights=str(shipped_like[other]))


def test_missing_shipped_weights_say_how_to_train():
    with pytest.raises(ModelError, match='cva-train --arch lgcnet --matcher census_bm'):
        CONFIDENCE_METHODS.get('lgc_net')(matcher='census_bm', max_disparity=24)


def test_predict_rejects_other_networks():
    from cva_confidence_ros.model import CVANet

    with pytest.raises(ModelError, match='expected a network of'):
        predict_disparity_confidence(CVANet(16), np.zeros((4, 4)), np.zeros((4, 4), np.uint8))
    assert isinstance(_net('lfn'), LFN) and isinstance(_net('ccnn'), CCNN)
    assert isinstance(_net('lgcnet'), LGCNet)


@pytest.mark.parametrize(('method', 'arch'), [('ccnn', 'ccnn'), ('lgc_net', 'lgcnet')])
def test_usable_as_the_pipelines_confidence_method(shipped_like, method, arch):
    from cva_confidence_ros.datasets.synthetic import synthetic_pair
    from cva_confidence_ros.pipeline import PipelineConfig, StereoPipeline

    pair = synthetic_pair(5, 32, 48, D)
    config = PipelineConfig(matcher='census_bm', max_disparity=D, confidence_method=method,
                            model_path=str(shipped_like[arch]))
    result = StereoPipeline(config).process(pair.left, pair.right)
    assert result.confidence.shape == (32, 48)
    assert ((result.confidence > 0) & (result.confidence < 1)).all()


@pytest.mark.parametrize('matcher', ['census_bm', 'census_sgm', 'mccnn_fast'])
@pytest.mark.parametrize(('method', 'arch'), [('ccnn', 'ccnn'), ('lfn', 'lfn'),
                                              ('lgc_net', 'lgcnet')])
def test_shipped_weights_load_and_have_cards(method, arch, matcher):
    from cva_confidence_ros.model import default_weights_path

    try:
        path = default_weights_path(matcher, 64, arch)
    except ModelError:
        pytest.skip(f'no shipped {arch} weights for {matcher}')
    built = CONFIDENCE_METHODS.get(method)(matcher=matcher, max_disparity=64)
    assert built.meta['arch'] == arch and built.meta['samples_seen'] > 0
    card = path.with_suffix('.md').read_text()
    assert card.startswith(f'# {built.meta["network"]} weights')
    assert '## Evaluation on the develop split' in card and '(to be added)' not in card

"""``hubconf.py``: the networks and the pipeline through ``torch.hub.load`` from a checkout."""

from __future__ import annotations

from pathlib import Path
import re

import numpy as np
import pytest

torch = pytest.importorskip('torch')

from cva_confidence_ros.errors import ConfigError, ModelError  # noqa: E402
from cva_confidence_ros.model import load_weights, predict_confidence  # noqa: E402
from cva_confidence_ros.model.baselines import predict_disparity_confidence  # noqa: E402
from cva_confidence_ros.model.weights import default_weights_path  # noqa: E402
from cva_confidence_ros.pipeline import PipelineConfig, StereoPipeline  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def _hub(entry: str, **options: object) -> object:
    return torch.hub.load(str(ROOT), entry, source='local', verbose=False, **options)


@pytest.mark.parametrize('arch', ['cvanet', 'cvanet_fast', 'cvanet_lite'])
def test_a_network_comes_with_its_shipped_weights_and_predicts(arch: str) -> None:
    net = _hub(arch, matcher='census_sgm', max_disparity=64)
    shipped, meta = load_weights(default_weights_path('census_sgm', 64, arch), arch=arch)
    assert net.meta == meta and not net.training
    for (name, a), (_, b) in zip(net.state_dict().items(), shipped.state_dict().items(),
                                 strict=True):
        assert torch.equal(a, b), name
    volume = np.random.default_rng(1).uniform(0.0, 1.0, (64, 17, 23)).astype(np.float32)
    np.testing.assert_array_equal(net.predict(volume), predict_confidence(shipped, volume))


def test_untrained_networks_of_any_depth() -> None:
    net = _hub('cvanet', pretrained=False, max_disparity=32)
    assert net.max_disparity == 32 and net.meta['matcher'] == 'census_bm'
    assert net.predict(np.full((32, 5, 6), 0.5, np.float32)).shape == (5, 6)
    # The paper's network at D = 256: the parameter count the paper states, counted as Keras does.
    paper = _hub('cvanet', pretrained=False, max_disparity=256)
    counted = sum(p.numel() for p in paper.parameters()) + sum(
        b.numel() for name, b in paper.named_buffers() if name.endswith(('running_mean',
                                                                           'running_var')))
    assert counted == 782_725


@pytest.mark.parametrize('arch', ['ccnn', 'lfn', 'lgcnet'])
def test_a_baseline_judges_a_disparity_map(arch: str) -> None:
    net = _hub(arch)
    shipped, _ = load_weights(default_weights_path('census_bm', 64, arch), arch=arch)
    assert net.meta['arch'] == arch
    rng = np.random.default_rng(2)
    disparity = rng.uniform(0.0, 60.0, (24, 31)).astype(np.float32)
    image = rng.integers(0, 256, (24, 31), dtype=np.uint8)
    np.testing.assert_array_equal(
        net.predict(disparity, image), predict_disparity_confidence(shipped, disparity, image)
    )


def test_the_pipeline_is_the_node_pipeline() -> None:
    rng = np.random.default_rng(3)
    texture = rng.integers(0, 256, (40, 90), dtype=np.uint8)
    left, right = texture[:, :64].copy(), texture[:, 6:70].copy()  # disparity 6
    options = {'matcher': 'census_bm', 'max_disparity': 16, 'confidence_method': 'pkrn'}
    hub = _hub('pipeline', **options).process(left, right)
    direct = StereoPipeline(PipelineConfig(**options)).process(left, right)
    np.testing.assert_array_equal(hub.confidence, direct.confidence)
    np.testing.assert_array_equal(hub.valid, direct.valid)
    assert np.nanmedian(hub.disparity[:, 20:]) == pytest.approx(6.0, abs=0.5)


def test_weights_that_are_not_shipped_say_how_to_train_them() -> None:
    with pytest.raises(ModelError, match=r'no shipped cvanet weights cvanet_census_bm_d128\.pt'
                       r'.*cva-train --arch cvanet --matcher census_bm --max-disparity 128'):
        _hub('cvanet', max_disparity=128)


@pytest.mark.parametrize(
    ('options', 'message'),
    [
        ({'max_disparity': 64.7}, 'max_disparity must be an integer ≥ 1; got 64.7'),
        ({'max_disparity': 0}, 'max_disparity must be an integer ≥ 1; got 0'),
        ({'max_disparity': True}, 'max_disparity must be an integer ≥ 1; got True'),
        ({'matcher': 'census_xx'}, "unknown matcher 'census_xx'"),
    ],
)
def test_an_untrained_network_of_an_impossible_depth_or_matcher_is_refused(
    options: dict[str, object], message: str
) -> None:
    # Untrained, 64.7 used to become D = 64 and any matcher name went into net.meta.
    with pytest.raises(ConfigError, match=re.escape(message)):
        _hub('cvanet', pretrained=False, **options)


@pytest.mark.parametrize('arch', ['cvanet_fast', 'lgcnet'])
def test_a_hub_network_can_be_saved_whole_and_loaded_back(arch: str, tmp_path: Path) -> None:
    net = _hub(arch, pretrained=False, max_disparity=16)
    path = tmp_path / 'net.pt'
    torch.save(net, path)  # pickles net.predict with the network
    back = torch.load(path, weights_only=False)
    assert back.meta == net.meta and back.predict._net[0] is back
    rng = np.random.default_rng(4)
    if arch == 'lgcnet':
        disparity = rng.uniform(0.0, 15.0, (9, 11)).astype(np.float32)
        image = rng.integers(0, 256, (9, 11), dtype=np.uint8)
        np.testing.assert_array_equal(back.predict(disparity, image),
                                      net.predict(disparity, image))
    else:
        volume = rng.uniform(0.0, 1.0, (16, 9, 11)).astype(np.float32)
        np.testing.assert_array_equal(back.predict(volume), net.predict(volume))

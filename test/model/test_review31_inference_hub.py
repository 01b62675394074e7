"""Review 31: the folded head keeps to the tile budget, ``from_options`` of a method that is no
dataclass, a bare cost volume given to ``cva_net``, and the sizes ``tile_shape`` takes."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from cva_confidence_ros.confidence import ConfidenceInputs
from cva_confidence_ros.confidence.base import ConfidenceMethod
from cva_confidence_ros.confidence.cva_net import CVANetConfidence
from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.model import CVANet, fold_batchnorm, save_weights, tile_shape

DEPTH = 14

pytestmark = pytest.mark.usefixtures('one_torch_thread')


@pytest.fixture(scope='module')
def weights(tmp_path_factory: pytest.TempPathFactory) -> Path:
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp('weights') / 'cvanet_d14.pt'
    return save_weights(CVANet(DEPTH).eval(), path, {'matcher': 'census_bm'})


def _inputs(height: int = 5, width: int = 6) -> ConfidenceInputs:
    volume = np.random.default_rng(0).random((DEPTH, height, width), dtype=np.float32)
    disparity = np.argmin(volume, axis=0).astype(np.float32)
    return ConfidenceInputs(volume, disparity, np.zeros((height, width), dtype=np.uint8))


def test_the_head_pads_no_more_curve_at_once_than_it_was_given() -> None:
    # The depth convolutions pad each (32, D − 12) curve by 63 values: at D = 64 all pixels of
    # a tile at once took 2.2 times the fused curves (a 90×90 tile at 256 MB peaked at 400 MB,
    # 1.56 times the budget; 233 MB now).
    torch.manual_seed(0)
    net = fold_batchnorm(CVANet(64).eval())
    curves = torch.rand(120, 32, 64 - 12)
    seen: list[int] = []
    hooks = [
        conv.register_forward_pre_hook(lambda _, args: seen.append(args[0].numel()))
        for conv in net.depth
    ]
    try:
        with torch.inference_mode():
            logits = net.head_logits(curves)
    finally:
        for hook in hooks:
            hook.remove()
    assert max(seen) <= curves.numel()
    with torch.inference_mode():
        one_by_one = torch.cat([net.head_logits(curves[i : i + 1]) for i in range(120)])
    assert logits.shape == (120,)
    torch.testing.assert_close(logits, one_by_one, atol=1e-5, rtol=0)


class _Untyped(ConfidenceMethod):
    """A method that is no dataclass, as ``cva_net``: its options are ``__init__``'s."""

    def __init__(self, max_disparity: int = 64, scale: float = 1.0, **_: Any) -> None:
        self.max_disparity = max_disparity
        self.scale = scale

    def __call__(self, inputs: ConfidenceInputs) -> np.ndarray:
        return np.zeros(inputs.shape, dtype=np.float32)


def test_from_options_passes_the_init_parameters_of_a_method_that_is_no_dataclass() -> None:
    # Every option was dropped (a generic one as max_disparity too): the method ran with its
    # defaults, and its own options were refused as unknown ("expected []").
    method = _Untyped.from_options(max_disparity=14, scale=2.0, device='cpu')
    assert (method.max_disparity, method.scale) == (14, 2.0)
    expected = r"unknown options \['sigma'\].*'max_disparity', 'scale'"
    with pytest.raises(ConfigError, match=expected):
        _Untyped.from_options(sigma=1.0)


def test_cva_net_from_options_loads_the_weights_it_is_given(weights: Path) -> None:
    # It loaded the shipped census_bm D = 64 weights whatever weights, D and stride said.
    method = CVANetConfidence.from_options(max_disparity=DEPTH, weights=str(weights), cva_stride=2)
    assert isinstance(method, CVANetConfidence)
    assert (method.max_disparity, method.weights_path, method.sparse.stride) == (DEPTH, weights, 2)
    assert method(_inputs()).shape == (5, 6)


def test_cva_net_names_a_bare_cost_volume(weights: Path) -> None:
    # It failed with "'numpy.ndarray' object has no attribute 'max_disparity'".
    method = CVANetConfidence(max_disparity=DEPTH, weights=weights)
    volume = _inputs().cost_volume
    with pytest.raises(InputError, match=r'takes a ConfidenceInputs .*got ndarray'):
        method(volume)  # type: ignore[arg-type]
    with pytest.raises(InputError, match=r'takes a ConfidenceInputs .*got ndarray'):
        method.confidence_at(volume, np.array([0]), np.array([0]))  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ('sizes', 'name'),
    [
        ((0, 5, 14), 'height'),
        ((-3, 5, 14), 'height'),
        ((5, 0, 14), 'width'),
        ((5, 4.0, 14), 'width'),
        ((5, 5, True), 'max_disparity'),
        ((5, 5, 14, 2.5), 'activations_per_pixel'),
        ((5, 5, 14, float('nan')), 'activations_per_pixel'),
        ((5, 5, 14, 0), 'activations_per_pixel'),
    ],
)
def test_tile_shape_refuses_sizes_that_are_not_positive_integers(
    sizes: tuple[Any, ...], name: str
) -> None:
    # A height of 0 or -3 gave a (0, 1) or (-3, 1) tile, 2.5 values per pixel passed, and a
    # NaN one raised "cannot convert float NaN to integer".
    height, width, depth, *values = sizes
    with pytest.raises(ConfigError, match=rf'{name} must be an integer >= 1; got'):
        tile_shape(height, width, depth, 1.0, *values)


def test_tile_shape_still_takes_numpy_integers() -> None:
    assert tile_shape(np.int64(5), np.int32(6), np.int64(14), 1e3, np.int64(448)) == (5, 6)

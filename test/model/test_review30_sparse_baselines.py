"""Review 30 of the sparse evaluation and the baseline networks: input checks that used to
crash with foreign errors or pass bad data on silently."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.model import SparseConfig, sparse_confidence
from cva_confidence_ros.model.baselines import CCNN, network_inputs, predict_disparity_confidence
from cva_confidence_ros.model.sparse import joint_bilateral_fill

DEPTH, HEIGHT, WIDTH = 4, 9, 11


def _lookup(values: np.ndarray):
    """A network stand-in: the precomputed map, whatever the mask."""
    return lambda _volume, _mask: values


def _frame(seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    volume = rng.random((DEPTH, HEIGHT, WIDTH), dtype=np.float32)
    image = rng.integers(0, 256, (HEIGHT, WIDTH), dtype=np.uint8)
    disparity = volume.argmin(axis=0).astype(np.float32)
    exact = rng.uniform(0.05, 0.95, (HEIGHT, WIDTH)).astype(np.float32)
    return volume, image, disparity, exact


# -- sparse.py --------------------------------------------------------------------------------


@pytest.mark.parametrize('volume', [np.zeros((HEIGHT, WIDTH), np.float32), [[0.0]]])
def test_sparse_confidence_names_a_volume_that_is_not_a_3d_array(volume):
    # Was a bare ValueError (unpacking a 2-D shape) or AttributeError (a list has no shape).
    _, image, disparity, exact = _frame()
    with pytest.raises(InputError, match=r'cost_volume must be a \(D, H, W\) numpy array'):
        sparse_confidence(_lookup(exact), volume, image, disparity, SparseConfig(stride=2))


@pytest.mark.parametrize(
    ('image', 'message'),
    [
        # Was accepted: the colour weight (σ in 8-bit grey levels) saw every neighbour alike.
        (np.full((HEIGHT, WIDTH), 0.5), 'image must be uint8.*float64'),
        # Was accepted, the fourth channel taken as colour.
        (np.zeros((HEIGHT, WIDTH, 4), np.uint8), r'image must be .*got \(9, 11, 4\)'),
        # Was a numba TypingError from the fill kernel.
        (np.zeros((HEIGHT, WIDTH, 1, 1), np.uint8), r'image must be .*got \(9, 11, 1, 1\)'),
    ],
)
def test_sparse_confidence_refuses_guide_images_it_cannot_read(image, message):
    volume, _, disparity, exact = _frame()
    with pytest.raises(InputError, match=message):
        sparse_confidence(_lookup(exact), volume, image, disparity, SparseConfig(stride=2))


def test_sparse_confidence_takes_a_cheap_map_of_any_array_like():
    volume, image, disparity, exact = _frame()
    cheap = np.random.default_rng(1).random((HEIGHT, WIDTH))
    config = SparseConfig(stride=2, cascade='pkrn', cascade_fraction=0.5)
    # A nested list was an AttributeError ('list' object has no attribute 'shape').
    from_list = sparse_confidence(_lookup(exact), volume, image, disparity, config, cheap.tolist())
    from_array = sparse_confidence(_lookup(exact), volume, image, disparity, config, cheap)
    np.testing.assert_array_equal(from_list.confidence, from_array.confidence)


def test_joint_bilateral_fill_refuses_an_integer_known_mask():
    # A 0/1 integer array indexed rows instead of masking: the grid samples were silently
    # overwritten (up to 2.5 off on this ramp) instead of kept exactly.
    image = np.zeros((8, 8), np.uint8)
    disparity = np.zeros((8, 8), np.float32)
    values = np.arange(16.0).reshape(4, 4)
    kept = joint_bilateral_fill(values, np.ones((4, 4), bool), 2, image, disparity)
    np.testing.assert_array_equal(kept[::2, ::2], values)
    with pytest.raises(InputError, match='known must be a bool array; got dtype int64'):
        joint_bilateral_fill(values, np.ones((4, 4), np.int64), 2, image, disparity)


@pytest.mark.parametrize('stride', [0, -2, 2.5])
def test_joint_bilateral_fill_refuses_a_stride_below_one_or_not_whole(stride):
    # 0 was a ZeroDivisionError; the others a grid-shape message about a nonsense grid.
    image = np.zeros((8, 8), np.uint8)
    with pytest.raises(InputError, match='stride must be an integer >= 1'):
        joint_bilateral_fill(
            np.zeros((2, 2)), np.ones((2, 2), bool), stride, image, np.zeros((8, 8), np.float32)
        )


# -- baselines.py -----------------------------------------------------------------------------


@pytest.mark.parametrize('channels', [1, 4])
def test_network_inputs_names_an_image_of_other_channel_counts(channels):
    # Was numpy's matmul ValueError about a 'core dimension'.
    with pytest.raises(InputError, match=rf'image must be .*got \(3, 5, {channels}\)'):
        network_inputs(np.zeros((3, 5)), np.zeros((3, 5, channels), np.uint8), 64)


@pytest.mark.parametrize(
    'image', [np.full((3, 5), 0.5, np.float32), np.full((3, 5), 4000, np.uint16)]
)
def test_network_inputs_refuses_images_that_are_not_uint8(image):
    # Was divided by 255 all the same: grey 0.002 for a [0, 1] image, 15.7 for a 16-bit one.
    with pytest.raises(InputError, match=f'image must be uint8.*{image.dtype}'):
        network_inputs(np.zeros((3, 5)), image, 64)


@pytest.mark.parametrize('max_disparity', [float('nan'), float('inf'), None])
def test_network_inputs_refuses_a_depth_that_is_not_a_finite_number(max_disparity):
    # NaN passed the `< 1` test and made every input NaN; None was a bare TypeError.
    with pytest.raises(InputError, match='max_disparity must be a finite number >= 1'):
        network_inputs(np.ones((3, 5)), np.zeros((3, 5), np.uint8), max_disparity)


def test_predict_names_a_network_on_another_device():
    # Was a raw torch error from the first convolution.
    net = CCNN(16).to('meta')
    with pytest.raises(ConfigError, match='CCNN lies on meta; got device cpu'):
        predict_disparity_confidence(net, np.ones((6, 7)), np.zeros((6, 7), np.uint8))


def test_predict_takes_auto_and_a_network_of_another_dtype():
    torch.manual_seed(0)
    net = CCNN(16)
    disparity = np.random.default_rng(0).uniform(0, 16, (6, 7))
    image = np.random.default_rng(1).integers(0, 256, (6, 7), dtype=np.uint8)
    reference = predict_disparity_confidence(net, disparity, image)
    # 'auto' was a RuntimeError from torch.device; a float64 network a dtype mismatch.
    if not torch.cuda.is_available():  # 'auto' is the CPU here, where the network lies
        np.testing.assert_array_equal(
            predict_disparity_confidence(net, disparity, image, device='auto'), reference
        )
    doubled = predict_disparity_confidence(net.double(), disparity, image)
    assert doubled.dtype == np.float32
    np.testing.assert_allclose(doubled, reference, atol=1e-6)

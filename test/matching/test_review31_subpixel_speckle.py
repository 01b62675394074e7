"""Review 31: LRD at the left edge, sub-pixel refusals, speckle sizes, MC-CNN input checks."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cva_confidence_ros.confidence import ConfidenceInputs, compute_confidence
from cva_confidence_ros.confidence.handcrafted import left_right_difference_map
from cva_confidence_ros.errors import InputError, ModelError
from cva_confidence_ros.matching import mccnn_net, refine_subpixel, remove_speckles


def _row_volume(curves: list[list[float]]) -> np.ndarray:
    """Cost curves per column → a (D, 1, W) volume."""
    return np.asarray(curves, np.float32).T[:, None, :].copy()


def test_lrd_is_lowest_where_the_right_partner_is_outside_the_image() -> None:
    # Pixel x = 1 has its minimum at d1 = 2: its partner x − 2 lies left of the right image.
    # The old code looked up right column 0 instead, whose minimum happened to equal c1, and
    # gave (0.6 − 0.1) / eps ≈ 500, the most confident pixel of the image (LRC gives it -D).
    left = _row_volume([[0.9, 0.8, 1.0], [0.9, 0.6, 0.1], [0.9, 0.7, 0.2]])
    right = _row_volume([[0.1, 0.5, 0.5], [0.9, 0.9, 0.9], [0.9, 0.9, 0.9]])
    result = left_right_difference_map(left, right, 1e-3)
    # x = 0: d1 = 1, outside too; x = 2: d1 = 2 → right column 0, min 0.1.
    np.testing.assert_allclose(result, [[0.0, 0.0, (0.7 - 0.2) / (0.1 + 1e-3)]], rtol=1e-5)
    inputs = ConfidenceInputs(
        cost_volume=left,
        disparity=np.argmin(left, axis=0).astype(np.float32),
        image=np.zeros((1, 3), np.uint8),
        cost_volume_right=right,
    )
    lrd = compute_confidence('lrd', inputs)
    assert lrd[0, 1] == 0.0 and lrd[0, 1] < lrd[0, 2]


def test_subpixel_refusal_names_the_range_of_the_offending_values_alone() -> None:
    # 2.5 among the good integers 0, 1, 3: the message read 'finite ones in [0, 3]'.
    volume = np.zeros((4, 1, 4), np.float32)
    disparity = np.array([[0.0, 1.0, 2.5, 3.0]], np.float32)
    with pytest.raises(InputError, match=r'got 1 other values \(finite ones in \[2\.5, 2\.5\]\)'):
        refine_subpixel(volume, disparity, 'parabola')


def test_speckle_max_size_beyond_64_bits_is_no_limit() -> None:
    # A Python int beyond (u)int64 stopped numba's typing (TypingError) instead of meaning
    # that every region is a speckle.
    disparity = np.ones((3, 4), np.float32)
    disparity[0, 0] = 9.0
    kept = remove_speckles(disparity, max_size=10**20)
    assert kept.dtype == np.bool_ and not kept.any()
    np.testing.assert_array_equal(kept, remove_speckles(disparity, max_size=11))


@pytest.mark.parametrize('shape', [(7, 9, 4), (7, 9, 1), (7, 9, 2), (0, 5), (7,)])
def test_mccnn_normalise_image_refuses_other_shapes(shape: tuple[int, ...]) -> None:
    # RGBA and one-channel images failed in the product with the 3 luma weights (a bare
    # ValueError about gufunc signatures); an empty one gave NaN statistics.
    image = np.zeros(shape, np.uint8)
    with pytest.raises(InputError, match=r'H×W or H×W×3 numpy array; got \(' + str(shape[0])):
        mccnn_net.normalise_image(image)


@pytest.mark.parametrize(
    'images',
    [[], [np.zeros((5, 5), np.uint8), np.zeros((5, 6), np.uint8)]],
    ids=['none', 'mixed-shapes'],
)
def test_mccnn_extract_features_refuses_no_or_mixed_images(images: list[np.ndarray]) -> None:
    # np.stack's 'need at least one array' / 'same shape' ValueErrors came through bare.
    network = mccnn_net.McCnnFastFeatures()
    with pytest.raises(InputError, match='at least one image, all of one shape'):
        mccnn_net.extract_features(network, images, torch.device('cpu'))


def test_mccnn_network_refuses_input_smaller_than_its_receptive_field() -> None:
    # A 10×10 input (the padding of a 0×0 image) stopped inside torch with a RuntimeError
    # about kernel sizes; 11×11 is the smallest input, one output pixel.
    network = mccnn_net.McCnnFastFeatures()
    with torch.inference_mode():
        with pytest.raises(ModelError, match=r'padded images with H, W ≥ 1; got \(1, 1, 11, 10\)'):
            network(torch.zeros(1, 1, 11, 10))
        assert tuple(network(torch.zeros(1, 1, 11, 11)).shape) == (1, 64, 1, 1)

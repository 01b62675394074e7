"""Review 32 of the sparse evaluation and of the learned baselines' confidence methods: empty
frames, masks and fit values that passed silently or crashed with foreign errors, and options
or inputs of the wrong kind that the baselines took without a word."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from cva_confidence_ros.confidence import ConfidenceInputs
from cva_confidence_ros.confidence.baselines import CCNNConfidence, LFNConfidence
from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.model import SparseConfig, save_weights, sparse_confidence
from cva_confidence_ros.model.baselines import CCNN, LFN
from cva_confidence_ros.model.sparse import cascade_selection, joint_bilateral_fill, monotone_map

DEPTH, HEIGHT, WIDTH = 8, 20, 30


def _half(_volume: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """A network stand-in: 0.5 at every pixel."""
    return np.full(mask.shape, 0.5, np.float32)


def _inputs(matcher: str = 'census_bm') -> ConfidenceInputs:
    rng = np.random.default_rng(0)
    volume = rng.random((DEPTH, HEIGHT, WIDTH), dtype=np.float32)
    return ConfidenceInputs(
        cost_volume=volume,
        disparity=volume.argmin(axis=0).astype(np.float32),
        image=rng.integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8),
        matcher=matcher,
    )


@pytest.fixture(scope='module')
def weights(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp('w')
    torch.manual_seed(0)
    return {
        'ccnn': save_weights(CCNN(DEPTH), folder / 'ccnn.pt', {'matcher': 'census_bm'}),
        'lfn': save_weights(LFN(DEPTH), folder / 'lfn.pt', {'matcher': 'census_bm'}),
    }


# -- sparse.py --------------------------------------------------------------------------------


@pytest.mark.parametrize('shape', [(DEPTH, 0, WIDTH), (DEPTH, HEIGHT, 0)])
@pytest.mark.parametrize('config', [SparseConfig(stride=2), SparseConfig(cascade='pkrn')])
def test_sparse_confidence_names_an_empty_volume(shape, config):
    # Was an IndexError ('index -1 is out of bounds for axis 0 with size 0') from the grid.
    _, height, width = shape
    with pytest.raises(InputError, match=r'no axis empty; got \(8, (0, 30|20, 0)\)'):
        sparse_confidence(
            _half,
            np.zeros(shape, np.float32),
            np.zeros((height, width), np.uint8),
            np.zeros((height, width), np.float32),
            config,
            np.zeros((height, width)),
        )


@pytest.mark.parametrize('dtype', [np.complex128, np.bool_, np.str_])
def test_sparse_confidence_refuses_a_disparity_or_cheap_map_that_is_not_real_numbers(dtype):
    volume = np.zeros((DEPTH, HEIGHT, WIDTH), np.float32)
    image = np.zeros((HEIGHT, WIDTH), np.uint8)
    odd = np.ones((HEIGHT, WIDTH)).astype(dtype)
    real = np.ones((HEIGHT, WIDTH), np.float32)
    # The guide disparity was cast to float32: '1' parsed, True taken as 1 px, imaginary parts
    # dropped (a ComplexWarning at most).
    with pytest.raises(InputError, match=f'disparity must hold real numbers.*{odd.dtype}'):
        sparse_confidence(_half, volume, image, odd, SparseConfig(stride=2))
    # The cheap map likewise (a string map of words was a bare ValueError).
    with pytest.raises(InputError, match=f'cheap must hold real numbers.*{odd.dtype}'):
        sparse_confidence(_half, volume, image, real, SparseConfig(cascade='pkrn'), odd)


def test_sparse_confidence_names_a_network_result_of_another_shape():
    volume = np.zeros((DEPTH, HEIGHT, WIDTH), np.float32)
    image = np.zeros((HEIGHT, WIDTH), np.uint8)
    disparity = np.zeros((HEIGHT, WIDTH), np.float32)

    def other_frame(_volume: np.ndarray, _mask: np.ndarray) -> np.ndarray:
        return np.full((HEIGHT - 1, WIDTH), 0.5, np.float32)  # a lookup of another frame

    # Was an IndexError ('boolean index did not match indexed array along axis 0').
    with pytest.raises(InputError, match=r'network must give \(20, 30\) .* got \(19, 30\)'):
        sparse_confidence(other_frame, volume, image, disparity, SparseConfig(stride=2))


def test_cascade_selection_refuses_an_integer_candidate_mask():
    rank = np.random.default_rng(0).random((HEIGHT, WIDTH))
    grid = np.zeros((HEIGHT, WIDTH), bool)
    grid[::2, ::2] = True
    _, calibration = cascade_selection(rank, grid, 0.25)
    assert calibration.sum() == 16 and not (calibration & ~grid).any()
    # A 0/1 integer mask indexed the order instead of masking it: 2 calibration pixels
    # instead of 16, both off the grid, and the network ran where it was not meant to.
    with pytest.raises(InputError, match=r'candidates must be a bool array .* int64'):
        cascade_selection(rank, grid.astype(np.int64), 0.25)


def test_cascade_selection_names_a_mask_of_another_shape_and_a_fraction_of_another_type():
    rank = np.random.default_rng(0).random((4, 5))
    # Was numpy's 'operands could not be broadcast together'.
    with pytest.raises(InputError, match=r'rank shape \(4, 5\); got \(5, 4\) bool'):
        cascade_selection(rank, np.ones((5, 4), bool), 0.5)
    # Was "'<' not supported between instances of 'float' and 'str'".
    with pytest.raises(ConfigError, match="real number in \\(0, 1\\]; got str '0.5'"):
        cascade_selection(rank, np.ones((4, 5), bool), '0.5')


def test_joint_bilateral_fill_names_an_empty_image():
    # Was 'grid samples for a 0×5 image at stride 2 must be (1, 3)': a sample of no image.
    with pytest.raises(InputError, match=r'image must not be empty; got \(0, 5\)'):
        joint_bilateral_fill(
            np.zeros((1, 3)),
            np.ones((1, 3), bool),
            2,
            np.zeros((0, 5), np.uint8),
            np.zeros((0, 5), np.float32),
        )


@pytest.mark.parametrize(
    ('x_fit', 'y_fit'), [([0.1, 0.2, np.nan], [1.0, 2.0, 3.0]), ([0.1, 0.2], [1.0, np.inf])]
)
def test_monotone_map_refuses_fit_values_that_are_not_finite(x_fit, y_fit):
    # A NaN rank became a step centre: the map was NaN at x = 0.5 (and everywhere past 0.2).
    with pytest.raises(InputError, match='fit arrays must be finite; got 1 NaN or infinite'):
        monotone_map(x_fit, y_fit, np.array([0.1, 0.5]))


# -- confidence/baselines.py ------------------------------------------------------------------


def test_baseline_method_refuses_a_misspelt_option(weights):
    # 'weigths' was swallowed with the generic options: the shipped weights were loaded (at
    # D = 64) or a missing-weights error named a file that was never asked for.
    with pytest.raises(ConfigError, match=r"unknown options \['weigths'\] for CCNNConfidence"):
        CCNNConfidence(matcher='census_bm', max_disparity=DEPTH, weigths=str(weights['ccnn']))
    # The pipeline's generic options are still taken and ignored.
    built = CCNNConfidence(
        matcher='census_bm', max_disparity=DEPTH, weights=str(weights['ccnn']),
        tile_budget_mb=8.0, cva_stride=2,
    )
    assert built(_inputs()).shape == (HEIGHT, WIDTH)


@pytest.mark.parametrize('matcher', [None, 5, ''])
def test_baseline_method_refuses_a_matcher_that_is_no_name(weights, matcher):
    # None skipped the weights' matcher check and then refused every named input ("weights
    # are for matcher None"); 5 asked to train weights for matcher 5; '' did the same check
    # against the file's 'census_bm' and named no matcher.
    with pytest.raises(ConfigError, match=f'matcher must be a non-empty str.*{matcher!r}'):
        CCNNConfidence(matcher=matcher, max_disparity=DEPTH, weights=str(weights['ccnn']))


def test_baseline_method_refuses_weights_that_are_no_path():
    # Was a bare TypeError from Path(5).
    with pytest.raises(ConfigError, match='weights must be a path .* got int 5'):
        CCNNConfidence(matcher='census_bm', max_disparity=DEPTH, weights=5)


def test_baseline_method_names_inputs_that_are_no_confidence_inputs(weights):
    built = LFNConfidence(matcher='census_bm', max_disparity=DEPTH, weights=str(weights['lfn']))
    inputs = _inputs()
    assert built(inputs).shape == (HEIGHT, WIDTH)
    # Was "'numpy.ndarray' object has no attribute 'max_disparity'".
    with pytest.raises(InputError, match='LFNConfidence takes a ConfidenceInputs.*ndarray'):
        built(inputs.cost_volume)

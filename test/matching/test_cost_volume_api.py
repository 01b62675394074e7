"""The public entry compute_cost_volume: registry, contract of the volume, every bad input."""

from __future__ import annotations

import os
from pathlib import Path

from matching_test_utils import shifted_pair
import numpy as np
import pytest

from cva_confidence_ros.errors import ConfigError, CVAError, InputError
from cva_confidence_ros.matching import (
    MATCHERS,
    CensusBMConfig,
    CensusSGMConfig,
    MCCNNFastConfig,
    compute_cost_volume,
    left_right_check,
    wta_disparity,
)

ALL = ['census_bm', 'census_sgm', 'mccnn_fast']


def test_registry_names_and_configs() -> None:
    assert MATCHERS.names() == ALL
    assert MATCHERS.get('census_bm').Config is CensusBMConfig
    assert MATCHERS.get('census_sgm').Config is CensusSGMConfig
    assert MATCHERS.get('mccnn_fast').Config is MCCNNFastConfig
    with pytest.raises(AttributeError):
        CensusSGMConfig().p1 = 3  # type: ignore[misc]  # frozen


@pytest.mark.parametrize('matcher', ALL)
@pytest.mark.parametrize('view', ['left', 'right'])
def test_volume_contract(matcher: str, view: str) -> None:
    shift, depth = 3, 7
    left, right = shifted_pair(40, 60, shift, seed=21, colour=True)
    volume = compute_cost_volume(left, right, matcher, depth, view=view)
    assert volume.shape == (depth, 40, 60)
    assert volume.dtype == np.float32 and volume.flags['C_CONTIGUOUS']
    assert np.isfinite(volume).all() and volume.min() >= 0.0 and volume.max() <= 1.0
    columns = np.arange(60)
    for d in range(depth):
        outside = columns - d < 0 if view == 'left' else columns + d >= 60
        assert np.all(volume[d][:, outside] == 1.0)
        # inside the image 1.0 is possible (SGM can reach its bound) but rare
        assert np.mean(volume[d][:, ~outside] == 1.0) < 0.01
    disparity = wta_disparity(volume)
    interior = disparity[5:-5, shift + 5:-5] if view == 'left' else disparity[5:-5, 5:-shift - 5]
    assert np.all(interior == shift)


@pytest.mark.parametrize('matcher', ALL)
def test_left_right_check_passes_on_a_shifted_pair(matcher: str) -> None:
    left, right = shifted_pair(30, 50, 2, seed=22)
    disp_left = wta_disparity(compute_cost_volume(left, right, matcher, 6))
    disp_right = wta_disparity(compute_cost_volume(left, right, matcher, 6, view='right'))
    assert left_right_check(disp_left, disp_right)[5:-5, 7:-5].all()


@pytest.mark.parametrize('matcher', ['census_bm', 'census_sgm'])
def test_colour_is_matched_as_its_gray_conversion(matcher: str) -> None:
    cv2 = pytest.importorskip('cv2')
    left, right = shifted_pair(12, 20, 1, seed=23, colour=True)
    gray_left = cv2.cvtColor(left, cv2.COLOR_RGB2GRAY)
    gray_right = cv2.cvtColor(right, cv2.COLOR_RGB2GRAY)
    np.testing.assert_array_equal(
        compute_cost_volume(left, right, matcher, 4),
        compute_cost_volume(gray_left, gray_right, matcher, 4),
    )


def test_float_images_in_range_are_rounded_to_uint8() -> None:
    left, right = shifted_pair(10, 16, 1, seed=24)
    np.testing.assert_array_equal(
        compute_cost_volume(left.astype(np.float64), right.astype(np.float32), 'census_bm', 3),
        compute_cost_volume(left, right, 'census_bm', 3),
    )


def _pair() -> tuple[np.ndarray, np.ndarray]:
    return shifted_pair(8, 12, 1, seed=25)


def _with(image: np.ndarray, index: tuple[int, int], value: float) -> np.ndarray:
    out = image.astype(np.float32)
    out[index] = value
    return out


BAD_IMAGES = {
    'shape mismatch': (np.zeros((8, 12), np.uint8), np.zeros((8, 11), np.uint8), 'same shape'),
    'gray vs colour': (np.zeros((8, 12), np.uint8), np.zeros((8, 12, 3), np.uint8),
                       'both be grey or both colour'),
    'empty': (np.zeros((0, 12), np.uint8), np.zeros((0, 12), np.uint8), 'empty'),
    'empty width': (np.zeros((8, 0), np.uint8), np.zeros((8, 0), np.uint8), 'empty'),
    '4 channels': (np.zeros((8, 12, 4), np.uint8),) * 2 + ('H×W or H×W×3',),
    '1-D': (np.zeros(12, np.uint8),) * 2 + ('H×W or H×W×3',),
    'uint16': (np.zeros((8, 12), np.uint16),) * 2 + ('dtype uint16',),
    'int64': (np.zeros((8, 12), np.int64),) * 2 + ('dtype int64',),
    'bool': (np.zeros((8, 12), bool),) * 2 + ('dtype bool',),
    'nan': (_with(_pair()[0], (2, 3), np.nan), _pair()[1].astype(np.float32), 'NaN/inf'),
    'inf': (_pair()[0].astype(np.float32), _with(_pair()[1], (0, 0), np.inf), 'NaN/inf'),
    'float above 255': (_with(_pair()[0], (1, 1), 256.0), _pair()[1], r'\[0, 255\]'),
    'negative float': (_with(_pair()[0], (1, 1), -1.0), _pair()[1], r'\[0, 255\]'),
    'float in [0, 1]': (_pair()[0] / 255.0, _pair()[1] / 255.0, 'looks normalised'),
    'list': ([[0, 1], [2, 3]], np.zeros((2, 2), np.uint8), 'numpy array'),
}


@pytest.mark.parametrize('matcher', ALL)
@pytest.mark.parametrize('case', list(BAD_IMAGES))
def test_bad_images_raise_input_error(matcher: str, case: str) -> None:
    left, right, message = BAD_IMAGES[case]
    with pytest.raises(InputError, match=message):
        compute_cost_volume(left, right, matcher, 2)


@pytest.mark.parametrize('matcher', ALL)
@pytest.mark.parametrize(
    ('max_disparity', 'message'),
    [(0, '≥ 1'), (-3, '≥ 1'), (12, 'smaller than the image width 12'), (40, 'width'),
     (2.0, 'integer'), (True, 'integer'), ('8', 'integer')],
)
def test_bad_max_disparity_raises_config_error(
    matcher: str, max_disparity: object, message: str
) -> None:
    left, right = _pair()
    with pytest.raises(ConfigError, match=message):
        compute_cost_volume(left, right, matcher, max_disparity)  # type: ignore[arg-type]


def test_largest_max_disparity_is_width_minus_one() -> None:
    left, right = _pair()
    volume = compute_cost_volume(left, right, 'census_sgm', 11)
    assert volume.shape == (11, 8, 12)
    assert np.all(volume[10, :, :10] == 1.0) and np.all(volume[10, :, 10:] < 1.0)
    assert compute_cost_volume(left, right, 'census_bm', np.int64(3)).shape == (3, 8, 12)


def test_unknown_matcher_view_and_parameters() -> None:
    left, right = _pair()
    with pytest.raises(ConfigError, match="unknown matcher 'sad'.*census_bm"):
        compute_cost_volume(left, right, 'sad', 4)
    with pytest.raises(ConfigError, match="view must be one of .*'center'"):
        compute_cost_volume(left, right, 'census_bm', 4, view='center')
    with pytest.raises(ConfigError, match=r"unknown parameters \['p3'\].*\['p1', 'p2'\]"):
        compute_cost_volume(left, right, 'census_sgm', 4, p3=1)
    with pytest.raises(ConfigError, match=r"unknown parameters \['p1'\]"):
        compute_cost_volume(left, right, 'census_bm', 4, p1=1)
    with pytest.raises(ConfigError, match='unknown parameters'):
        compute_cost_volume(left, right, 'mccnn_fast', 4, window=5)


def test_errors_belong_to_the_package_tree() -> None:
    assert issubclass(InputError, CVAError) and issubclass(ConfigError, CVAError)


def _data_root() -> Path:
    env = os.environ.get('CVA_DATA_ROOT')
    return Path(env) if env else Path(__file__).resolve().parents[2] / '..' / 'shared' / 'data'


@pytest.mark.parametrize(('matcher', 'limit'), [('census_bm', 0.30), ('census_sgm', 0.25)])
def test_real_pair_error_rate(matcher: str, limit: float) -> None:
    cv2 = pytest.importorskip('cv2')
    scene = _data_root() / 'middlebury2003' / 'cones'
    if not scene.is_dir():
        pytest.skip(f'no Middlebury 2003 data at {scene}')
    left = cv2.imread(str(scene / 'cones_image_02.png'), cv2.IMREAD_GRAYSCALE)
    right = cv2.imread(str(scene / 'cones_image_06.png'), cv2.IMREAD_GRAYSCALE)
    truth = cv2.imread(str(scene / 'cones_disp_02.png'), cv2.IMREAD_UNCHANGED) / 4.0
    # 120 rows keep the test fast; scored on 200 columns away from the left border, where
    # the 64 disparities fit; ground truth 0 = unknown
    rows, cols = slice(120, 240), slice(150, 350)
    volume = compute_cost_volume(left[rows], right[rows], matcher, 64)
    disparity = wta_disparity(volume)
    known = truth[rows, cols] > 0
    errors = np.abs(disparity[:, cols] - truth[rows, cols])[known] > 1.0
    assert errors.mean() < limit

"""Review 30 of the confidence methods: hand-crafted measures at their limits, public helpers'
input checks and the option types of ``cva_net``."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from cva_confidence_ros.confidence import CONFIDENCE_METHODS, ConfidenceInputs
from cva_confidence_ros.confidence.handcrafted import left_right_difference_map, two_smallest
from cva_confidence_ros.errors import ConfigError, InputError

# D = 2, H = 1, W = 3: column 0 as a matcher leaves it (one candidate, then the filler), pixel
# 1 a clear perfect match, pixel 2 an ambiguous one.
VOLUME = np.array([[[0.3, 0.0, 0.5]], [[1.0, 1.0, 0.6]]], np.float32)


def _inputs(**kwargs: np.ndarray) -> ConfidenceInputs:
    return ConfidenceInputs(
        cost_volume=VOLUME,
        disparity=VOLUME.argmin(axis=0).astype(np.float32),
        image=np.zeros(VOLUME.shape[1:], np.uint8),
        **kwargs,
    )


def test_lrd_unit_interval_keeps_an_infinite_lrd_on_top() -> None:
    # An eps of 1e-40 is accepted (it is > 0 in float32) and makes LRD +inf where the left
    # and right minima agree; LRD / (1 + LRD) was then inf / inf = NaN and published as 0,
    # the least confident value, for the most confident pixels.
    lrd = CONFIDENCE_METHODS.get('lrd')(eps=1e-40)
    np.testing.assert_allclose(lrd.to_unit_interval(np.array([np.inf, 1.0, 0.0])), [1, 0.5, 0])
    with warnings.catch_warnings():
        warnings.simplefilter('error')  # the overflow to +inf is meant, not warned about
        raw = lrd(_inputs(cost_volume_right=VOLUME))
        unit = lrd.to_unit_interval(raw)
    assert raw[0, 0] == 0 and np.isposinf(raw[0, 1:]).all()
    np.testing.assert_array_equal(unit, [[0.0, 1.0, 1.0]])


def test_pkrn_tiny_eps_overflows_to_inf_without_a_warning() -> None:
    pkrn = CONFIDENCE_METHODS.get('pkrn')(eps=1e-40)
    with warnings.catch_warnings():
        warnings.simplefilter('error')  # was RuntimeWarning: overflow encountered in divide
        raw = pkrn(_inputs())
    assert raw[0, 0] == 1 and np.isposinf(raw[0, 1]) and raw[0, 2] == pytest.approx(1.2)
    np.testing.assert_allclose(pkrn.to_unit_interval(raw), [[0.0, 1.0, 1 - 1 / 1.2]],
                               rtol=1e-6)


@pytest.mark.parametrize('where', [(0, 0, 0), (1, 0, 1)], ids=['d0', 'd1'])
def test_two_smallest_refuses_nan(where: tuple[int, int, int]) -> None:
    # NaN fails every '<': at d = 0 it stayed c1 (NaN), elsewhere it was skipped, silently.
    volume = VOLUME.copy()
    volume[where] = np.nan
    with pytest.raises(InputError, match='volume must not contain NaN costs; got 1 NaN'):
        two_smallest(volume)
    # Without NaN the kernel is unchanged: ties keep the first d1 and give c2 == c1.
    c1, d1, c2 = two_smallest(np.array([[[0.3]], [[0.1]], [[0.1]], [[0.2]]], np.float32))
    assert (c1[0, 0], d1[0, 0], c2[0, 0]) == (np.float32(0.1), 1, np.float32(0.1))


@pytest.mark.parametrize(
    ('volume', 'message'),
    [
        (VOLUME.tolist(), 'volume must be a numpy array; got list'),
        (VOLUME.astype(np.complex64), 'volume must hold real numbers.*complex64'),
    ],
    ids=['list', 'complex'],
)
def test_two_smallest_refuses_what_is_no_real_array(volume: object, message: str) -> None:
    # A list raised a bare AttributeError; complex lost its imaginary part with a warning.
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        with pytest.raises(InputError, match=message):
            two_smallest(volume)  # type: ignore[arg-type]


@pytest.mark.parametrize('eps', [0.0, -1.0, 1e-300])
def test_left_right_difference_map_checks_eps(eps: float) -> None:
    # The public helper took any eps: 0 gave 0 / 0 = NaN where both minima are equal.
    flat = np.full((2, 1, 2), 0.5, np.float32)
    with pytest.raises(ConfigError, match='eps must'):
        left_right_difference_map(flat, flat, eps)


def test_left_right_difference_map_refuses_nan() -> None:
    right = VOLUME.copy()
    right[1, 0, 0] = np.nan  # made both pixels' LRD NaN
    with pytest.raises(InputError, match='volume_right must not contain NaN costs; got 1 NaN'):
        left_right_difference_map(VOLUME, right, 1e-3)
    with pytest.raises(InputError, match='volume must not contain NaN costs'):
        left_right_difference_map(right, VOLUME, 1e-3)
    with pytest.raises(InputError, match='volume_right must be a numpy array; got list'):
        left_right_difference_map(VOLUME, VOLUME.tolist(), 1e-3)  # type: ignore[arg-type]


@pytest.mark.parametrize('value', [1e20, -1e20, 3e38, -3e38])
def test_lrc_disparities_beyond_int64_are_outside_without_a_warning(value: float) -> None:
    # x - round(d) was cast to int64 first: "invalid value encountered in cast", and only the
    # wraparound of the undefined integer kept the pixel outside the image.
    volume = np.zeros((3, 1, 4), np.float32)
    disparity = np.array([[value, 0.0, 1.0, 1.0]], np.float32)
    inputs = ConfidenceInputs(
        cost_volume=volume,
        disparity=disparity,
        image=np.zeros((1, 4), np.uint8),
        disparity_right=np.array([[0.0, 0.0, 1.0, 0.0]], np.float32),
    )
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        result = CONFIDENCE_METHODS.get('lrc')()(inputs)
    np.testing.assert_array_equal(result, [[-3.0, 0.0, -1.0, 0.0]])


@pytest.mark.parametrize('matcher', [None, 5, ''])
def test_cva_net_refuses_a_matcher_that_is_no_name(matcher: object) -> None:
    # None skipped the weights' matcher check and then refused every named cost volume
    # ("weights are for matcher None"); 5 asked to train weights for matcher 5.
    with pytest.raises(ConfigError, match='matcher must be a non-empty str'):
        CONFIDENCE_METHODS.get('cva_net')(matcher=matcher, max_disparity=16, weights='w.pt')


@pytest.mark.parametrize('weights', [5, b'w.pt', ['w.pt']])
def test_cva_net_refuses_weights_that_are_no_path(weights: object) -> None:
    # Path(weights) raised a bare TypeError.
    with pytest.raises(ConfigError, match=r'weights must be a path \(str or os.PathLike\)'):
        CONFIDENCE_METHODS.get('cva_net')(max_disparity=16, weights=weights)

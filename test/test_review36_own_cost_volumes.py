"""Review 36: cost volumes of the user's own matchers and networks.

What a user with another matcher (OpenCV, an own SAD/NCC, a stereo network) runs into: NaN or
inf where a disparity is impossible, a similarity instead of a cost, integer costs, the
(H, W, D) layout.
"""

from __future__ import annotations

import numpy as np
import pytest

from cva_confidence_ros.confidence import ConfidenceInputs, compute_confidence
from cva_confidence_ros.errors import InputError

D, H, W = 6, 5, 9


def _volume() -> np.ndarray:
    return np.random.default_rng(36).random((D, H, W)).astype(np.float32)


def _inputs(volume: np.ndarray) -> ConfidenceInputs:
    disparity, image = np.zeros((H, W), np.float32), np.zeros((H, W), np.uint8)
    return ConfidenceInputs(cost_volume=volume, disparity=disparity, image=image)


def _border_marked(value: float) -> np.ndarray:
    # The way many matchers mark x < d, where the right pixel lies outside the image.
    volume = _volume()
    for d in range(D):
        volume[d, :, :d] = value
    return volume


def test_nan_marked_volume_error_counts_the_nans_and_says_how_to_mark() -> None:
    # Was "got values in [nan, nan]": as if the whole volume were NaN, and no way out.
    volume = _border_marked(np.nan)
    nans = int(np.isnan(volume).sum())
    expected = rf'finite costs in \[0, 1\]; got {nans} NaN entries'
    with pytest.raises(InputError, match=expected) as info:
        _inputs(volume)
    assert 'worst cost 1.0' in str(info.value)
    # Done as the message says, the volume is accepted.
    fixed = np.where(np.isnan(volume), np.float32(1.0), volume)
    assert compute_confidence('pkrn', _inputs(fixed)).shape == (H, W)


def test_inf_marked_volume_error_says_how_to_mark() -> None:
    with pytest.raises(InputError, match=r'got values in \[.*, inf\].*worst cost 1\.0'):
        _inputs(_border_marked(np.inf))


def test_similarity_volume_error_names_the_conversion() -> None:
    # NCC / a cosine in [-1, 1], higher = better: refused as a cost, with how it goes in.
    similarity = 2.0 * _volume() - 1.0
    with pytest.raises(InputError, match=r'similarity .* \(1 - s\) / 2'):
        _inputs(similarity)
    assert _inputs((1.0 - similarity) / 2.0).cost_volume.shape == (D, H, W)


def test_integer_costs_error_says_to_normalise() -> None:
    volume = (_volume() * 200).astype(np.uint8)
    volume[0, 0, 0], volume[1, 0, 0] = 0, 250  # e.g. a Census Hamming count or a clipped SAD
    with pytest.raises(InputError, match=r'\[0, 250\].*divide the costs by the largest'):
        _inputs(volume)


@pytest.mark.parametrize('field', ['disparity', 'image'])
def test_hwd_volume_is_refused_with_the_transpose(field: str) -> None:
    # (H, W, D) read as (D, H, W): the message was about the disparity's (or image's) shape.
    volume = np.ascontiguousarray(_volume().transpose(1, 2, 0))
    fields = {
        'cost_volume': volume,
        'disparity': np.zeros((H, W), np.float32),
        'image': np.zeros((H, W), np.uint8),
    }
    if field == 'image':
        # A disparity taken from the misread volume passes; the image gives it away.
        fields['disparity'] = np.zeros((W, D), np.float32)
    with pytest.raises(InputError, match=r'\(H, W, D\).*transpose\(2, 0, 1\)'):
        ConfidenceInputs(**fields)
    fields['cost_volume'] = volume.transpose(2, 0, 1)
    fields['disparity'] = np.zeros((H, W), np.float32)
    assert ConfidenceInputs(**fields).shape == (H, W)

"""Review 36: the speed/accuracy knobs of the learned confidence (cva_stride, cva_cascade,
cva_cascade_fraction) seen from the Python API of CVA-Net-Fast."""

from __future__ import annotations

import numpy as np
import pytest

from cva_confidence_ros.confidence import CONFIDENCE_METHODS, ConfidenceInputs
from cva_confidence_ros.errors import InputError
from cva_confidence_ros.matching import wta_disparity


def _inputs(with_right: bool) -> ConfidenceInputs:
    rng = np.random.default_rng(36)
    volume = rng.random((64, 8, 16), dtype=np.float32)
    image = rng.integers(0, 256, (8, 16), dtype=np.uint8)
    right = rng.random((64, 8, 16), dtype=np.float32) if with_right else None
    return ConfidenceInputs(
        volume, wta_disparity(volume), image, cost_volume_right=right, matcher='census_bm'
    )


@pytest.mark.parametrize('stride', [1, 4])
def test_lrd_cascade_without_the_right_volume_names_the_cascade(stride):
    # Was LeftRightDifference's refusal, a method the caller never chose by that name.
    method = CONFIDENCE_METHODS.get('cva_net_fast')(
        matcher='census_bm', max_disparity=64, cva_cascade='lrd', cva_stride=stride
    )
    with pytest.raises(InputError, match=r"cva_cascade 'lrd'.*cost_volume_right"):
        method(_inputs(with_right=False))
    with pytest.raises(InputError, match=r"cva_cascade 'lrd'"):
        method.confidence_at(_inputs(with_right=False), np.array([0]), np.array([0]))
    confidence = method(_inputs(with_right=True))
    assert confidence.shape == (8, 16) and np.isfinite(confidence).all()

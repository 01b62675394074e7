"""Review 31: missing shipped weights for a D the architecture cannot take name the reason,
not a cva-train command that would fail on it."""

from __future__ import annotations

import pytest

from cva_confidence_ros.errors import ModelError
from cva_confidence_ros.model import default_weights_path


@pytest.mark.parametrize(('arch', 'depth', 'why'), [
    ('cvanet', 12, r'>= 13 \(the fusion removes 12 disparities\); got 12'),
    ('cvanet_fast', 4, r'>= 9 .*; got 4'),
])
def test_a_depth_the_architecture_cannot_take_is_named(arch: str, depth: int, why: str) -> None:
    # Before: "Train them with: cva-train --arch cvanet --max-disparity 12 …", which fails.
    with pytest.raises(ModelError, match=f'^no {arch} network for D = {depth}: max_disparity '
                                         f'must be an integer {why}$'):
        default_weights_path('census_bm', depth, arch)


def test_a_depth_it_can_take_still_names_the_training_command() -> None:
    with pytest.raises(ModelError, match='Train them with: cva-train --arch cvanet --matcher '
                                         'census_bm --max-disparity 13 '):
        default_weights_path('census_bm', 13, 'cvanet')

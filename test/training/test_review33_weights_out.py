"""Review 33 of cva-train's outputs: existing weights are not replaced without --overwrite."""

from __future__ import annotations

from pathlib import Path

import pytest

from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.training.config import TrainConfig
from cva_confidence_ros.training.trainer import check_run_setup


@pytest.mark.parametrize('existing', ['w.pt', 'w.md', 'w.json'])
def test_existing_weights_or_card_are_refused_without_overwrite(tmp_path: Path,
                                                                existing: str) -> None:
    # `cva-train ... --weights-out models/cvanet_census_sgm_d64.pt` (the README's first command,
    # run from the clone) replaced the shipped weights and card without a word.
    (tmp_path / existing).write_text('earlier')
    weights = tmp_path / 'w.pt'
    run = str(tmp_path / 'run')
    config = TrainConfig(matcher='census_bm', max_disparity=16, synthetic=1, out=run,
                         weights_out=str(weights))
    with pytest.raises(ConfigError, match=rf'--weights-out .*{existing} exists .*--overwrite'):
        check_run_setup(config)
    assert (tmp_path / existing).read_text() == 'earlier'
    check_run_setup(TrainConfig(matcher='census_bm', max_disparity=16, synthetic=1, out=run,
                                weights_out=str(weights), overwrite=True))

"""Review 38, a second look at cva-train's stop on signals: regression tests of faults found."""

from __future__ import annotations

import os
from pathlib import Path
import signal

import pytest
from train_test_utils import TINY

from cva_confidence_ros.training import trainer
from cva_confidence_ros.training.cli import build_parser, config_from_args


def test_a_failed_train_leaves_no_deferred_signals(tmp_path: Path, monkeypatch) -> None:
    # train() called directly (a notebook, a test) failed in a step: the signals stayed
    # "deferred", and the next run of the process ignored a SIGTERM or Ctrl-C while it
    # prepared its scenes (minutes on real data sets) until its first step was done.
    config = config_from_args(build_parser().parse_args([*TINY, '--out', str(tmp_path)]))

    def fail(*_args, **_kwargs):
        raise RuntimeError('a bad batch')

    monkeypatch.setattr(trainer, 'distillation_loss', fail)
    with pytest.raises(RuntimeError, match='a bad batch'):
        trainer.train(config)
    with pytest.raises(trainer.Stopped) as stopped, trainer.stop_on_signals():
        os.kill(os.getpid(), signal.SIGTERM)  # at once, outside any training step
    assert stopped.value.signum == signal.SIGTERM and stopped.value.saved == ''

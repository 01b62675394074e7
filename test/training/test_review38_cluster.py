"""Review 38 of ``cva-train`` on clusters: a Slurm preemption (SIGTERM) ended the run at once,
without a word, and the epoch in progress was lost (hours, on the paper's data); there was no
checkpoint within an epoch; a full disk while writing a checkpoint said only torch's
'unexpected pos …'. Now SIGTERM / Ctrl-C checkpoint the step reached and say so (exit 143 /
130), ``--checkpoint-every N`` checkpoints within epochs, and a resume from either trains to
the bit as the run that did not stop.
"""

from __future__ import annotations

import os
from pathlib import Path
import resource
import signal

import pytest
import torch
from train_test_utils import TINY

from cva_confidence_ros.errors import DataError
from cva_confidence_ros.training import trainer
from cva_confidence_ros.training.cli import main

#: Two epochs of 4 steps each (64 samples in steps of 16), the second at the low rate.
RUN = [*TINY, '--samples-per-epoch', '64', '--epochs', '1', '--epochs-low-lr', '1']


def _weights(path: Path) -> dict[str, torch.Tensor]:
    return torch.load(path, map_location='cpu', weights_only=False)['state_dict']


def _same_weights(a: Path, b: Path) -> bool:
    first, second = _weights(a), _weights(b)
    return first.keys() == second.keys() and all(torch.equal(first[k], second[k]) for k in first)


def _losses(out: Path) -> list[float]:
    return [r['train_loss'] for r in trainer.json.loads((out / 'history.json').read_text())]


def _at_step(monkeypatch, number: int, action) -> None:
    """Run ``action()`` in the ``number``-th training step (1-based, over the whole run)."""
    calls = [0]
    loss = trainer.distillation_loss

    def counted(*args, **kwargs):
        calls[0] += 1
        if calls[0] == number:
            action()
        return loss(*args, **kwargs)

    monkeypatch.setattr(trainer, 'distillation_loss', counted)


class _Unhandled(Exception):
    """A SIGTERM that cva-train did not handle (it ended the process: here, the tests)."""


@pytest.fixture
def _sigterm_guard():
    """A SIGTERM outside cva-train's own handling fails the test, not the test session."""

    def unhandled(_signum, _frame):
        raise _Unhandled

    previous = signal.signal(signal.SIGTERM, unhandled)
    yield unhandled
    signal.signal(signal.SIGTERM, previous)


@pytest.fixture(scope='module')
def straight(tmp_path_factory) -> Path:
    """The run that did not stop: its weights file (its run folder beside it)."""
    folder = tmp_path_factory.mktemp('straight')
    assert main([*RUN, '--out', str(folder / 'run'), '--weights-out', str(folder / 'w.pt')]) == 0
    return folder


@pytest.mark.parametrize('signum', [signal.SIGTERM, signal.SIGINT], ids=['SIGTERM', 'SIGINT'])
def test_a_signal_within_an_epoch_checkpoints_the_step_and_resumes_to_the_bit(
    tmp_path: Path, monkeypatch, capsys, straight: Path, signum: int, _sigterm_guard
) -> None:
    out = tmp_path / 'run'
    # In step 6 (the second of epoch 2): the run ends that step, checkpoints it and stops.
    _at_step(monkeypatch, 6, lambda: os.kill(os.getpid(), signum))
    assert main([*RUN, '--out', str(out), '--weights-out', str(tmp_path / 'w.pt')]) == 128 + signum
    err = capsys.readouterr().err
    name = signal.Signals(signum).name
    assert f'stopped by {name}; the checkpoint in {out} holds step 2 of 4 of epoch 2/2' in err
    state = torch.load(out / 'checkpoint.pt', weights_only=True)
    assert state['epoch'] == 1 and state['partial']['step'] == 2
    assert signal.getsignal(signal.SIGTERM) is _sigterm_guard  # given back
    monkeypatch.undo()
    assert (
        main([*RUN, '--out', str(out), '--weights-out', str(tmp_path / 'w.pt'), '--resume']) == 0
    )
    assert 'within epoch 2 after its step 2' in (out / 'train.log').read_text()
    assert _same_weights(tmp_path / 'w.pt', straight / 'w.pt')
    assert _losses(out) == _losses(straight / 'run')


def test_a_signal_outside_the_steps_says_what_is_lost(
    tmp_path: Path, monkeypatch, capsys, _sigterm_guard
) -> None:
    def stop(*_args, **_kwargs):
        os.kill(os.getpid(), signal.SIGTERM)
        raise AssertionError('SIGTERM did not stop the run')

    monkeypatch.setattr(trainer, 'sample_index', stop)  # while the scenes are prepared
    assert main([*RUN, '--out', str(tmp_path / 'run')]) == 143
    err = capsys.readouterr().err
    # No checkpoint yet (stopped while the scenes were prepared): no --resume to advise.
    assert (
        f'stopped by SIGTERM; no checkpoint was written in {tmp_path / "run"} yet: run it '
        'again from the start' in err
    )


def test_checkpoint_every_resumes_a_killed_run_to_the_bit(
    tmp_path: Path, monkeypatch, straight: Path
) -> None:
    out = tmp_path / 'run'

    class Killed(Exception):
        """The process ends here (SIGKILL, a lost node): nothing after this step runs."""

    def kill() -> None:
        raise Killed

    _at_step(monkeypatch, 8, kill)  # the last step of epoch 2: steps 2 and 3 were not saved
    with pytest.raises(Killed):
        main([*RUN, '--out', str(out), '--weights-out', str(tmp_path / 'w.pt'),
              '--checkpoint-every', '2'])  # fmt: skip
    state = torch.load(out / 'checkpoint.pt', weights_only=True)
    assert (state['epoch'], state['partial']['step']) == (1, 2)
    monkeypatch.undo()
    assert main([*RUN, '--out', str(out), '--weights-out', str(tmp_path / 'w.pt'), '--resume',
                 '--checkpoint-every', '2']) == 0  # fmt: skip
    assert _same_weights(tmp_path / 'w.pt', straight / 'w.pt')
    assert _losses(out) == _losses(straight / 'run')
    history = trainer.json.loads((out / 'history.json').read_text())
    assert [r['samples'] for r in history] == [64, 64]


def test_a_full_disk_names_the_cause_and_keeps_the_checkpoint(tmp_path: Path) -> None:
    path = tmp_path / 'checkpoint.pt'
    trainer._save_checkpoint(path, {'epoch': 1})
    before = path.read_bytes()
    # A file size limit: the write fails as on a full disk (EFBIG instead of ENOSPC).
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (1 << 20, hard))
    try:
        with pytest.raises(DataError) as error:
            trainer._save_checkpoint(path, {'epoch': 2, 'model': torch.zeros(1 << 20)})
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
    message = str(error.value)
    assert f'cannot write checkpoint {path} (OSError: [Errno 27] File too large)' in message
    assert 'unexpected pos' not in message and 'left as it was' in message
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ['checkpoint.pt']

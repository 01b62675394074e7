"""Review 32 of ``cva-train`` (training/trainer.py, training/cli.py): --resume with
--overwrite, an overwritten run stopped before its first checkpoint, a checkpoint that cannot
be written, weights over the run's own files, and DistributedDataParallel when process 0 fails
alone."""

from __future__ import annotations

import multiprocessing
import os
from pathlib import Path
import socket
import time
from typing import Any

import pytest
from train_test_utils import TINY

from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.training import TrainConfig
from cva_confidence_ros.training.cli import main
from cva_confidence_ros.training.trainer import check_run_setup

ONE_EPOCH = [*TINY, '--epochs', '1', '--epochs-low-lr', '0']


def test_resume_and_overwrite_together_are_refused(tmp_path: Path, capsys) -> None:
    # Both were taken and the resume won: the earlier run went on instead of a fresh one.
    config = TrainConfig(synthetic=1, out=str(tmp_path), resume=True, overwrite=True)
    with pytest.raises(ConfigError, match='--resume .* --overwrite .*give one'):
        check_run_setup(config)
    with pytest.raises(SystemExit) as stop:
        main([*ONE_EPOCH, '--out', str(tmp_path), '--resume', '--overwrite'])
    assert stop.value.code == 2
    assert 'not allowed with argument' in capsys.readouterr().err
    assert not (tmp_path / 'checkpoint.pt').exists()


def test_an_overwrite_stopped_in_its_first_epoch_leaves_no_earlier_checkpoint(
    tmp_path: Path, monkeypatch
) -> None:
    from cva_confidence_ros.training import trainer

    # An earlier run's files; a --resume after the stop below continued (or, with other
    # settings, refused) that run instead of the one --overwrite started.
    (tmp_path / 'checkpoint.pt').write_bytes(b'the checkpoint of an earlier run')
    (tmp_path / 'history.json').write_text('[{"epoch": 1}]')

    def interrupted(*args: Any, **kwargs: Any) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(trainer, '_run_epoch', interrupted)
    assert main([*ONE_EPOCH, '--out', str(tmp_path), '--overwrite']) == 130
    assert not (tmp_path / 'checkpoint.pt').exists()
    assert not (tmp_path / 'history.json').exists()


def test_a_checkpoint_that_cannot_be_written_is_named(
    tmp_path: Path, capsys, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Was a raw RuntimeError '[enforce fail at inline_container.cc:747] . open file failed'.
    from cva_confidence_ros import outputs

    monkeypatch.setattr(outputs, 'temporary_sibling', lambda path: path.with_name('blocked.tmp'))
    (tmp_path / 'blocked.tmp').mkdir()
    assert main([*ONE_EPOCH, '--out', str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert f'cannot write checkpoint {tmp_path / "checkpoint.pt"}' in err
    assert 'Is a directory' in err
    assert not (tmp_path / 'checkpoint.pt').exists()


@pytest.mark.parametrize(
    ('weights', 'replaced'), [('checkpoint.pt', 'checkpoint.pt'), ('history.pt', 'history.json')]
)
def test_weights_over_the_checkpoint_or_history_are_refused(
    tmp_path: Path, capsys, weights: str, replaced: str
) -> None:
    # Were written there: a resume found a weights file, or history.json held the model card.
    args = [*ONE_EPOCH, '--out', str(tmp_path), '--weights-out', str(tmp_path / weights)]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert f'would replace the {replaced} of the run in --out {tmp_path}' in err
    assert not (tmp_path / weights).exists() and not (tmp_path / 'history.json').exists()


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(('127.0.0.1', 0))
        return int(probe.getsockname()[1])


def _rank(rank: int, port: int, out: str, results: Any, release: Any) -> None:
    """One of two processes of a DDP run (gloo, CPU) whose validation fails on process 0."""
    os.environ.update(
        MASTER_ADDR='127.0.0.1', MASTER_PORT=str(port), WORLD_SIZE='2', RANK=str(rank),
        LOCAL_RANK=str(rank),
    )  # fmt: skip
    from cva_confidence_ros.training import trainer

    if rank == 0:

        def broken(*args: Any, **kwargs: Any) -> None:
            raise RuntimeError('validation broke on process 0')

        trainer._validate = broken
    config = TrainConfig(
        matcher='census_bm', max_disparity=16, synthetic=1, synthetic_size=(32, 48),
        val_synthetic=1, val_pixels=40, batch_size=16, samples_per_epoch=32, epochs=1,
        epochs_low_lr=0, seed=3, threads=1, progress=False, out=out,
        weights_out=str(Path(out) / 'w.pt'),
    )  # fmt: skip
    tic = time.perf_counter()
    try:
        trainer.train(config)
        outcome = 'finished'
    except Exception as exc:
        outcome = f'{type(exc).__name__}: {exc}'
    results.put((rank, outcome, time.perf_counter() - tic))
    if rank == 0:
        release.wait(30)  # a caller that lives on after the error


def test_a_failure_of_process_0_alone_stops_the_other_process_at_once(tmp_path: Path) -> None:
    # Process 1 waited in the barrier for as long as process 0 lived on after its error, then
    # ended with gloo's 'Connection closed by peer'.
    context = multiprocessing.get_context('spawn')
    results, release = context.Queue(), context.Event()
    port, out = _free_port(), str(tmp_path / 'run')
    processes = [
        context.Process(target=_rank, args=(rank, port, out, results, release))
        for rank in range(2)
    ]
    for process in processes:
        process.start()
    outcomes: dict[int, str] = {}
    try:
        while len(outcomes) < 2:
            rank, outcome, _ = results.get(timeout=120)
            outcomes[rank] = outcome
            if rank == 1:
                release.set()
    finally:
        release.set()
        for process in processes:
            process.join(60)
            if process.is_alive():
                process.kill()
    assert outcomes[0] == 'RuntimeError: validation broke on process 0'
    assert outcomes[1].startswith('ModelError: process 0 of 2 stopped with an error'), outcomes
    assert not (tmp_path / 'run' / 'checkpoint.pt').exists()
    assert not (tmp_path / 'run' / 'w.pt').exists()
    log = (tmp_path / 'run' / 'train.log').read_text()
    assert 'epoch 1/1' not in log  # nothing of the epoch was recorded

"""Review 35 of ``cva-train`` under torchrun (training/cli.py): a run that failed ends its
processes with the error's exit code and without finalising the interpreter, whose gloo threads
(the process group is left alive after a failure) could turn that exit into a SIGABRT."""

from __future__ import annotations

import atexit
import multiprocessing
import os
from pathlib import Path
import socket
import sys
from typing import Any

import pytest
from train_test_utils import TINY


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(('127.0.0.1', 0))
        return int(probe.getsockname()[1])


def _rank(rank: int, port: int, out: str, error: str) -> None:
    """One of two processes of ``cva-train`` (gloo, CPU) whose validation fails on process 0."""
    os.environ.update(
        MASTER_ADDR='127.0.0.1', MASTER_PORT=str(port), WORLD_SIZE='2', RANK=str(rank),
        LOCAL_RANK=str(rank),
    )  # fmt: skip
    from cva_confidence_ros.errors import DataError
    from cva_confidence_ros.training import trainer
    from cva_confidence_ros.training.cli import main

    if rank == 0:
        kind = {'DataError': DataError, 'RuntimeError': RuntimeError}[error]

        def broken(*args: Any, **kwargs: Any) -> None:
            raise kind('validation broke on process 0')

        trainer._validate = broken
    # Stands in for the interpreter's finalisation, which the failed run must not reach.
    atexit.register(Path(out, f'finalised{rank}').write_text, 'yes')
    args = [*TINY, '--epochs', '1', '--epochs-low-lr', '0']
    sys.exit(main([*args, '--out', out, '--weights-out', str(Path(out, 'w.pt'))]))


@pytest.mark.parametrize(('error', 'codes'), [('DataError', (2, 2)), ('RuntimeError', (1, 2))])
def test_a_failed_run_ends_its_processes_with_its_code_and_no_finalisation(
    tmp_path: Path, error: str, codes: tuple[int, int]
) -> None:
    context = multiprocessing.get_context('spawn')
    port, out = _free_port(), str(tmp_path)
    processes = [context.Process(target=_rank, args=(rank, port, out, error)) for rank in range(2)]
    for process in processes:
        process.start()
    for process in processes:
        process.join(180)
        if process.is_alive():
            process.kill()
    assert tuple(process.exitcode for process in processes) == codes
    assert not list(tmp_path.glob('finalised*'))  # left by os._exit, not by finalisation
    assert not (tmp_path / 'w.pt').exists()

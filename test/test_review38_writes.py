"""Review 38 of interrupted writes: a full disk names its cause and the file (torch's writer said
'unexpected pos', the replay's report and the evaluation named a folder or nothing), leaves no
truncated file over an earlier run's; a torchrun process that lost another ends in one line."""

from __future__ import annotations

from collections.abc import Callable
from contextlib import AbstractContextManager
import multiprocessing
import os
from pathlib import Path
import signal
import socket
import sys
from typing import Any

import cv2
import numpy as np
import pytest
import torch

from cva_confidence_ros.datasets.synthetic import synthetic_pair
from cva_confidence_ros.errors import ConfigError, ModelError
from cva_confidence_ros.model import CVANet, save_weights
from cva_confidence_ros.outputs import torch_save_atomic

Limit = Callable[[int], AbstractContextManager[None]]


def test_save_weights_on_a_full_disk_names_the_cause(tmp_path: Path, file_size_limit: Limit):
    path = tmp_path / 'small' / 'w.pt'
    net = CVANet(16)
    save_weights(net, path, {'matcher': 'census_bm'})
    before = path.read_bytes()
    with file_size_limit(len(before) // 2), pytest.raises(ModelError) as error:
        save_weights(net, path, {'matcher': 'census_bm', 'note': 'second'})
    # Before: '(RuntimeError: [enforce fail at inline_container.cc:…] . unexpected pos …)'.
    assert str(error.value) == (
        f'cannot write weights file {path} (OSError: [Errno 27] File too large); the one there '
        'was left as it was'
    )
    assert path.read_bytes() == before
    assert [p.name for p in path.parent.iterdir()] == ['w.pt']


def test_torch_save_atomic_raises_the_file_systems_error(tmp_path: Path, file_size_limit: Limit):
    path = tmp_path / 'state.pt'
    with file_size_limit(1 << 16), pytest.raises(OSError) as error:
        torch_save_atomic(path, {'x': torch.zeros(1 << 16)})
    assert error.value.errno == 27 and not list(tmp_path.iterdir())
    torch_save_atomic(path, {'x': torch.ones(3)})
    assert torch.equal(torch.load(path, weights_only=True)['x'], torch.ones(3))


def test_replay_report_on_a_full_disk_keeps_the_old_file_and_names_it(
    tmp_path: Path, file_size_limit: Limit, monkeypatch: pytest.MonkeyPatch
) -> None:
    from msg_tools import scoring

    folder = tmp_path / 'report'
    frames = [scoring.FrameScore(frame=i, stamp_ns=i, kept_fraction=0.5) for i in range(3)]
    report = scoring.ReplayReport(frames=frames, config={'bag': 'in'})
    scoring.ReportWriter(folder, max_plots=0).write(report)
    before = (folder / 'summary.md').read_bytes()
    # A summary larger than the limit (the JSON and CSV fit): it fails half-way.
    monkeypatch.setattr(scoring, 'format_summary', lambda document: 'x' * 300_000)
    with file_size_limit(200_000), pytest.raises(ConfigError) as error:
        scoring.ReportWriter(folder, max_plots=0).write(report)
    # Before: 'cannot write the report into <folder>: …' and a summary.md cut at 200000 bytes.
    assert str(error.value) == (
        f'cannot write the report file {folder / "summary.md"}: OSError: [Errno 27] File too '
        'large; the one there was left as it was'
    )
    assert (folder / 'summary.md').read_bytes() == before
    assert not list(folder.glob('*.tmp'))


def test_a_killed_report_writers_partial_file_is_a_report_file(tmp_path: Path) -> None:
    from msg_tools.scoring import report_files

    (tmp_path / 'report.csv.123-456.tmp').write_text('half')
    (tmp_path / 'notes.txt.1-2.tmp').write_text('mine')
    assert [p.name for p in report_files(tmp_path)] == ['report.csv.123-456.tmp']


def _scenes(root: Path) -> Path:
    """Two tiny stereo_folder scenes (48×64, D = 16)."""
    for number in range(2):
        pair = synthetic_pair(500 + number, 48, 64, 16)
        folder = root / f's{number}'
        folder.mkdir(parents=True)
        for name, image in (('left.png', pair.left), ('right.png', pair.right)):
            cv2.imwrite(
                str(folder / name),
                cv2.cvtColor(image, cv2.COLOR_RGB2BGR) if image.ndim == 3 else image,
            )
        np.save(
            folder / 'disparity.npy',
            np.where(np.isfinite(pair.disparity), pair.disparity, 0.0).astype(np.float32),
        )
    return root


def test_evaluate_on_a_full_disk_names_the_png(
    tmp_path: Path, file_size_limit: Limit, capsys: pytest.CaptureFixture[str]
) -> None:
    from cva_confidence_ros.evaluation.cli import main as evaluate

    root = _scenes(tmp_path / 'data')
    out = tmp_path / 'out'
    # The records (< 1 kB) and disparity.png (~2 kB) fit; a confidence map (~8 kB) does not.
    with file_size_limit(4000):
        code = evaluate(['--data-root', str(root), '--dataset', 'stereo_folder', '--matchers',
                         'census_bm', '--methods', 'pkrn', '--max-disparity', '16', '--json',
                         str(out / 'r.json'), '--out', str(out)])  # fmt: skip
    line = capsys.readouterr().err.strip().splitlines()[-1]
    png = out / 'stereo_folder' / 's0' / 'census_bm' / 'confidence_pkrn.png'
    # Before: 'cva-evaluate: error: [Errno 27] File too large', no file named.
    assert code == 1
    assert line == f"cva-evaluate: error: [Errno 27] File too large: '{png}'"


def test_table1_png_on_a_full_disk_keeps_the_old_one_and_names_it(
    tmp_path: Path, file_size_limit: Limit
) -> None:
    from cva_confidence_ros.evaluation.table1 import TableRow, save_table_png

    path = tmp_path / 'table1.png'
    path.write_bytes(b'old')
    records = [{'row': 'KITTI 2012', 'scene': 'S0', 'matcher': 'census_bm', 'method': 'pkrn',
                'auc': 0.05, 'auc_opt': 0.02}]  # fmt: skip
    rows = [TableRow('KITTI 2012', 'kitti2012')]
    with file_size_limit(2000), pytest.raises(OSError) as error:
        save_table_png(records, rows, ['census_bm'], path, 'title', [('pkrn', 'PKRN')])
    # Before: a PNG cut at 2000 bytes over the old one, and an error naming no file.
    assert str(error.value) == f"[Errno 27] File too large: '{path}'"
    assert path.read_bytes() == b'old' and [p.name for p in tmp_path.iterdir()] == ['table1.png']


def test_a_torchrun_process_that_lost_another_says_so_in_one_line(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from cva_confidence_ros.training import cli

    def lost(*args: Any) -> int:
        raise RuntimeError(
            '[/pytorch/third_party/gloo/gloo/transport/tcp/pair.cc:537] Read error '
            '[127.0.0.1]:16007: Connection reset by peer. This is typically caused by a remote '
            'worker hanging or bugs in the application.'
        )

    ended: list[int] = []
    monkeypatch.setattr(cli, '_train', lost)
    monkeypatch.setattr(cli, '_group_left', lambda: True)
    monkeypatch.setattr(cli, 'end_process', ended.append)
    monkeypatch.setenv('RANK', '0')
    monkeypatch.setenv('WORLD_SIZE', '2')
    assert cli.main(['--synthetic', '1', '--out', 'run']) == 1
    err = capsys.readouterr().err
    # Before: the whole traceback, ending in gloo's 'GLHF!'.
    assert ended == [1] and 'Traceback' not in err
    assert err == (
        'cva-train: error: process 0 of 2 lost another process of its torchrun group '
        '(Connection reset by peer): it was killed or ended (out of memory, its node down, '
        "an error in its own output); torchrun's summary names it; --resume goes on from the "
        'last checkpoint in run (the work since it is lost)\n'
    )


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(('127.0.0.1', 0))
        return int(probe.getsockname()[1])


def _rank(rank: int, port: int, out: str) -> None:
    """One of two processes of ``cva-train`` (gloo, CPU); process 1 is killed (SIGKILL) at
    its second epoch."""
    os.environ.update(
        MASTER_ADDR='127.0.0.1', MASTER_PORT=str(port), WORLD_SIZE='2', RANK=str(rank),
        LOCAL_RANK=str(rank), OMP_NUM_THREADS='1',
    )  # fmt: skip
    sys.stderr = open(Path(out, f'err{rank}'), 'w', encoding='utf-8')  # noqa: SIM115
    from cva_confidence_ros.training import trainer
    from cva_confidence_ros.training.cli import main

    if rank == 1:
        run_epoch = trainer._run_epoch
        calls: list[int] = []

        def killed(*args: Any, **kwargs: Any) -> Any:
            calls.append(1)
            if len(calls) == 2:
                os.kill(os.getpid(), signal.SIGKILL)
            return run_epoch(*args, **kwargs)

        trainer._run_epoch = killed
    sys.exit(main([
        '--synthetic', '2', '--synthetic-size', '24x40', '--max-disparity', '16',
        '--samples-per-epoch', '64', '--epochs', '2', '--epochs-low-lr', '1', '--threads', '1',
        '--no-progress', '--out', str(Path(out, 'run')),
    ]))  # fmt: skip


def test_a_killed_worker_ends_the_other_in_one_line(tmp_path: Path) -> None:
    context = multiprocessing.get_context('spawn')
    port, out = _free_port(), str(tmp_path)
    processes = [context.Process(target=_rank, args=(rank, port, out)) for rank in range(2)]
    for process in processes:
        process.start()
    for process in processes:
        process.join(120)
        if process.is_alive():
            process.kill()
    assert [process.exitcode for process in processes] == [1, -signal.SIGKILL]
    err = (tmp_path / 'err0').read_text(encoding='utf-8')
    assert 'Traceback' not in err, err
    assert (
        err.strip()
        .splitlines()[-1]
        .startswith(
            'cva-train: error: process 0 of 2 lost another process of its torchrun group ('
        )
    )
    assert f'--resume goes on from the last checkpoint in {tmp_path / "run"}' in err
    assert (tmp_path / 'run' / 'checkpoint.pt').is_file()  # epoch 1's: --resume has a start


def test_a_png_that_fails_half_way_is_named(tmp_path: Path) -> None:
    # Every PNG writer goes through plots._save: a full disk said only '[Errno 28] No space
    # left on device', naming neither the PNG nor its temporary file.
    import errno

    from cva_confidence_ros import plots

    def full(partial: Path) -> None:
        partial.write_bytes(b'\x89PNG')
        raise OSError(errno.ENOSPC, 'No space left on device')

    with pytest.raises(OSError, match='confidence.png') as caught:
        plots._save(tmp_path / 'confidence.png', full)
    assert caught.value.errno == errno.ENOSPC
    assert list(tmp_path.iterdir()) == []

"""Review 37: the command-line tools driven from shell scripts, Makefiles and CI jobs (no
terminal, ``timeout``/SIGTERM, two jobs at once), regression tests of the faults found."""

from __future__ import annotations

import fcntl
import os
from pathlib import Path
import signal
import threading
import time

import pytest

from cva_confidence_ros.training.cli import build_parser, config_from_args
from cva_confidence_ros.training.cli import main as train_main

#: Two 24×40 synthetic pairs at D = 16, 32 samples, one epoch: a second or two.
TINY = [
    '--matcher', 'census_bm', '--max-disparity', '16', '--synthetic', '2',
    '--synthetic-size', '24x40', '--batch-size', '16', '--samples-per-epoch', '32',
    '--threads', '1', '--epochs', '1', '--epochs-low-lr', '0',
]  # fmt: skip


class _Terminal:
    def isatty(self) -> bool:
        return True

    def write(self, text: str) -> int:
        return len(text)

    def flush(self) -> None:
        pass


def test_train_shows_no_progress_bar_where_stderr_is_no_terminal(monkeypatch) -> None:
    # Was: the bar went to a log file or a pipe too (`2>&1 | tee log`, CI), a stream of
    # carriage returns; only --no-progress stopped it.
    args = build_parser().parse_args(['--synthetic', '2'])
    monkeypatch.setattr('sys.stderr', _Terminal())
    assert config_from_args(args).progress
    assert not config_from_args(build_parser().parse_args(['--synthetic', '2', '--no-progress'])
                                ).progress
    monkeypatch.undo()  # pytest's capture: no terminal
    assert not config_from_args(args).progress


def test_a_second_train_run_into_the_same_out_is_refused(tmp_path, capsys) -> None:
    # Was: both trained, replacing each other's checkpoint and history epoch by epoch, until
    # one failed on the other's temporary file (FileNotFoundError: checkpoint.pt.tmp).
    out = tmp_path / 'run dir'
    out.mkdir()
    held = os.open(out, os.O_RDONLY)  # what the run going on holds
    try:
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        assert train_main([*TINY, '--out', str(out)]) == 2
        err = capsys.readouterr().err
        assert f'--out {out} is in use by another cva-train run' in err
        assert list(out.iterdir()) == []
    finally:
        os.close(held)
    assert train_main([*TINY, '--out', str(out), '--no-progress']) == 0
    assert (out / 'checkpoint.pt').is_file()
    # Released at the end: the next run in that folder is not refused.
    assert train_main([*TINY, '--out', str(out), '--overwrite']) == 0


def _terminate_once_waiting(stop: threading.Event) -> None:
    """SIGTERM to this process once the tool has its own handler in place (or rclpy's)."""
    deadline = time.monotonic() + 20.0
    while time.monotonic() < deadline and not stop.is_set():
        if signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL:
            time.sleep(1.0)  # into the wait for the node
            if not stop.is_set():
                os.kill(os.getpid(), signal.SIGTERM)
            return
        time.sleep(0.05)


@pytest.mark.parametrize('tool', ['param', 'lifecycle'])
def test_param_and_lifecycle_end_on_sigterm_with_143(tool, monkeypatch, capsys) -> None:
    # Was: rclpy's handler shut the context down and the wait failed with a traceback
    # (RCLError: rcl node's context is invalid) and exit status 1, the status of a refusal.
    if tool == 'param':
        from cva_confidence_ros.ros.param_cli import main
        argv = ['--timeout', '30', 'get', '/review37_no_such_node', 'x']
    else:
        from cva_confidence_ros.ros.lifecycle_cli import main
        argv = ['--timeout', '30', 'get', '/review37_no_such_node']
    monkeypatch.setenv('ROS_DOMAIN_ID', '97')
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL
    stop = threading.Event()
    killer = threading.Thread(target=_terminate_once_waiting, args=(stop,), daemon=True)
    killer.start()
    started = time.monotonic()
    try:
        code = main(argv)
    finally:
        stop.set()
        killer.join()
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
    assert code == 143 and time.monotonic() - started < 25
    assert capsys.readouterr().err == f'cva-{tool}: terminated\n'


def test_param_and_lifecycle_end_on_ctrl_c_with_130(capsys) -> None:
    from cva_confidence_ros.ros.lifecycle_cli import interruptible

    def body() -> int:
        raise KeyboardInterrupt

    assert interruptible('cva-param', body) == 130
    assert capsys.readouterr().err == 'cva-param: interrupted\n'
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL


def test_a_run_refused_for_its_options_makes_no_out_folder(tmp_path: Path) -> None:
    # The --out lock made the folder before the trainer refused an unknown matcher.
    from cva_confidence_ros.training.cli import main

    out = tmp_path / 'run'
    assert main(['--matcher', 'census_bn', '--max-disparity', '16', '--synthetic', '2',
                 '--out', str(out), '--no-progress']) == 2
    assert not out.exists()

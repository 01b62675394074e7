"""Review 31 of cva-bag-from-dataset: the first Ctrl-C says that the run stops after the
frame (a scene can take a while to load: the run looked stuck)."""

from __future__ import annotations

from pathlib import Path
import signal

from msg_test_utils import synthetic_samples
import pytest


def test_the_first_ctrl_c_is_answered_on_stderr(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from msg_tools.bag_from_dataset import STOPPING, write_dataset_bag

    lines: list[str] = []

    def log(line: str) -> None:
        lines.append(line)
        if line.startswith('frame 0'):
            signal.raise_signal(signal.SIGINT)

    summary = write_dataset_bag(synthetic_samples(2), tmp_path / 'bag', log=log)
    assert summary.interrupted and summary.frames == 1
    err = capsys.readouterr().err
    assert f'{STOPPING} (Ctrl-C again to stop at once)' in err
    assert 'stopping after this frame' in STOPPING

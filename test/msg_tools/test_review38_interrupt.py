"""Review 38 of the bag tools' interruptions: SIGTERM ends with 143 (as cva-evaluate), the folder
a killed writer left is a bag --overwrite may replace, and a sqlite3 bag whose storage rolled
back on a full disk leaves no metadata.yaml that lists messages it does not hold."""

from __future__ import annotations

from pathlib import Path
import resource
import signal
from typing import Any

from msg_test_utils import (
    read_bag,
    replay_offline,
    synthetic_samples,
    write_middlebury_root,
    write_stereo_bag,
)
import numpy as np
import pytest

from cva_confidence_ros.errors import BagError
from msg_tools.bagio import OutputBag, check_replaceable, remove_bag
from msg_tools.convert import IMAGE, image_to_msg
from msg_tools.progress import GracefulInterrupt


def test_graceful_interrupt_tells_sigterm_from_ctrl_c(capsys: pytest.CaptureFixture[str]) -> None:
    with GracefulInterrupt(notice='[tool] Ctrl-C: stopping after this frame') as interrupts:
        signal.raise_signal(signal.SIGTERM)
        assert interrupts.requested
    assert interrupts.exit_code == 143
    assert '[tool] SIGTERM: stopping after this frame' in capsys.readouterr().err
    with GracefulInterrupt() as interrupts:
        signal.raise_signal(signal.SIGINT)
    assert interrupts.exit_code == 130


def test_bag_from_dataset_ends_with_143_on_sigterm(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import msg_tools.bag_from_dataset as tool

    root = write_middlebury_root(tmp_path / 'data', synthetic_samples(3))
    frame_messages = tool._frame_messages

    def first_then_sigterm(*args: Any) -> Any:
        signal.raise_signal(signal.SIGTERM)  # a batch system's time limit, mid-run
        return frame_messages(*args)

    monkeypatch.setattr(tool, '_frame_messages', first_then_sigterm)
    bag = tmp_path / 'bag'
    code = tool.main(['--data-root', str(root), '--dataset', 'middlebury2014', '--out', str(bag)])
    assert code == 143
    assert 'SIGTERM: stopping after this frame' in capsys.readouterr().err
    assert len(read_bag(bag)['/left/image_rect']) == 1  # finalised, with the frame written


def test_bag_replay_ends_with_143_on_sigterm(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from msg_tools.replay import ReplaySession

    bag = write_stereo_bag(tmp_path / 'in', [{}, {}, {}])
    add_result = ReplaySession.add_result

    def then_sigterm(self: Any, result: Any) -> None:
        add_result(self, result)
        signal.raise_signal(signal.SIGTERM)

    monkeypatch.setattr(ReplaySession, 'add_result', then_sigterm)
    code, err, report = replay_offline(bag, tmp_path, capsys)
    assert code == 143, err
    assert 'interrupted after 1 frames' in err
    assert len(report['frames']) == 1
    assert len(read_bag(tmp_path / 'out')['/disparity']) == 1


def _killed_writes(tmp_path: Path) -> dict[str, Path]:
    """Bag folders as a SIGKILL (or a full disk) leaves them: storage files, no metadata."""
    folders = {}
    for storage, suffix in (('mcap', '.mcap'), ('sqlite3', '.db3')):
        source = write_stereo_bag(tmp_path / f'src_{storage}', [{}], storage=storage)
        folder = tmp_path / f'killed_{storage}'
        folder.mkdir()
        data = (source / f'src_{storage}{suffix}').read_bytes()
        # An MCAP cut short (no summary, no footer); a sqlite3 file with its journal.
        (folder / f'killed_{storage}{suffix}').write_bytes(
            data[: len(data) // 2] if suffix == '.mcap' else data
        )
        if suffix == '.db3':
            (folder / f'killed_{storage}.db3-journal').write_bytes(b'\0' * 512)
        folders[storage] = folder
    return folders


def test_overwrite_replaces_the_folder_a_killed_writer_left(tmp_path: Path) -> None:
    for folder in _killed_writes(tmp_path).values():
        assert check_replaceable(folder)
        with OutputBag(folder, overwrite=True) as bag:
            bag.write('/a', IMAGE, image_to_msg(np.zeros((4, 6), np.uint8), 1, 'l'), 1)
        assert bag.replacing and len(read_bag(folder)['/a']) == 1
    killed = _killed_writes(tmp_path / 'again')['mcap']
    remove_bag(killed)
    assert not killed.exists()
    # Only such folders: one with anything more, or a storage file that is none, stays.
    folders = _killed_writes(tmp_path / 'foreign')
    (folders['mcap'] / 'notes.txt').write_text('mine\n')
    (folders['sqlite3'] / 'killed_sqlite3.db3').write_bytes(b'not a database')
    other = tmp_path / 'foreign' / 'other'
    other.mkdir()
    (other / 'notes.mcap').write_bytes(b'\x89MCAP0\r\n')  # not named after the folder
    folders['other'] = other
    for folder in folders.values():
        with pytest.raises(BagError, match=f'refusing to overwrite {folder}'):
            remove_bag(folder)
        assert any(folder.iterdir())


def test_replay_overwrite_after_a_killed_replay(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = write_stereo_bag(tmp_path / 'in', [{}])
    out = tmp_path / 'out'
    out.mkdir()
    (out / 'out.mcap').write_bytes(b'\x89MCAP0\r\n' + b'\0' * 64)  # what SIGKILL left
    (tmp_path / 'report').mkdir()
    code, err, report = replay_offline(bag, tmp_path, capsys)
    assert code == 2 and 'use --overwrite' in err
    code, err, report = replay_offline(bag, tmp_path, capsys, '--overwrite')
    assert code == 0, err
    assert len(read_bag(out)['/disparity']) == 1


@pytest.fixture
def file_size_limit() -> Any:
    """Set RLIMIT_FSIZE's soft limit (a full disk for files past it: EFBIG; Python ignores
    SIGXFSZ); put it back afterwards."""
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)

    def limit(size: int) -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (size, hard))

    yield limit
    resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))


def test_sqlite3_bag_on_a_full_disk_leaves_no_lying_metadata(
    tmp_path: Path, file_size_limit: Any
) -> None:
    path = tmp_path / 'full'
    image = np.zeros((200, 300), np.uint8)
    bag = OutputBag(path, 'sqlite3')
    bag.open()
    file_size_limit(300_000)
    with pytest.raises(BagError) as caught:
        for stamp in range(50):
            bag.write('/a', IMAGE, image_to_msg(image, stamp, 'l', bag.typestore), stamp)
    bag.close()
    message = str(caught.value)
    # Before: metadata.yaml listed every message written; the storage held none of them.
    assert message.startswith(f'cannot write to output bag {path}: ')
    assert 'sqlite3 dropped the' in message and 'no bag was left there' in message
    assert bag.lost and not path.exists()


def test_bag_from_dataset_on_a_full_disk_says_no_bag_was_left(
    tmp_path: Path, file_size_limit: Any, capsys: pytest.CaptureFixture[str]
) -> None:
    from cva_confidence_ros.datasets.synthetic import synthetic_pair
    from msg_tools.bag_from_dataset import main

    # More than sqlite3's page cache holds (2 MB), so that the writes spill to the file.
    samples = [synthetic_pair(seed, 240, 320, max_disparity=16) for seed in range(6)]
    root = write_middlebury_root(tmp_path / 'data', samples)
    bag = tmp_path / 'bag'
    file_size_limit(1_000_000)
    code = main(['--data-root', str(root), '--dataset', 'middlebury2014', '--out', str(bag),
                 '--storage', 'sqlite3'])
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if 'error' in line]
    assert code == 2 and len(errors) == 1 and 'Traceback' not in err
    # Before: "... holds the N frames written before it", of a bag that held none.
    assert 'no bag was left there' in err and 'frames written before' not in err
    assert not bag.exists()


def test_a_sigterm_notice_does_not_ask_for_ctrl_c(capsys: pytest.CaptureFixture[str]) -> None:
    # Nobody pressed Ctrl-C under a batch system's SIGTERM: the notice said to press it again.
    from msg_tools.progress import GracefulInterrupt

    with GracefulInterrupt('Ctrl-C: stopping after this frame') as interrupts:
        signal.raise_signal(signal.SIGTERM)
    err = capsys.readouterr().err
    assert 'SIGTERM: stopping after this frame (a second signal to stop at once)' in err
    assert interrupts.exit_code == 143

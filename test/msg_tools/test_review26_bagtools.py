"""Review fixes of the bag tools: damaged compressed bags, a metadata.yaml that does not match
its storage, an output bag whose storage file cannot be created, Ctrl-C in
``cva-bag-from-dataset`` before its first frame and between frames."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
import signal
import sqlite3
from typing import Any

from msg_test_utils import synthetic_samples
import numpy as np
import pytest

from cva_confidence_ros.errors import BagError, DataError
from msg_tools.bagio import InputBag, OutputBag
from msg_tools.convert import IMAGE, image_to_msg, jazzy_typestore

ZSTD_MAGIC = b'\x28\xb5\x2f\xfd'


def _images(bag: Any, topic: str = '/a', count: int = 3) -> None:
    for index in range(count):
        bag.write(topic, IMAGE, image_to_msg(np.full((20, 30), index, np.uint8), index, 'f'),
                  index)


def _read_all(path: Path) -> int:
    with InputBag(path) as bag:
        return len(list(bag.messages(list(bag.topics))))


def _damage_zstd(file: Path, length: int) -> None:
    """Overwrite ``length`` bytes of the first zstd frame in ``file``, past its magic."""
    data = bytearray(file.read_bytes())
    at = data.find(ZSTD_MAGIC)
    data[at + 4 : at + 4 + length] = b'\xff' * length
    file.write_bytes(data)


def test_damaged_zstd_is_a_bag_error(tmp_path: Path) -> None:
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

    # An MCAP with zstd chunks (what `ros2 bag record` writes by default), one chunk damaged.
    chunked = tmp_path / 'chunked'
    writer = Writer(chunked, version=8, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    writer.open()
    conn = writer.add_connection('/a', IMAGE, typestore=jazzy_typestore())
    for index in range(3):
        message = image_to_msg(np.full((20, 30), index, np.uint8), index, 'f')
        writer.write(conn, index, jazzy_typestore().serialize_cdr(message, IMAGE))
    writer.close()
    _damage_zstd(chunked / 'chunked.mcap', 8)
    with pytest.raises(BagError, match='corrupt or truncated after 0 messages: ZstdError'):
        _read_all(chunked)

    # Per-message zstd (--compression message), one message's data damaged.
    for storage_id in ('mcap', 'sqlite3'):
        path = tmp_path / f'message_{storage_id}'
        with OutputBag(path, storage_id, compression='message') as bag:
            _images(bag)
        if storage_id == 'sqlite3':
            with sqlite3.connect(path / f'{path.name}.db3') as db:
                db.execute("UPDATE messages SET data = x'28b52ffd00000000' WHERE id = 2")
            db.close()
        else:
            _damage_zstd(path / f'{path.name}.mcap', 16)
        with pytest.raises(BagError, match='ZstdError'):
            _read_all(path)

    # A metadata.yaml that says the file is zstd-compressed, over a plain file.
    plain = tmp_path / 'plain'
    with OutputBag(plain) as bag:
        _images(bag)
    metadata = plain / 'metadata.yaml'
    metadata.write_text(
        metadata.read_text()
        .replace("compression_mode: ''", 'compression_mode: file')
        .replace("compression_format: ''", 'compression_format: zstd')
    )
    with pytest.raises(BagError, match=r'cannot open bag .*ZstdError'):
        _read_all(plain)


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
@pytest.mark.parametrize(
    'old,new',
    [
        ('type: sensor_msgs/msg/Image', 'type: sensor_msgs/msg/CameraInfo'),
        ('name: /a', 'name: /renamed'),
    ],
)
def test_metadata_that_does_not_match_the_storage(
    tmp_path: Path, storage: str, old: str, new: str
) -> None:
    path = tmp_path / 'bag'
    with OutputBag(path, storage) as bag:
        _images(bag)
        _images(bag, '/b')
    assert _read_all(path) == 6
    metadata = path / 'metadata.yaml'
    text = metadata.read_text()
    assert old in text
    metadata.write_text(text.replace(old, new, 1))
    with InputBag(path) as bag:
        topic = '/renamed' if 'renamed' in new else '/a'
        # Before: nothing at all came back for the edited topic, as if it were empty.
        with pytest.raises(BagError, match=f'lists 3 messages on {topic} .*holds none'):
            list(bag.messages([topic, '/b']))
        # A topic whose metadata is right still reads.
        assert [t for _, _, t, _ in bag.messages(['/b'])] == [0, 1, 2]


@pytest.mark.parametrize('count', ['lots', '-1'])
def test_metadata_with_a_bad_message_count(tmp_path: Path, count: str) -> None:
    path = tmp_path / 'bag'
    with OutputBag(path) as bag:
        _images(bag)
    metadata = path / 'metadata.yaml'
    text = metadata.read_text().replace('message_count: 3', f'message_count: {count}')
    metadata.write_text(text)
    # Before: a ValueError from message_counts ('lots'), or a count of -1.
    shown = repr(count) if count == 'lots' else count
    with pytest.raises(BagError, match=f'gives topic /a {shown} messages; expected a count'):
        with InputBag(path) as bag:
            bag.message_counts  # noqa: B018


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_output_bag_whose_storage_file_cannot_be_created(tmp_path: Path, storage: str) -> None:
    # The folder name fits (255 bytes at most), the storage file's (name + suffix) does not.
    path = tmp_path / ('b' * 252)
    with pytest.raises(BagError, match='cannot create output bag'):
        OutputBag(path, storage).open()
    # Before: sqlite3 raised sqlite3.OperationalError, and an empty folder stayed behind,
    # which no later run could write or --overwrite.
    assert list(tmp_path.iterdir()) == []


def _middlebury_root(tmp_path: Path) -> Path:
    from msg_test_utils import write_middlebury_root

    return write_middlebury_root(tmp_path / 'data', synthetic_samples(2))


def test_ctrl_c_before_the_first_frame_exits_130(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import cva_confidence_ros.datasets as datasets
    from msg_tools.bag_from_dataset import main

    [sample] = synthetic_samples(1)

    def ctrl_c_while_loading(*_: object, **__: object) -> Any:
        signal.raise_signal(signal.SIGINT)  # during the first scene's loading
        yield sample

    monkeypatch.setattr(datasets, 'load_dataset', ctrl_c_while_loading)
    out = tmp_path / 'bag'
    code = main(['--data-root', str(tmp_path), '--dataset', 'middlebury2014', '--out', str(out)])
    err = capsys.readouterr().err
    # Before: exit 2 and 'error: data set ... yielded no frames'.
    assert code == 130
    assert 'yielded no frames' not in err
    assert f'interrupted before the first frame was written; no bag was written at {out}' in err
    assert not out.exists()  # review 30: an empty bag blocked the retry (it needed --overwrite)


def test_ctrl_c_during_a_frame_loads_no_further_scene(tmp_path: Path) -> None:
    from msg_tools.bag_from_dataset import write_dataset_bag

    first, _ = synthetic_samples(2)
    loaded = []

    def samples() -> Any:
        loaded.append(0)
        yield first
        loaded.append(1)
        raise DataError('scene 1 is broken')  # a slow or broken next scene

    def log(line: str) -> None:
        if line.startswith('frame 0'):
            signal.raise_signal(signal.SIGINT)

    # Before: the next scene was loaded after the Ctrl-C; its DataError ended the run.
    summary = write_dataset_bag(samples(), tmp_path / 'bag', log=log)
    assert summary.interrupted and summary.frames == 1
    assert loaded == [0]
    assert _read_all(tmp_path / 'bag') == 5


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_a_full_disk_keeps_the_old_bag(
    tmp_path: Path, storage: str, file_size_limit: Callable[[int], Any]
) -> None:
    path = tmp_path / 'bag'
    with OutputBag(path, storage) as bag:
        _images(bag, '/old', 1)
    big = image_to_msg(np.zeros((200, 300, 3), np.uint8), 0, 'f')
    # Before: OSError / sqlite3.OperationalError tracebacks; for sqlite3 the old bag was then
    # replaced by the new one, whose metadata listed messages its storage had rolled back
    # (0 messages), and for MCAP the staging folder was left behind.
    with pytest.raises(BagError, match='output bag .*the old bag was left as it was'):
        with file_size_limit(400_000), OutputBag(path, storage, overwrite=True) as bag:
            for index in range(12):
                bag.write('/new', IMAGE, big, index)
    with InputBag(path) as old:
        assert [topic for topic, *_ in old.messages(['/old', '/new'])] == ['/old']
    assert list(tmp_path.iterdir()) == [path]
    # Without an old bag: an error that says so, not a traceback.
    with pytest.raises(BagError, match=f'output bag {tmp_path / "new"}'):
        with file_size_limit(400_000), OutputBag(tmp_path / 'new', storage) as bag:
            for index in range(12):
                bag.write('/new', IMAGE, big, index)

"""rosbag2 reading and writing: real MCAP and sqlite3 bags in tmp_path, and damaged ones."""

from __future__ import annotations

from pathlib import Path
import shutil

from msg_test_utils import break_storage, read_bag, textured_pair, write_stereo_bag
import numpy as np
import pytest

from cva_confidence_ros.errors import BagError, ConfigError
from msg_tools.bagio import TOPIC_MAX_LENGTH, InputBag, OutputBag, check_topic_name, remove_bag
from msg_tools.convert import CAMERA_INFO, IMAGE, image_to_msg, jazzy_typestore


def _small_bag(path: Path, storage: str) -> Path:
    store = jazzy_typestore()
    with OutputBag(path, storage) as bag:
        for index in range(3):
            msg = image_to_msg(np.full((2, 3), index, np.uint8), 1000 + index, 'cam')
            bag.write('/cam/image', IMAGE, msg, 1000 + index)
            # Raw CDR bytes are written as they are.
            bag.write('/cam/raw', IMAGE, bytes(store.serialize_cdr(msg, IMAGE)), 1000 + index)
    return path


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_round_trip(tmp_path: Path, storage: str) -> None:
    path = _small_bag(tmp_path / 'bag', storage)
    metadata = (path / 'metadata.yaml').read_text()
    assert 'version: 8' in metadata
    assert f'storage_identifier: {storage}' in metadata
    assert 'RIHS01_' in metadata  # Jazzy type hashes, which `ros2 bag` checks
    with InputBag(path) as bag:
        assert bag.topics == {'/cam/image': IMAGE, '/cam/raw': IMAGE}
        assert bag.message_counts == {'/cam/image': 3, '/cam/raw': 3}
        assert bag.require('/cam/image', (IMAGE,), 'left') == IMAGE
        rows = list(bag.messages(['/cam/image']))
    assert [timestamp for _, _, timestamp, _ in rows] == [1000, 1001, 1002]
    messages = read_bag(path)
    for (_, a), (_, b) in zip(messages['/cam/image'], messages['/cam/raw'], strict=True):
        np.testing.assert_array_equal(a.data, b.data)
    assert [int(m.data[0]) for _, m in messages['/cam/image']] == [0, 1, 2]


def test_output_bag_refuses_existing_and_type_changes(tmp_path: Path) -> None:
    path = _small_bag(tmp_path / 'bag', 'mcap')
    with pytest.raises(BagError, match='exists already'):
        OutputBag(path).open()
    with pytest.raises(BagError, match='storage'):
        OutputBag(tmp_path / 'x', storage='rosbag1')
    with OutputBag(tmp_path / 'other') as bag:
        bag.write('/a', IMAGE, image_to_msg(np.zeros((1, 1), np.uint8), 0, 'f'), 0)
        with pytest.raises(BagError, match='has type'):
            bag.write('/a', CAMERA_INFO, b'\x00\x01\x00\x00', 1)
    (tmp_path / 'plain').mkdir()
    with pytest.raises(BagError, match='refusing'):
        remove_bag(tmp_path / 'plain')
    remove_bag(path)
    assert not path.exists()


def test_missing_and_foreign_paths(tmp_path: Path) -> None:
    with pytest.raises(BagError, match='does not exist'):
        InputBag(tmp_path / 'nothing').__enter__()
    (tmp_path / 'folder').mkdir()
    with pytest.raises(BagError, match='not a rosbag2'):
        InputBag(tmp_path / 'folder').__enter__()


def test_corrupt_and_truncated_storage(tmp_path: Path) -> None:
    path = write_stereo_bag(tmp_path / 'bag', [{}, {}, {}])
    data_file = path / 'bag.mcap'
    original = data_file.read_bytes()
    data_file.write_bytes(original[: len(original) // 2])
    with pytest.raises(BagError, match='corrupt or truncated'):
        with InputBag(path) as bag:
            list(bag.messages(list(bag.topics)))
    data_file.write_bytes(b'\x89MCAP0\r\n' + bytes(range(256)) * 8)
    with pytest.raises(BagError, match='corrupt or truncated'):
        with InputBag(path) as bag:
            list(bag.messages(list(bag.topics)))


def test_require_names_what_the_bag_has(tmp_path: Path) -> None:
    path = write_stereo_bag(tmp_path / 'bag', [{}], skip_topics=('right/camera_info',))
    with InputBag(path) as bag:
        with pytest.raises(BagError, match=r"no right info topic '/right/camera_info'.*"
                                           r'/left/camera_info \[sensor_msgs/msg/CameraInfo\]'):
            bag.require('/right/camera_info', (CAMERA_INFO,), 'right info')
        with pytest.raises(BagError, match='expected one of'):
            bag.require('/left/image_rect', (CAMERA_INFO,), 'left info')


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_storage_that_fails_part_way(tmp_path: Path, storage: str) -> None:
    # rosbags raises OverflowError (MCAP) and apsw.CorruptError (sqlite3) for these.
    frames = [dict(zip(('left', 'right'), textured_pair(100, 120, 4, i), strict=True))
              for i in range(6)]
    path = write_stereo_bag(tmp_path / 'bag', frames, storage=storage)
    read = break_storage(path)
    rows = []
    with pytest.raises(BagError) as caught:
        with InputBag(path) as bag:
            rows.extend(bag.messages(list(bag.topics)))
    message = str(caught.value)
    assert message.startswith(f'bag {path} is corrupt or truncated after {read} messages: ')
    assert len(rows) == read and '\n' not in message


def test_malformed_metadata_is_one_line(tmp_path: Path) -> None:
    path = write_stereo_bag(tmp_path / 'bag', [{}])
    (path / 'metadata.yaml').write_text('rosbag2_bagfile_information: [\n')
    with pytest.raises(BagError) as caught:
        InputBag(path).__enter__()
    message = str(caught.value)
    assert message.startswith(f'cannot open bag {path} (corrupt or truncated?): ReaderError: ')
    assert 'metadata.yaml' in message and '\n' not in message


def test_remove_bag_removes_only_bags(tmp_path: Path) -> None:
    folder = write_stereo_bag(tmp_path / 'bag', [{}], storage='mcap')
    single = {}
    for storage, suffix in (('mcap', '.mcap'), ('sqlite3', '.db3')):
        source = write_stereo_bag(tmp_path / f'src_{storage}', [{}], storage=storage)
        single[suffix] = tmp_path / f'single{suffix}'
        shutil.copy(source / f'src_{storage}{suffix}', single[suffix])
    foreign = {
        'notes.mcap': b'not a bag\n',
        'notes.db3': b'\x89MCAP0\r\n',  # the other format's magic
        'empty.mcap': b'',
    }
    for name, content in foreign.items():
        (tmp_path / name).write_bytes(content)
    (tmp_path / 'link').symlink_to(folder)
    for name in (*foreign, 'link'):
        with pytest.raises(BagError, match=f'refusing to overwrite {tmp_path / name}'):
            remove_bag(tmp_path / name)
        assert (tmp_path / name).exists()
    for name, content in foreign.items():
        assert (tmp_path / name).read_bytes() == content
    assert (folder / 'metadata.yaml').exists()  # not through the link either
    for path in (folder, *single.values()):
        remove_bag(path)
        assert not path.exists()
    remove_bag(tmp_path / 'never_there')  # nothing to do


@pytest.mark.parametrize('name', ['/a', '/stereo/left/image_rect', '/a_1/_b/C9', '/x' * 100])
def test_valid_topic_names(name: str) -> None:
    assert check_topic_name(name) == name


@pytest.mark.parametrize(
    ('name', 'rule'),
    [
        ('a/b', 'must start with /'),
        ('/a b', "only letters, digits, _ and / are allowed; it has ' '"),
        ('/~/a', "it has '~'"),
        ('/{ns}/a', "it has '{}'"),
        ('/caméra', "it has 'é'"),
        ('/1bad//x', 'no part of it may be empty'),
        ('/a/', 'no part of it may be empty'),
        ('/', 'no part of it may be empty'),
        ('/stereo/1bad', 'no part of it may start with a digit'),
        ('/' + 'a' * TOPIC_MAX_LENGTH, f'at most {TOPIC_MAX_LENGTH} characters'),
    ],
)
def test_invalid_topic_names(name: str, rule: str) -> None:
    with pytest.raises(ConfigError) as caught:
        check_topic_name(name, 'topic prefix')
    message = str(caught.value)
    assert message.startswith('topic prefix must be a valid ROS 2 topic name (')
    assert rule in message and message.endswith(f'); got {name!r}')

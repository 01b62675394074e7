"""Review fixes of the bag I/O, the message conversions and the ``cva-bag-replay`` options:
big-endian 16-bit images, empty images, stamps past int32 seconds, a damaged row step, a
topic with messages of several types, messages lost from the storage, an empty --gt-topic."""

from __future__ import annotations

from pathlib import Path
import sqlite3
import struct

import numpy as np
import pytest

from cva_confidence_ros.errors import BagError, ConfigError, InputError
from msg_tools.bag_replay import build_parser, options_from_args
from msg_tools.bagio import InputBag, OutputBag
from msg_tools.convert import (
    COMPRESSED_IMAGE,
    IMAGE,
    disparity_from_msg,
    float_image_to_msg,
    image_to_msg,
    jazzy_typestore,
    make_header,
)


def test_a_big_endian_uint16_image_is_written_as_mono16() -> None:
    # A 16-bit PGM or PNG comes as '>u2'. Before: refused as "got (2, 3) >u2".
    values = np.array([[0, 1, 258], [65535, 4096, 7]], dtype='>u2')
    msg = image_to_msg(values, 5, 'cam')
    assert (msg.encoding, msg.is_bigendian, msg.step) == ('mono16', 0, 6)
    assert bytes(msg.data) == values.astype('<u2').tobytes()


@pytest.mark.parametrize(
    ('write', 'array'),
    [
        (image_to_msg, np.zeros((0, 4), np.uint8)),
        (image_to_msg, np.zeros((3, 0, 3), np.uint8)),
        (float_image_to_msg, np.zeros((0, 4), np.float32)),
    ],
)
def test_an_empty_image_is_not_written(write, array: np.ndarray) -> None:
    # Before: a message of height or width 0 and step 0, which every reader refuses.
    with pytest.raises(InputError, match=r'cannot write an empty .* image \(\d×\d\)'):
        write(array, 0, 'cam')


@pytest.mark.parametrize('stamp', [2**31 * 10**9, 2**63, float('nan')])
def test_a_stamp_a_header_cannot_hold_is_refused(stamp: float) -> None:
    # Before: a header whose serialisation failed later with a bare struct.error (int32
    # seconds), or a ValueError for NaN.
    with pytest.raises(InputError, match='int32 seconds'):
        make_header(stamp, 'f')
    last = make_header(2**31 * 10**9 - 1, 'f')
    assert (last.stamp.sec, last.stamp.nanosec) == (2**31 - 1, 999_999_999)
    jazzy_typestore().serialize_cdr(last, 'std_msgs/msg/Header')


def test_a_damaged_row_step_costs_no_memory() -> None:
    # One row whose step is far beyond the data (a damaged message). Before: a MemoryError
    # (1 PiB of padding allocated for the missing end of the row).
    store = jazzy_typestore()
    data = np.frombuffer(np.array([1.0, 2.0], '<f4').tobytes(), np.uint8).copy()
    msg = store.types[IMAGE](
        header=make_header(0, 'f', store), height=1, width=2, encoding='32FC1',
        is_bigendian=0, step=2**50, data=data,
    )
    assert disparity_from_msg(msg).tolist() == [[1.0, 2.0]]
    # Padded big-endian rows, the last one without its padding, still read right.
    rows = np.array([[1.5, np.nan, 3.0], [0.0, -1.0, 2.25]], '>f4')
    padded = rows[0].tobytes() + b'\xaa' * 4 + rows[1].tobytes()
    msg = store.types[IMAGE](
        header=make_header(0, 'f', store), height=2, width=3, encoding='32FC1',
        is_bigendian=1, step=16, data=np.frombuffer(padded, np.uint8).copy(),
    )
    np.testing.assert_array_equal(
        disparity_from_msg(msg), np.array([[1.5, np.nan, 3.0], [0.0, np.nan, 2.25]], np.float32)
    )


def test_a_topic_with_messages_of_several_types_is_refused(tmp_path: Path) -> None:
    from rosbags.rosbag2 import StoragePlugin, Writer

    store = jazzy_typestore()
    path = tmp_path / 'mixed'
    writer = Writer(path, version=8, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    compressed = writer.add_connection('/left', COMPRESSED_IMAGE, typestore=store)
    raw = writer.add_connection('/left', IMAGE, typestore=store)
    jpeg = store.types[COMPRESSED_IMAGE](
        header=make_header(0, 'f', store), format='jpeg', data=np.zeros(3, np.uint8)
    )
    writer.write(compressed, 0, store.serialize_cdr(jpeg, COMPRESSED_IMAGE))
    image = image_to_msg(np.zeros((2, 2), np.uint8), 1, 'f', store)
    writer.write(raw, 1, store.serialize_cdr(image, IMAGE))
    writer.close()
    with InputBag(path) as bag:
        assert bag.topics == {'/left': f'{COMPRESSED_IMAGE} | {IMAGE}'}
        # Before: the type of the last connection (Image) was returned, and the reading
        # then yielded a CompressedImage on the "raw" topic too.
        with pytest.raises(BagError, match=r"left topic '/left' .*holds messages of several "
                                           r'types \(sensor_msgs/msg/CompressedImage \| '):
            bag.require('/left', [IMAGE, COMPRESSED_IMAGE], 'left')


def _three_images(path: Path, storage: str) -> None:
    with OutputBag(path, storage) as bag:
        for index in range(3):
            message = image_to_msg(np.full((4, 5), index, np.uint8), index, 'f')
            bag.write('/a', IMAGE, message, 1000 + index)


@pytest.mark.parametrize('damage', ['mcap record', 'sqlite3 row', 'metadata count'])
def test_messages_lost_from_the_storage_are_a_bag_error(tmp_path: Path, damage: str) -> None:
    path = tmp_path / 'bag'
    _three_images(path, 'sqlite3' if damage == 'sqlite3 row' else 'mcap')
    with InputBag(path) as bag:  # intact, the counts agree
        assert [t for _, _, t, _ in bag.messages(['/a'])] == [1000, 1001, 1002]
    if damage == 'mcap record':
        # The second message record's channel id damaged: the reader skips the record.
        file = path / 'bag.mcap'
        data = bytearray(file.read_bytes())
        at = data.find(struct.pack('<QQ', 1001, 1001))  # its log and publish time
        data[at - 6 : at - 4] = struct.pack('<H', 99)
        file.write_bytes(bytes(data))
    elif damage == 'sqlite3 row':
        with sqlite3.connect(path / 'bag.db3') as db:
            db.execute('UPDATE messages SET topic_id = 99 WHERE timestamp = 1001')
        db.close()
    else:
        metadata = path / 'metadata.yaml'
        metadata.write_text(metadata.read_text().replace('message_count: 3', 'message_count: 4'))
    lists = 4 if damage == 'metadata count' else 3
    found = 3 if damage == 'metadata count' else 2
    with InputBag(path) as bag:
        read = []
        # Before: the messages the storage still held came back, as if that were all.
        with pytest.raises(BagError, match=f'lists {lists} messages on /a .*holds only {found}'):
            for _, _, stamp, _ in bag.messages(['/a']):
                read.append(stamp)
        assert len(read) == found
        # A read from a later time on, or one stopped early, is no full read: no error.
        assert len(list(bag.messages(['/a'], start=1002))) == 1
        assert next(iter(bag.messages(['/a'])))[2] == 1000


def test_an_empty_gt_topic_is_refused(tmp_path: Path) -> None:
    argv = [str(tmp_path / 'in'), '--out', str(tmp_path / 'out'), '--report',
            str(tmp_path / 'report')]
    # Before: '' silently became the default ground_truth/disparity, and a required one.
    with pytest.raises(ConfigError, match="topic ground_truth must be a non-empty name; got ''"):
        options_from_args(build_parser().parse_args([*argv, '--gt-topic', '']))
    options = options_from_args(build_parser().parse_args(argv))
    assert (options.topics.resolve('ground_truth'), options.gt_required) == (
        '/ground_truth/disparity', False
    )

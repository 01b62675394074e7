"""Reading and writing rosbag2 files through ``rosbags``, with one error type for every fault.

Input bags may be MCAP or sqlite3, compressed in any way ``rosbags`` reads (file or message
zstd, MCAP chunk compression). Output bags are written as ROS 2 Jazzy writes them: rosbag2
version 8, Jazzy message definitions and type hashes, MCAP by default.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path
import shutil
import sqlite3
import struct
from typing import Any

from cva_confidence_ros.errors import BagError
from msg_tools.convert import jazzy_typestore

__all__ = ['BAG_VERSION', 'COMPRESSIONS', 'STORAGES', 'InputBag', 'OutputBag', 'remove_bag']

BAG_VERSION = 8
STORAGES = ('mcap', 'sqlite3')
#: rosbag2 compression modes (zstd), as ``ros2 bag record --compression-mode`` names them.
COMPRESSIONS = ('none', 'file', 'message')

# Low-level failures a damaged file raises from inside rosbags' storage plugins.
_STORAGE_FAULTS = (
    OSError,
    EOFError,
    ValueError,
    KeyError,
    IndexError,
    TypeError,
    AssertionError,
    struct.error,
    sqlite3.Error,
)


def _reliable_qos() -> Any:
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )

    # What rclpy offers for a default publisher: reliable, volatile, keep last 10. Written into
    # the bag so that `ros2 bag play` offers the same, which best-effort subscribers accept too.
    never = QosTime(sec=0, nsec=0)
    return Qos(
        history=QosHistory.KEEP_LAST,
        depth=10,
        reliability=QosReliability.RELIABLE,
        durability=QosDurability.VOLATILE,
        deadline=never,
        lifespan=never,
        liveliness=QosLiveliness.AUTOMATIC,
        liveliness_lease_duration=never,
        avoid_ros_namespace_conventions=False,
    )


class InputBag:
    """A rosbag2 opened for reading; use as a context manager.

    Args:
        path: Bag folder (with ``metadata.yaml``) or a single ``.mcap`` / ``.db3`` file.

    Raises:
        BagError: On entering, when the bag does not exist, is not a bag, or cannot be opened.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._reader: Any = None

    def __enter__(self) -> InputBag:
        from rosbags.rosbag2 import Reader, ReaderError

        if not self.path.exists():
            raise BagError(f'bag {self.path} does not exist')
        try:
            reader = Reader(self.path)
            reader.open()
        except FileNotFoundError as err:
            raise BagError(f'{self.path} is not a rosbag2 (no metadata.yaml): {err}') from None
        except (ReaderError, *_STORAGE_FAULTS) as err:
            raise BagError(f'cannot open bag {self.path} (corrupt or truncated?): {err}') from None
        self._reader = reader
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the bag (idempotent)."""
        reader, self._reader = self._reader, None
        if reader is not None and reader.is_open:
            try:
                reader.close()
            except _STORAGE_FAULTS:
                pass  # a damaged file may fail again on close; the error was reported already

    @property
    def reader(self) -> Any:
        if self._reader is None:
            raise BagError(f'bag {self.path} is not open')
        return self._reader

    @property
    def topics(self) -> dict[str, str]:
        """Topic name → message type (``pkg/msg/Type``) of every connection."""
        return {conn.topic: conn.msgtype for conn in self.reader.connections}

    @property
    def message_counts(self) -> dict[str, int]:
        """Topic name → number of messages (as the bag's metadata states)."""
        counts: dict[str, int] = {}
        for conn in self.reader.connections:
            counts[conn.topic] = counts.get(conn.topic, 0) + int(conn.msgcount)
        return counts

    def require(self, topic: str, msgtypes: Sequence[str], what: str) -> str:
        """Check that ``topic`` exists with one of ``msgtypes``; return its type.

        Raises:
            BagError: Topic missing or of another type; the message lists what the bag has.
        """
        topics = self.topics
        if topic not in topics:
            listing = ', '.join(f'{name} [{kind}]' for name, kind in sorted(topics.items()))
            raise BagError(
                f'bag {self.path} has no {what} topic {topic!r}; it has: {listing or "nothing"} '
                f'(set the topic options or --topic-prefix)'
            )
        if topics[topic] not in msgtypes:
            raise BagError(
                f'{what} topic {topic!r} has type {topics[topic]}; expected one of '
                f'{list(msgtypes)}'
            )
        return topics[topic]

    def messages(self, topics: Sequence[str]) -> Iterator[tuple[str, str, int, bytes]]:
        """Raw messages of ``topics`` in bag-time order.

        Yields:
            (topic, message type, bag timestamp in ns, CDR bytes).

        Raises:
            BagError: The storage fails part-way (truncated or corrupt data).
        """
        from rosbags.rosbag2 import ReaderError

        wanted = [conn for conn in self.reader.connections if conn.topic in set(topics)]
        if not wanted:
            return
        count = 0
        iterator = self.reader.messages(connections=wanted)
        while True:
            try:
                item = next(iterator)
            except StopIteration:
                return
            except (ReaderError, *_STORAGE_FAULTS) as err:
                raise BagError(
                    f'bag {self.path} is corrupt or truncated after {count} messages: {err}'
                ) from None
            conn, timestamp, data = item
            count += 1
            yield conn.topic, conn.msgtype, int(timestamp), bytes(data)


def remove_bag(path: str | Path) -> None:
    """Delete an existing output bag; refuse anything that does not look like one.

    Raises:
        BagError: ``path`` exists but is neither a bag folder nor a bag file.
    """
    target = Path(path)
    if not target.exists():
        return
    if target.is_dir() and (target / 'metadata.yaml').exists():
        shutil.rmtree(target)
    elif target.is_file() and target.suffix in ('.mcap', '.db3'):
        target.unlink()
    else:
        raise BagError(f'refusing to overwrite {target}: it is not a rosbag2 folder')


class OutputBag:
    """A rosbag2 written as ROS 2 Jazzy writes it (version 8); use as a context manager.

    Leaving the ``with`` block always finalises the bag (metadata and MCAP summary), also on
    an exception or Ctrl-C, so the messages written so far stay readable.

    Args:
        path: Bag folder to create; must not exist.
        storage: ``mcap`` (default) or ``sqlite3``.
        typestore: ``rosbags`` typestore; the Jazzy one by default.
        compression: ``none`` (default), ``file`` or ``message`` (zstd).

    Raises:
        BagError: Unknown storage or compression, or ``path`` exists already.
    """

    def __init__(
        self,
        path: str | Path,
        storage: str = 'mcap',
        typestore: Any | None = None,
        compression: str = 'none',
    ) -> None:
        if storage not in STORAGES:
            raise BagError(f'storage must be one of {STORAGES}; got {storage!r}')
        if compression not in COMPRESSIONS:
            raise BagError(f'compression must be one of {COMPRESSIONS}; got {compression!r}')
        self.path = Path(path)
        self.storage = storage
        self.compression = compression
        self.typestore = typestore or jazzy_typestore()
        self.counts: dict[str, int] = {}
        self._writer: Any = None
        self._connections: dict[str, Any] = {}
        self._qos = _reliable_qos()

    def __enter__(self) -> OutputBag:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def open(self) -> None:
        """Create the bag folder and its storage file.

        Raises:
            BagError: The folder exists or cannot be created.
        """
        from rosbags.rosbag2 import (
            CompressionFormat,
            CompressionMode,
            StoragePlugin,
            Writer,
            WriterError,
        )

        if self.path.exists():
            raise BagError(f'output bag {self.path} exists already; remove it or pick another')
        plugin = StoragePlugin.MCAP if self.storage == 'mcap' else StoragePlugin.SQLITE3
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            writer = Writer(self.path, version=BAG_VERSION, storage_plugin=plugin)
            if self.compression != 'none':
                writer.set_compression(
                    CompressionMode[self.compression.upper()], CompressionFormat.ZSTD
                )
            writer.open()
        except (WriterError, OSError) as err:
            raise BagError(f'cannot create output bag {self.path}: {err}') from None
        self._writer = writer

    def write(self, topic: str, msgtype: str, message: Any, timestamp_ns: int) -> None:
        """Append one message (a ``rosbags`` message object or CDR bytes)."""
        if self._writer is None:
            raise BagError(f'output bag {self.path} is not open')
        conn = self._connections.get(topic)
        if conn is None:
            conn = self._writer.add_connection(
                topic, msgtype, typestore=self.typestore, offered_qos_profiles=[self._qos]
            )
            self._connections[topic] = conn
        elif conn.msgtype != msgtype:
            raise BagError(f'topic {topic!r} has type {conn.msgtype}; got a {msgtype}')
        data = message if isinstance(message, (bytes, bytearray, memoryview)) else (
            self.typestore.serialize_cdr(message, msgtype)
        )
        self._writer.write(conn, int(timestamp_ns), data)
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def close(self) -> None:
        """Finalise the bag (idempotent)."""
        writer, self._writer = self._writer, None
        if writer is not None:
            writer.close()

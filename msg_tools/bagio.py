"""Reading and writing rosbag2 files through ``rosbags``, with one error type for every fault.

Input bags may be MCAP or sqlite3, compressed in any way ``rosbags`` reads (file or message
zstd, MCAP chunk compression). Output bags are written as ROS 2 Jazzy writes them: rosbag2
version 8, Jazzy message definitions and type hashes, MCAP by default.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
import contextlib
import importlib
import os
from pathlib import Path
import re
import shutil
import sqlite3
import struct
from typing import Any, Final

from cva_confidence_ros.errors import BagError, ConfigError, reason
from msg_tools.convert import jazzy_typestore

_SqliteReadError: type[Exception]
try:
    from apsw import Error as _ApswError
except ImportError:  # rosbags before 0.10 read sqlite3 bags through the standard module
    _SqliteReadError = sqlite3.Error
else:
    _SqliteReadError = _ApswError


def _zstd_error() -> type[Exception]:
    """The error of the zstd module ``rosbags`` decompresses with (file and message
    compression, MCAP chunks): ``compression.zstd`` from Python 3.14, ``backports.zstd``
    before, ``zstandard`` in older ``rosbags``."""
    for module in ('compression.zstd', 'backports.zstd', 'zstandard'):
        try:
            error = importlib.import_module(module).ZstdError
        except (ImportError, AttributeError):
            continue
        if isinstance(error, type) and issubclass(error, Exception):
            return error
    return OSError  # none installed: nothing of the kind can be raised


__all__ = [
    'BAG_VERSION',
    'COMPRESSIONS',
    'STORAGES',
    'TOPIC_MAX_LENGTH',
    'InputBag',
    'OutputBag',
    'check_replaceable',
    'check_topic_name',
    'deserialize',
    'remove_bag',
    'staging_folder',
]

BAG_VERSION: Final = 8
STORAGES = ('mcap', 'sqlite3')
#: rosbag2 compression modes (zstd), as ``ros2 bag record --compression-mode`` names them.
COMPRESSIONS = ('none', 'file', 'message')
#: Longest fully qualified topic name rmw accepts (``RMW_TOPIC_MAX_NAME_LENGTH``).
TOPIC_MAX_LENGTH = 247

# Low-level failures a damaged file raises from inside rosbags' storage plugins: the MCAP
# reader seeks by record lengths read from the file (a garbage length overflows the seek),
# and the sqlite3 reader goes through apsw, whose errors are not sqlite3's.
_STORAGE_FAULTS = (
    OSError,
    EOFError,
    ValueError,
    KeyError,
    IndexError,
    TypeError,
    AssertionError,
    OverflowError,
    MemoryError,
    struct.error,
    sqlite3.Error,
    _SqliteReadError,
    _zstd_error(),  # a damaged zstd frame (compressed file, message or MCAP chunk)
    RuntimeError,  # what lz4 raises for a damaged lz4 MCAP chunk
)
# What the first bytes of a single-file bag hold, per suffix.
_STORAGE_MAGIC = {'.mcap': b'\x89MCAP0\r\n', '.db3': b'SQLite format 3\x00'}
_TOPIC_CHARACTERS = re.compile(r'[A-Za-z0-9_/]*')


def check_topic_name(name: str, what: str = 'topic') -> str:
    """Check a fully qualified topic name against ROS 2's rules.

    The rules of ``rmw_validate_full_topic_name``: it starts with ``/``, holds only ASCII
    letters, digits, ``_`` and ``/``, has no empty part (``//``, a trailing ``/``), no part
    that starts with a digit, and at most :data:`TOPIC_MAX_LENGTH` characters. ``ros2 bag
    play`` cannot advertise a topic that breaks one of them.

    Args:
        name: The absolute topic name, e.g. ``/stereo/left/image_rect``.
        what: What the name is, for the message (``'topic left'``, ``'topic prefix'``).

    Returns:
        ``name``.

    Raises:
        ConfigError: The rule it breaks, and the name.
    """
    problem = ''
    if not name.startswith('/'):
        problem = 'it must start with /'
    elif not _TOPIC_CHARACTERS.fullmatch(name):
        bad = ''.join(sorted({c for c in name if not _TOPIC_CHARACTERS.fullmatch(c)}))
        problem = f'only letters, digits, _ and / are allowed; it has {bad!r}'
    elif '//' in name or name.endswith('/'):
        problem = 'no part of it may be empty (// or a trailing /)'
    elif any(part[:1].isdigit() for part in name.split('/')):
        problem = 'no part of it may start with a digit'
    elif len(name) > TOPIC_MAX_LENGTH:
        problem = f'at most {TOPIC_MAX_LENGTH} characters; it has {len(name)}'
    if problem:
        raise ConfigError(f'{what} must be a valid ROS 2 topic name ({problem}); got {name!r}')
    return name


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
        self._found: set[int] = set()  # connections whose messages the storage was seen to hold

    def __enter__(self) -> InputBag:
        from rosbags.rosbag2 import Reader, ReaderError

        if not self.path.exists():
            raise BagError(f'bag {self.path} does not exist')
        try:
            reader = Reader(self.path)
            reader.open()
        except FileNotFoundError as err:
            raise BagError(_no_metadata(self.path, err)) from None
        except (ReaderError, *_STORAGE_FAULTS) as err:
            # One clause: a YAML parser explains a bad metadata.yaml over several lines.
            raise BagError(
                f'cannot open bag {self.path} (corrupt or truncated?): {reason(err)}'
                f'{_unfinished_mcap(self.path)}'
            ) from None
        for conn in reader.connections:
            count = conn.msgcount
            if isinstance(count, bool) or not isinstance(count, int) or count < 0:
                reader.close()
                raise BagError(
                    f'cannot open bag {self.path}: its metadata gives topic {conn.topic} '
                    f'{count!r} messages; expected a count >= 0 (a damaged or hand-edited '
                    f'metadata.yaml?)'
                )
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
        """Topic name → message type (``pkg/msg/Type``) of every connection.

        A topic recorded with messages of several types (one connection per type) maps to
        them all, joined by `` | ``: no single type, so that no reader takes its messages
        for one type (:meth:`require` refuses it by name).
        """
        types: dict[str, set[str]] = {}
        for conn in self.reader.connections:
            types.setdefault(conn.topic, set()).add(conn.msgtype)
        return {topic: ' | '.join(sorted(kinds)) for topic, kinds in types.items()}

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
        if isinstance(msgtypes, str):  # one type, not its characters (`in` would match a part)
            msgtypes = [msgtypes]
        topics = self.topics
        if topic not in topics:
            listing = ', '.join(f'{name} [{kind}]' for name, kind in sorted(topics.items()))
            raise BagError(
                f'bag {self.path} has no {what} topic {topic!r}; it has: {listing or "nothing"} '
                f'(set the topic options or --topic-prefix)'
            )
        if ' | ' in topics[topic]:
            raise BagError(
                f'{what} topic {topic!r} of bag {self.path} holds messages of several types '
                f'({topics[topic]}); expected all of one type, one of {list(msgtypes)}'
            )
        if topics[topic] not in msgtypes:
            raise BagError(
                f'{what} topic {topic!r} has type {topics[topic]}; expected one of '
                f'{list(msgtypes)}'
            )
        return topics[topic]

    @property
    def time_range(self) -> tuple[int, int]:
        """Bag time (ns) of the first message and just after the last one."""
        return int(self.reader.start_time), int(self.reader.end_time)

    def messages(
        self, topics: Sequence[str], start: int | None = None, stop: int | None = None
    ) -> Iterator[tuple[str, str, int, bytes]]:
        """Raw messages of ``topics`` in bag-time order, from bag time ``start`` (ns) on and
        before ``stop``.

        ``topics`` is a list of topic names; a single name (a ``str``) is one topic, not a
        list of its characters.

        Yields:
            (topic, message type, bag timestamp in ns, CDR bytes).

        Raises:
            BagError: The storage fails part-way (truncated or corrupt data), holds no
                message of a topic that the bag's metadata lists messages of, or, read
                whole, fewer messages of a topic than the metadata lists
                (records lost to damage: raised after the messages it holds).
        """
        from rosbags.rosbag2 import ReaderError

        names = {topics} if isinstance(topics, str) else set(topics)
        wanted = [conn for conn in self.reader.connections if conn.topic in names]
        if not wanted:
            return
        self._check_storage(wanted)
        count = 0
        counts: dict[int, int] = {}  # connection id → messages read
        iterator = self.reader.messages(connections=wanted, start=start, stop=stop)
        while True:
            try:
                item = next(iterator)
            except StopIteration:
                if start is None and stop is None:
                    self._check_counts(wanted, counts)
                return
            except (ReaderError, *_STORAGE_FAULTS) as err:
                raise BagError(
                    f'bag {self.path} is corrupt or truncated after {count} messages: '
                    f'{reason(err)}'
                ) from None
            conn, timestamp, data = item
            count += 1
            counts[conn.id] = counts.get(conn.id, 0) + 1
            yield conn.topic, conn.msgtype, int(timestamp), bytes(data)

    def _check_counts(self, connections: Sequence[Any], counts: dict[int, int]) -> None:
        """Check that a full read found as many messages per connection as the metadata lists.

        The readers skip what they cannot place (a damaged MCAP record header, a message of
        an unknown channel) without an error; only the count tells that messages were lost.
        """
        for conn in connections:
            found = counts.get(conn.id, 0)
            if found < conn.msgcount:
                raise BagError(
                    f'bag {self.path}: its metadata.yaml lists {conn.msgcount} messages on '
                    f'{conn.topic} [{conn.msgtype}], but its storage file holds only {found} '
                    f'of them (corrupt or truncated storage, or metadata.yaml edited or of '
                    f'another bag?)'
                )

    def _check_storage(self, connections: Sequence[Any]) -> None:
        """Check that the storage holds messages of each connection the metadata says has some.

        ``rosbags`` finds a connection's messages by the topic, type, QoS and type hash that
        ``metadata.yaml`` gives it; where they differ from the storage file's (a metadata.yaml
        edited by hand, or copied from another bag) it yields nothing, as for an empty topic.
        A storage fault here is left for the reading itself to report, after the messages
        before it.
        """
        from rosbags.rosbag2 import ReaderError

        for conn in connections:
            if conn.id in self._found or not conn.msgcount:
                continue
            probe = self.reader.messages(connections=[conn])
            try:
                found = next(probe, None)
            except (ReaderError, *_STORAGE_FAULTS):
                continue
            finally:
                probe.close()
            if found is None:
                raise BagError(
                    f'bag {self.path}: its metadata.yaml lists {conn.msgcount} messages on '
                    f'{conn.topic} [{conn.msgtype}], but its storage file holds none of that '
                    f'topic and type (metadata.yaml edited or of another bag, or a recording '
                    f'that failed?)'
                )
            self._found.add(conn.id)


def _no_metadata(path: Path, err: Exception) -> str:
    """Why a folder is no bag, and what to do: a recording that was killed before it wrote
    its metadata.yaml (rosbag2 writes it last) still holds its storage files."""
    text = f'{path} is not a rosbag2 (no metadata.yaml): {reason(err)}'
    try:
        files = sorted(p for p in path.iterdir() if p.suffix in _STORAGE_MAGIC and p.is_file())
    except OSError:
        return text
    if not files:
        return text
    listing = ', '.join(str(p) for p in files[:5]) + (', ...' if len(files) > 5 else '')
    # Split recordings: one file is one part of the recording.
    each = ', each a part of the recording' if len(files) > 1 else ''
    return (
        f'{path} has no metadata.yaml (a recording that was killed?), but holds the storage '
        f'file{"s" if len(files) > 1 else ""} {listing}: give one as the bag (a .mcap or .db3 '
        f'file is read without metadata.yaml{each}), or write the metadata with '
        f'`ros2 bag reindex {path}`'
    )


def _unfinished_mcap(path: Path) -> str:
    """A hint for an MCAP file that starts as one but does not end with its magic: a
    recording that was killed (no summary, no footer), which ``rosbags`` cannot read."""
    magic = _STORAGE_MAGIC['.mcap']
    if path.suffix != '.mcap' or not path.is_file():
        return ''
    try:
        with path.open('rb') as stream:
            head = stream.read(len(magic))
            stream.seek(0, os.SEEK_END)
            size = stream.tell()
            stream.seek(max(size - len(magic), 0))
            tail = stream.read()
    except OSError:
        return ''
    if head != magic or tail == magic:
        return ''
    return (
        f'; the file does not end like an MCAP file (a recording that was killed, or a copy '
        f'cut short): recover its messages with the mcap CLI, `mcap recover {path} -o '
        f'{path.with_name(path.stem + "_recovered.mcap")}`, and replay that'
    )


def deserialize(store: Any, data: bytes, msgtype: str, where: str) -> Any:
    """Deserialise one message's CDR bytes, with a :class:`BagError` for a corrupt one.

    Args:
        store: ``rosbags`` typestore (:func:`msg_tools.convert.jazzy_typestore`).
        data: The message's CDR bytes, as :meth:`InputBag.messages` yields them.
        msgtype: Its message type (``pkg/msg/Type``).
        where: Which message it is, for the error (``'message 3 on /left/image_rect of
            bag robot_bag'``).

    Raises:
        BagError: The bytes are no ``msgtype`` (truncated or corrupt data), or ``msgtype``
            is no type of ``store``; names ``where``.
    """
    from rosbags.serde import SerdeError

    if msgtype not in store.types:
        raise BagError(
            f'{where} cannot be read: its type {msgtype!r} is not a message type of the '
            f'typestore (ROS 2 Jazzy)'
        )
    try:
        return store.deserialize_cdr(data, msgtype)
    except SerdeError as err:
        raise BagError(
            f'{where} cannot be read as a {msgtype} (corrupt or truncated?): {reason(err)}'
        ) from None


def check_replaceable(path: str | Path, what: str = 'output bag') -> bool:
    """Check that ``path`` is nothing or a bag that ``--overwrite`` may replace.

    A bag is a folder with a ``metadata.yaml``, or a single ``.mcap`` / ``.db3`` file that
    starts with its format's magic bytes; a symbolic link is never followed. So is the
    folder a killed writer left (:func:`_unfinished_bag`): only its storage files.

    Returns:
        Whether ``path`` exists (and is a bag).

    Raises:
        BagError: ``path`` exists but is not recognisably a bag.
    """
    target = Path(path)
    if not target.exists() and not target.is_symlink():
        return False
    if target.is_symlink():
        raise BagError(f'refusing to overwrite {target}: it is a symbolic link, not a rosbag2')
    if target.is_dir() and (target / 'metadata.yaml').is_file():
        return True
    if target.is_dir() and _unfinished_bag(target):
        return True
    if target.is_file() and target.suffix in _STORAGE_MAGIC:
        magic = _STORAGE_MAGIC[target.suffix]
        try:
            with target.open('rb') as stream:
                head = stream.read(len(magic))
        except OSError as err:
            raise BagError(f'cannot read the old {what} {target}: {reason(err)}') from None
        if head != magic:
            raise BagError(
                f'refusing to overwrite {target}: it does not start like a '
                f'{target.suffix} bag file (expected {magic!r}; got {head!r})'
            )
        return True
    raise BagError(
        f'refusing to overwrite {target}: it is not a rosbag2 folder '
        f'(with metadata.yaml) or a .mcap/.db3 bag file'
    )


def _unfinished_bag(folder: Path) -> bool:
    """Whether ``folder`` is what a bag writer that was killed (or hit a full disk) left:
    only its storage files (``<folder>.mcap``, ``<folder>_<n>.db3``, ..., starting with
    their format's magic, and sqlite3's journals), no ``metadata.yaml``.

    Refused as "no bag", such a folder made ``--overwrite`` a dead end for the very run that
    had left it.
    """
    name = re.escape(folder.name)
    storage = re.compile(rf'{name}(_[0-9]+)?(\.mcap|\.db3)(-journal|-wal|-shm)?')
    try:
        entries = list(folder.iterdir())
        if not any(re.fullmatch(rf'{name}(_[0-9]+)?(\.mcap|\.db3)', e.name) for e in entries):
            return False  # an empty folder is no bag (one may have made it for anything)
        for entry in entries:
            match = storage.fullmatch(entry.name)
            if match is None or entry.is_symlink() or not entry.is_file():
                return False
            if match.group(3) is None:
                magic = _STORAGE_MAGIC[match.group(2)]
                with entry.open('rb') as stream:
                    if stream.read(len(magic)) != magic:
                        return False
    except OSError:
        return False
    return True


def _delete(target: Path) -> None:
    if target.is_dir() and not target.is_symlink():
        shutil.rmtree(target)
    else:
        target.unlink()


def remove_bag(path: str | Path) -> None:
    """Delete an existing output bag; refuse anything that is not recognisably one
    (see :func:`check_replaceable`).

    Raises:
        BagError: ``path`` exists but is not a bag, or cannot be removed.
    """
    target = Path(path)
    if not check_replaceable(target):
        return
    try:
        _delete(target)
    except OSError as err:
        raise BagError(f'cannot remove the old output bag {target}: {reason(err)}') from None


def staging_folder(path: str | Path) -> Path:
    """The hidden sibling folder a bag that replaces ``path`` is written in first.

    The new bag gets ``path``'s own name inside it, so that its storage file is named as if
    it had been written in place (rosbag2 names the file after the bag's folder).
    """
    target = Path(path)
    return target.parent / f'.{target.name}.new-{os.getpid()}'


class OutputBag:
    """A rosbag2 written as ROS 2 Jazzy writes it (version 8); use as a context manager.

    Leaving the ``with`` block always finalises the bag (metadata and MCAP summary), also on
    an exception or Ctrl-C, so the messages written so far stay readable.

    With ``overwrite`` and an existing bag at ``path``, the new bag is written in a hidden
    sibling folder (:func:`staging_folder`) and replaces the old one when it is closed, only
    if at least one message was written (also after a Ctrl-C, or a fault part-way that the
    caller does not report as ``close(failed=True)``); a run that writes nothing leaves the old
    bag as it was (:attr:`kept_old`), and so does a new bag that cannot be written or finalised
    (a full disk), which is dropped with a :class:`BagError`.

    Args:
        path: Bag folder to create; must not exist unless ``overwrite``.
        storage: ``mcap`` (default) or ``sqlite3``.
        typestore: ``rosbags`` typestore; the Jazzy one by default.
        compression: ``none`` (default), ``file`` or ``message`` (zstd).
        overwrite: Replace an existing bag at ``path`` (see above).
        keep_empty: Keep a bag this object created when nothing was written to it; False
            removes it on :meth:`close` (:attr:`dropped_empty`), so that a run that wrote
            nothing leaves no bag that a retry would have to be told to overwrite.

    A run that fails part-way (an error, not a Ctrl-C) closes with ``close(failed=True)``: then
    a staged bag never replaces the old one, and a new bag that holds nothing is removed.

    Attributes:
        kept_old: After :meth:`close`: an old bag was to be replaced, but nothing was written
            (or the run failed), so it is still there, untouched.
        dropped_empty: After :meth:`close`: the new bag held nothing and ``keep_empty`` was
            off (or the run failed), so it was removed (there is no bag at ``path``).
        replacing: After :meth:`open`: the bag is written aside, to replace an old one.
        lost: A storage fault lost every message written (sqlite3 rolls back its one
            transaction on a full disk); a bag this object created was removed.

    Raises:
        BagError: Unknown storage or compression.
    """

    def __init__(
        self,
        path: str | Path,
        storage: str = 'mcap',
        typestore: Any | None = None,
        compression: str = 'none',
        overwrite: bool = False,
        keep_empty: bool = True,
    ) -> None:
        if storage not in STORAGES:
            raise BagError(f'storage must be one of {STORAGES}; got {storage!r}')
        if compression not in COMPRESSIONS:
            raise BagError(f'compression must be one of {COMPRESSIONS}; got {compression!r}')
        self.path = Path(path)
        self.storage = storage
        self.compression = compression
        self.overwrite = overwrite
        self.typestore = typestore or jazzy_typestore()
        self.counts: dict[str, int] = {}
        self.keep_empty = keep_empty
        self.kept_old = False
        self.dropped_empty = False
        self.replacing = False
        self.lost = False
        self._created = False
        self._writer: Any = None
        self._staging: Path | None = None
        self._connections: dict[str, Any] = {}
        self._qos = _reliable_qos()

    def __enter__(self) -> OutputBag:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def written(self) -> int:
        """Messages written so far."""
        return sum(self.counts.values())

    def open(self) -> None:
        """Create the bag folder and its storage file (in the staging folder when an old bag
        is to be replaced).

        Raises:
            BagError: The folder exists (and ``overwrite`` is off, or it is not a bag), or it
                cannot be created.
        """
        from rosbags.rosbag2 import (
            CompressionFormat,
            CompressionMode,
            StoragePlugin,
            Writer,
            WriterError,
        )

        target = self.path
        if self.path.exists() or self.path.is_symlink():
            if not self.overwrite:
                raise BagError(
                    f'output bag {self.path} exists already; remove it or pick another'
                )
            check_replaceable(self.path)
            staging = staging_folder(self.path)
            if staging.exists():
                remove_bag(staging / self.path.name)  # left by a killed run of this pid
            target = staging / self.path.name
            self._staging = staging
        plugin = StoragePlugin.MCAP if self.storage == 'mcap' else StoragePlugin.SQLITE3
        created = not (target.exists() or target.is_symlink())
        try:
            target.parent.mkdir(parents=True, exist_ok=True)
            writer = Writer(target, version=BAG_VERSION, storage_plugin=plugin)
            if self.compression != 'none':
                writer.set_compression(
                    CompressionMode[self.compression.upper()], CompressionFormat.ZSTD
                )
            writer.open()
        except (WriterError, OSError, sqlite3.Error) as err:
            # The writer makes the bag folder before its storage file: a file it cannot
            # create (a name too long, ...) would leave an empty folder that no later run
            # may write or replace (it is no bag).
            if created:
                with contextlib.suppress(OSError):
                    target.rmdir()  # only if empty: never what another process wrote
            self._discard_staging()
            raise BagError(f'cannot create output bag {self.path}: {err}') from None
        self._writer = writer
        self._created = created and self._staging is None
        self.replacing = self._staging is not None

    def write(self, topic: str, msgtype: str, message: Any, timestamp_ns: int) -> None:
        """Append one message (a ``rosbags`` message object or CDR bytes).

        Raises:
            BagError: The bag is not open, ``msgtype`` is no type of the typestore, the topic
                has another type already, a timestamp outside 0 … 2^63 − 1 ns (rosbag2's
                int64 nanoseconds; MCAP's are unsigned), or the storage fails.
        """
        if self._writer is None:
            raise BagError(f'output bag {self.path} is not open')
        try:
            stamp = int(timestamp_ns)
        except (TypeError, ValueError, OverflowError):
            stamp = -1
        if not 0 <= stamp < 2**63:
            raise BagError(
                f'cannot write a message on {topic} to output bag {self.path}: its timestamp '
                f'must be 0 … 2^63 − 1 ns; got {timestamp_ns!r}'
            )
        conn = self._connections.get(topic)
        if conn is None:
            if msgtype not in self.typestore.types:
                raise BagError(
                    f'cannot write topic {topic} to output bag {self.path}: {msgtype!r} is '
                    f'not a message type of its typestore (ROS 2 Jazzy)'
                )
            conn = self._writer.add_connection(
                topic, msgtype, typestore=self.typestore, offered_qos_profiles=[self._qos]
            )
            self._connections[topic] = conn
        elif conn.msgtype != msgtype:
            raise BagError(f'topic {topic!r} has type {conn.msgtype}; got a {msgtype}')
        data = message if isinstance(message, (bytes, bytearray, memoryview)) else (
            self.typestore.serialize_cdr(message, msgtype)
        )
        try:
            self._writer.write(conn, stamp, data)
        except (OSError, sqlite3.Error) as err:  # a full disk, a file system gone away
            state = ''
            if self._staging is not None:
                # The new bag is damaged (sqlite3 drops what it had not committed): it must
                # not replace the old one, which stays.
                writer, self._writer = self._writer, None
                with contextlib.suppress(OSError, sqlite3.Error):
                    writer.close()
                self._discard_staging()
                self._staging = None
                state = '; the old bag was left as it was'
            elif self._rolled_back():
                # rosbags keeps every sqlite3 message in one transaction until close, which
                # the fault rolled back: closed, the bag's metadata.yaml listed messages its
                # storage does not hold. What holds none of them is no bag to keep.
                writer, self._writer = self._writer, None
                with contextlib.suppress(OSError, sqlite3.Error):
                    getattr(writer, 'abort', writer.close)()
                lost, self.counts = self.written, {}
                state = f'; sqlite3 dropped the {lost} messages written (none was committed)'
                if self._created:
                    self._created = False
                    with contextlib.suppress(OSError):
                        _delete(self.path)
                    state += ', so no bag was left there'
                self.lost = True
            raise BagError(
                f'cannot write to output bag {self.path}: {reason(err)}{state}'
            ) from None
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def _rolled_back(self) -> bool:
        """Whether the sqlite3 storage is out of the transaction that held the messages."""
        conn = getattr(getattr(self._writer, 'storage', None), 'conn', None)
        return (
            self.storage == 'sqlite3' and self.written > 0
            and isinstance(conn, sqlite3.Connection) and not conn.in_transaction
        )

    def close(self, failed: bool = False) -> None:
        """Finalise the bag; put a staged bag in place of the old one if it holds anything,
        else drop it and keep the old one (idempotent).

        Args:
            failed: The run that wrote the bag failed part-way: a staged bag is dropped and
                the old one kept (:attr:`kept_old`), as if nothing had been written, and a
                new bag that holds nothing is removed (:attr:`dropped_empty`) whatever
                ``keep_empty`` says; a new bag that holds messages stays, readable.

        Raises:
            BagError: The bag cannot be finalised (a full disk: a staged bag is dropped and
                the old one kept), or the old bag cannot be swapped for the new one (the new
                one is left in the staging folder, and the message says where).
        """
        writer, self._writer = self._writer, None
        if writer is not None:
            try:
                writer.close()
            except (OSError, sqlite3.Error) as err:
                staging, self._staging = self._staging, None
                state = 'it may not be readable'
                if staging is not None:
                    self._discard_staging(staging)
                    state = 'the old bag was left as it was'
                raise BagError(
                    f'cannot finish output bag {self.path}: {reason(err)}; {state}'
                ) from None
        staging, self._staging = self._staging, None
        if staging is None:
            if self._created and self.written == 0 and (failed or not self.keep_empty):
                self._created = False
                remove_bag(self.path)
                self.dropped_empty = True
            return
        if self.written == 0 or failed:
            self.kept_old = True
            self._discard_staging(staging)
            return
        old = staging / f'old-{self.path.name}'
        try:
            self.path.rename(old)
        except OSError as err:
            raise BagError(
                f'cannot replace the old output bag {self.path}: {reason(err)}; the new one is '
                f'{staging / self.path.name}'
            ) from None
        try:
            (staging / self.path.name).rename(self.path)
        except OSError as err:
            old.rename(self.path)  # the old bag back where it was
            raise BagError(
                f'cannot move the new output bag into {self.path}: {reason(err)}; the old bag '
                f'is there as before, the new one is {staging / self.path.name}'
            ) from None
        self._discard_staging(staging)

    def _discard_staging(self, staging: Path | None = None) -> None:
        """Delete the staging folder (it holds only bags this object wrote or moved there)."""
        staging = staging or self._staging
        if staging is not None and staging.is_dir():
            shutil.rmtree(staging, ignore_errors=True)

"""Check output paths before a long job starts, not after it has computed everything.

A command that evaluates or trains for an hour and then finds that ``--json`` names a folder
loses the hour. Permission bits do not tell everything (a read-only mount, ``/proc``, a full
quota, or a root user for whom ``os.access`` always says yes), so the checks try: they make
the missing folders and write and delete a probe file there. Only those folders are left
behind, which the job would make anyway.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
import contextlib
import os
from pathlib import Path
import tempfile
import threading
from typing import BinaryIO, cast

from cva_confidence_ros.errors import ConfigError, DataError, reason

__all__ = [
    'check_output_dir',
    'check_output_file',
    'lock_folder',
    'naming',
    'temporary_sibling',
    'torch_save_atomic',
    'write_atomic',
    'write_text_atomic',
]


def _unusable(option: str, path: Path, error: OSError) -> ConfigError:
    """The error for a path that cannot even be looked at (a name too long, no search
    permission on a folder above it)."""
    reason = error.strerror or type(error).__name__
    return ConfigError(f'{option} {path}: cannot use this path ({reason})')


def _probe(folder: Path, option: str, path: Path) -> None:
    """Make ``folder`` (and its parents) and write a probe file in it."""
    try:
        for candidate in (folder, *folder.parents):
            if candidate.exists():
                if not candidate.is_dir():
                    raise ConfigError(f'{option} {path}: {candidate} is a file, not a folder')
                break
    except OSError as error:
        raise _unusable(option, path, error) from None
    try:
        folder.mkdir(parents=True, exist_ok=True)
        # A byte written, not only a file made: a full disk or quota still makes empty files.
        with tempfile.TemporaryFile(dir=folder, prefix='.write-probe-') as probe:
            probe.write(b'\0')
            probe.flush()
    except OSError as error:
        reason = error.strerror or type(error).__name__
        raise ConfigError(f'{option} {path}: cannot write in {folder} ({reason})') from None


def check_output_file(path: str | os.PathLike[str], option: str) -> Path:
    """Refuse an output file path that is a folder or cannot be written.

    Args:
        path: The file the job will write (its folders may not exist yet; they are made).
        option: The command-line option that named it, for the message (e.g. ``'--json'``).

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        ConfigError: ``path`` is a folder, lies under a file, sits where one cannot write, or
            cannot be looked at (a name too long, a folder above it without search permission).
    """
    path = Path(path)
    try:
        if path.is_dir():
            raise ConfigError(f'{option} {path} is a folder; expected a file path')
        if path.exists() and not os.access(path, os.W_OK):
            raise ConfigError(f'{option} {path}: the file exists and is not writable')
    except OSError as error:
        raise _unusable(option, path, error) from None
    _probe(path.parent, option, path)
    return path


def check_output_dir(path: str | os.PathLike[str], option: str) -> Path:
    """Refuse an output folder path that is a file or cannot be written; make it otherwise.

    Args:
        path: The folder the job will write into (it may not exist yet; it is made).
        option: The command-line option that named it, for the message (e.g. ``'--out'``).

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        ConfigError: ``path`` is empty (an unset variable, not the current folder), is a
            file, lies under a file, sits where one cannot write, or cannot be looked at (a
            name too long, a folder above it without search permission).
    """
    if os.fspath(path) == '':
        # Path('') is '.': outputs would land among whatever the current folder holds.
        raise ConfigError(f"{option} is empty; give a folder ('.' for the current one)")
    path = Path(path)
    try:
        if path.exists() and not path.is_dir():
            raise ConfigError(f'{option} {path} is a file; expected a folder')
    except OSError as error:
        raise _unusable(option, path, error) from None
    _probe(path, option, path)
    return path


def write_text_atomic(path: str | os.PathLike[str], text: str, what: str = '') -> Path:
    """Write ``text`` (UTF-8) beside ``path``, sync it to the disk and move it in place.

    Written directly, a full disk or a crash half-way left a truncated file over the one of
    an earlier run; synced only after the rename, a crash soon after it can leave an empty
    file (ext4, XFS with delayed allocation), the old one gone.

    Args:
        path: Output file; parent folders are created.
        text: The whole content.
        what: Words before the path in the error message (``'records '``).

    Returns:
        The path written.

    Raises:
        DataError: The file cannot be written; an older file at ``path`` is left as it was.
    """
    out = Path(path)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(out, lambda handle: handle.write(text.encode('utf-8')))
    except OSError as exc:
        state = '; the file there was left as it was' if out.exists() else ''
        raise DataError(f'cannot write {what}{out}: {reason(exc)}{state}') from None
    return out


def write_atomic(path: Path, write: Callable[[BinaryIO], object]) -> None:
    """``write(handle)`` into a temporary file beside ``path``, sync it to the disk, move it
    onto ``path`` and sync the folder (see :func:`write_text_atomic`).

    Raises:
        BaseException: Whatever ``write`` or the file system raised, after removing the
            partial file; a file at ``path`` is left as it was.
    """
    tmp = temporary_sibling(path)
    try:
        with open(tmp, 'wb') as handle:
            write(handle)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        raise
    _sync_folder(path.parent)


def torch_save_atomic(path: Path, obj: object) -> None:
    """``torch.save(obj)`` through :func:`write_atomic` (a temporary file beside ``path``,
    synced, moved in place), raising the file system's own error on a failed write.

    torch's writer, given a path, reports a full disk as ``RuntimeError: [enforce fail at
    inline_container.cc:…] unexpected pos …`` and a missing folder as a RuntimeError too; here
    it writes into a file opened by Python, whose OSError is kept and raised instead.

    Raises:
        OSError: The write failed (ENOSPC 'No space left on device', EFBIG, EIO); a file at
            ``path`` is left as it was and no temporary file is left behind.
        RuntimeError: torch's writer failed for another reason.
    """
    import torch  # not at the top: most users of this module need no torch

    failed: list[OSError] = []

    def save(handle: BinaryIO) -> None:
        torch.save(obj, cast('BinaryIO', _KeptErrors(handle, failed)))

    try:
        write_atomic(path, save)
    except RuntimeError as exc:
        if failed:
            raise failed[0] from exc
        raise


class _KeptErrors:
    """A binary file whose write errors are kept in ``failed`` before they are raised:
    torch's writer swallows them and raises its 'unexpected pos' instead."""

    def __init__(self, handle: BinaryIO, failed: list[OSError]) -> None:
        self.handle = handle
        self.failed = failed

    def write(self, data: bytes) -> int:
        try:
            return self.handle.write(data)
        except OSError as exc:
            self.failed.append(exc)
            raise

    def flush(self) -> None:
        self.handle.flush()


@contextlib.contextmanager
def naming(path: Path) -> Iterator[None]:
    """Meanwhile an OSError that does not name ``path`` is raised again naming it (of the same
    errno, hence class): a write that fails half-way (a full disk) said only '[Errno 28] No
    space left on device', or named the temporary file beside ``path``."""
    try:
        yield
    except OSError as exc:
        if str(path) in str(exc):
            raise
        if exc.errno is None:
            raise OSError(f'cannot write {path}: {exc}') from exc
        raise OSError(exc.errno, exc.strerror, str(path)) from exc


def lock_folder(folder: Path, shared: bool = False) -> int | None:
    """Hold ``folder`` for this process: a non-blocking ``flock`` on the folder itself,
    exclusive (or ``shared``: to probe whether another holds it), so no lock file is left
    behind and a killed process holds nothing. Two runs into one output folder at once
    otherwise mixed (or deleted) each other's files without a word.

    Returns:
        The descriptor holding the lock (close it to release); None where nothing can be
        held: the folder cannot be opened, a file system without locks, not POSIX.

    Raises:
        BlockingIOError: Another process holds the folder.
    """
    try:
        import fcntl
    except ImportError:  # Windows
        return None
    try:
        handle = os.open(folder, os.O_RDONLY)
    except OSError:
        return None
    try:
        fcntl.flock(handle, (fcntl.LOCK_SH if shared else fcntl.LOCK_EX) | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(handle)
        raise
    except OSError:  # no locks on this file system (some network mounts)
        os.close(handle)
        return None
    return handle


def temporary_sibling(path: Path) -> Path:
    """A name beside ``path`` to write it under before the rename, of this process and thread:
    one fixed ``path.tmp`` was shared by two writers of the same file (two runs into one
    folder), one renaming the other's half-written file or failing on its vanished one."""
    return path.with_name(f'{path.name}.{os.getpid()}-{threading.get_ident()}.tmp')


def _sync_folder(folder: Path) -> None:
    """Put a rename in ``folder`` on the disk, where the system can (not on Windows)."""
    try:
        handle = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        with contextlib.suppress(OSError):  # the file is in place; only durability is left
            os.fsync(handle)
    finally:
        os.close(handle)

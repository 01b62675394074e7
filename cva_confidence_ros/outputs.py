"""Check output paths before a long job starts, not after it has computed everything.

A command that evaluates or trains for an hour and then finds that ``--json`` names a folder
loses the hour. These checks create nothing; they only refuse paths that cannot work.
"""

from __future__ import annotations

import os
from pathlib import Path

from cva_confidence_ros.errors import ConfigError

__all__ = ['check_output_dir', 'check_output_file']


def _nearest_existing(path: Path) -> Path:
    for candidate in (path, *path.parents):
        if candidate.exists():
            return candidate
    return Path.cwd()


def _check_creatable(path: Path, option: str) -> None:
    """The parts of ``path`` that do not exist yet can be made under its nearest existing one."""
    base = _nearest_existing(path)
    if base != path and not base.is_dir():
        raise ConfigError(f'{option} {path}: {base} is a file, not a folder')
    if base.is_dir() and not os.access(base, os.W_OK | os.X_OK):
        raise ConfigError(f'{option} {path}: cannot write in {base} (permission denied)')


def check_output_file(path: str | os.PathLike[str], option: str) -> Path:
    """Refuse an output file path that is a folder or cannot be created.

    Args:
        path: The file the job will write (its folders may not exist yet).
        option: The command-line option that named it, for the message (e.g. ``'--json'``).

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        ConfigError: ``path`` is a folder, lies under a file, or sits where one cannot write.
    """
    path = Path(path)
    if path.is_dir():
        raise ConfigError(f'{option} {path} is a folder; expected a file path')
    if path.exists() and not os.access(path, os.W_OK):
        raise ConfigError(f'{option} {path}: the file exists and is not writable')
    _check_creatable(path, option)
    return path


def check_output_dir(path: str | os.PathLike[str], option: str) -> Path:
    """Refuse an output folder path that is a file or cannot be created.

    Args:
        path: The folder the job will write into (it may not exist yet).
        option: The command-line option that named it, for the message (e.g. ``'--out'``).

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        ConfigError: ``path`` is a file, lies under a file, or sits where one cannot write.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise ConfigError(f'{option} {path} is a file; expected a folder')
    _check_creatable(path, option)
    return path

"""Keep large freed blocks in the process instead of handing them back to the kernel every frame.

A frame allocates arrays of tens to hundreds of megabytes (cost volumes, network activations)
and frees them again. glibc's malloc serves blocks above its mmap threshold with fresh mappings
and returns them on ``free``, so every frame pays page faults on all of that memory again:
at 640×480 that made CVA-Net-Fast's confidence stage 2.5× slower on this project's 2-core CPU
(≈ 400 ms against ≈ 160 ms), CVA-Net-Lite's 1.7× and the matchers up to 6× when another
allocator (ONNX Runtime's) shifted glibc's dynamic threshold. Raising the mmap and trim
thresholds once at start-up keeps those blocks on the heap for the next frame; the resident
size then stays at the peak of a frame, which a long-running node reaches anyway.

Only the command-line programs call :func:`keep_freed_memory` (the node, the bag replay, the
evaluation, training and demo tools, ``cva-benchmark --suite fast``); importing the library
changes nothing. ``CVA_MALLOC_TUNING=0`` in the environment turns it off.

:func:`available_memory` is what a frame may still allocate here (the pipeline refuses a frame
whose arrays cannot fit, before allocating them); ``CVA_MEMORY_CHECK=0`` turns that check off.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import os
from pathlib import Path
import sys

__all__ = [
    'CHECK_SWITCH',
    'ENV_SWITCH',
    'available_memory',
    'keep_freed_memory',
    'memory_left',
    'shortfall',
    'size_text',
]

#: Environment variable that turns the tuning off when set to ``0``.
ENV_SWITCH = 'CVA_MALLOC_TUNING'
#: Environment variable that turns the pipeline's memory check off when set to ``0``.
CHECK_SWITCH = 'CVA_MEMORY_CHECK'
# mallopt parameters of glibc's <malloc.h>
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_THRESHOLD = 1 << 30  # 1 GiB: no frame allocates a single block that large
# Needs below this are not checked against the memory left (no read of /proc on small frames,
# where nothing is at stake).
_CHECKED_FROM = 256 * 2**20
#: Where the cgroup file systems are mounted (v2 unified, or v1's memory controller below it).
_CGROUP = '/sys/fs/cgroup'
#: This process's cgroups: ``0::/path`` (v2), ``N:memory:/path`` (v1), relative to the root.
_PROC_CGROUP = Path('/proc/self/cgroup')

_applied: bool | None = None


def keep_freed_memory() -> bool:
    """Raise glibc's mmap and trim thresholds (once per process; later calls are no-ops).

    Returns:
        Whether the thresholds are set: False off glibc (macOS, musl), when ``mallopt``
        refuses, or when ``CVA_MALLOC_TUNING=0``.
    """
    global _applied
    if _applied is not None:
        return _applied
    _applied = False
    if os.environ.get(ENV_SWITCH, '1') == '0' or not sys.platform.startswith('linux'):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library('c') or 'libc.so.6')
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    _applied = bool(mallopt(_M_MMAP_THRESHOLD, _THRESHOLD)) and bool(
        mallopt(_M_TRIM_THRESHOLD, _THRESHOLD)
    )
    return _applied


def _read_int(path: str, key: str = '') -> int | None:
    """The integer in the file at ``path`` (or on its line ``key: N kB``, in bytes); None when
    it cannot be read or holds none (cgroup v2's ``max``)."""
    try:
        with open(path, encoding='ascii') as stream:
            if not key:
                return int(stream.read().strip())
            for line in stream:
                name, _, value = line.partition(':')
                if name == key:
                    parts = value.split()
                    return int(parts[0]) * (1024 if parts[1:] == ['kB'] else 1)
    except (OSError, ValueError, IndexError):
        return None
    return None


def size_text(count: float) -> str:
    """Bytes as GB (MB below 0.1 GB)."""
    return f'{count / 1e9:.1f} GB' if count >= 1e8 else f'{count / 1e6:.1f} MB'


def _read_number(path: Path) -> int | None:
    """The integer in a cgroup file; None where it is absent, ``max`` or unreadable."""
    try:
        text = path.read_text().strip()
    except OSError:
        return None
    return int(text) if text.isdecimal() else None


def _stat_value(path: Path, keys: tuple[str, ...]) -> int:
    """The sum of ``keys``' values in a cgroup ``memory.stat`` (0 for those absent)."""
    total = 0
    with contextlib.suppress(OSError, ValueError):
        for line in path.read_text().splitlines():
            name, _, value = line.partition(' ')
            if name in keys:
                total += int(value)
    return total


def _cgroup_left(root: Path) -> tuple[int, str] | None:
    """What the tightest cgroup memory limit over this process leaves: limit − usage + the
    page cache (active and inactive files, which the kernel reclaims before the limit binds;
    tmpfs files it cannot), of its own group and of every group above it; None where no limit
    is set. A Slurm job's or a systemd slice's limit is set on a parent whose child groups,
    the process's among them, read ``max``: only the own group and the root were read, and
    such a limit was missed; a container that had read its limit in bag files refused every
    large frame ("0.11 GB available" of a 4 GB limit) while its page cache was counted used."""
    relative = {'v2': '', 'v1': ''}
    with contextlib.suppress(OSError):
        for line in _PROC_CGROUP.read_text().splitlines():
            number, _, rest = line.partition(':')
            controllers, _, path = rest.partition(':')
            if number == '0' and not controllers:
                relative['v2'] = path
            elif 'memory' in controllers.split(','):
                relative['v1'] = path
    layouts = (
        ('memory.max', 'memory.current', ('active_file', 'inactive_file'), root,
         relative['v2']),
        ('memory.limit_in_bytes', 'memory.usage_in_bytes',
         ('total_active_file', 'total_inactive_file'), root / 'memory', relative['v1']),
    )
    found: list[tuple[int, str]] = []
    for limit_name, usage_name, cache, top, path in layouts:
        parts = Path(path.strip().lstrip('/')).parts
        # The own group up to the root (in a container, the own path may not exist below a
        # root that already is the container's group: those folders read nothing).
        for depth in range(len(parts), -1, -1):
            folder = top.joinpath(*parts[:depth])
            limit = _read_number(folder / limit_name)
            usage = _read_number(folder / usage_name)
            # v1 writes "no limit" as a number near 2**63.
            if limit is None or usage is None or limit >= 1 << 60:
                continue
            left = limit - usage + _stat_value(folder / 'memory.stat', cache)
            found.append(
                (max(0, min(left, limit)), f'cgroup limit {size_text(limit)} in {folder}')
            )
    return min(found) if found else None


def memory_left(cgroup_root: Path | None = None) -> tuple[int | None, str]:
    """(bytes, where from) of the memory this process may still take: the smaller of
    MemAvailable in /proc/meminfo and what a cgroup memory limit leaves (a container's or a
    job's; ``cgroup_root``: where the cgroup file systems are mounted); ``(None, '')`` where
    neither is known (not Linux)."""
    found: list[tuple[int, str]] = []
    free = _read_int('/proc/meminfo', 'MemAvailable')
    if free is not None:
        found.append((free, 'MemAvailable in /proc/meminfo'))
    limited = _cgroup_left(Path(_CGROUP) if cgroup_root is None else cgroup_root)
    if limited is not None:
        found.append(limited)
    return min(found) if found else (None, '')


def available_memory() -> int | None:
    """Bytes this process can still hold in physical memory: the kernel's ``MemAvailable``,
    within what the cgroup's ``memory.max`` (a container's limit) leaves, its page cache
    counted as free, plus the process's own resident memory (the freed blocks
    :func:`keep_freed_memory` keeps, SGM's work arrays: a frame reuses them). Generous on
    purpose, so that what exceeds it surely does not fit: the process would swap or be killed
    by the kernel's OOM killer (no exception, nothing logged).

    Returns:
        None off Linux, when ``/proc`` cannot be read, or with ``CVA_MEMORY_CHECK=0``.
    """
    if os.environ.get(CHECK_SWITCH, '1') == '0':
        return None
    left, _ = memory_left()
    own = _read_int('/proc/self/status', 'VmRSS')
    if left is None or own is None:
        return None
    return left + own


def shortfall(need: int) -> int | None:
    """The bytes available (:func:`available_memory`) when ``need`` bytes exceed them, else
    None (also for needs under 256 MiB, which are not checked)."""
    if need <= _CHECKED_FROM:
        return None
    available = available_memory()
    return available if available is not None and need > available else None

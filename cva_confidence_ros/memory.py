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

import ctypes
import ctypes.util
import os
import sys

__all__ = ['CHECK_SWITCH', 'ENV_SWITCH', 'available_memory', 'keep_freed_memory', 'shortfall']

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
#: The cgroup v2 files of this process's group (a container's own group).
_CGROUP = '/sys/fs/cgroup'

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


def _page_cache(path: str) -> int:
    """Bytes of page cache (``active_file`` + ``inactive_file``) in a cgroup ``memory.stat``
    (0 where it cannot be read); tmpfs files (``shmem``, in ``file`` too) are not reclaimed."""
    total = 0
    try:
        with open(path, encoding='ascii') as stream:
            for line in stream:
                name, _, value = line.partition(' ')
                if name in ('active_file', 'inactive_file'):
                    total += int(value)
    except (OSError, ValueError):
        return 0
    return total


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
    free = _read_int('/proc/meminfo', 'MemAvailable')
    own = _read_int('/proc/self/status', 'VmRSS')
    if free is None or own is None:
        return None
    limit = _read_int(f'{_CGROUP}/memory.max')
    used = _read_int(f'{_CGROUP}/memory.current')
    if limit is not None and used is not None:
        # memory.current counts the page cache (the bags read, the files written), which the
        # kernel reclaims before the limit is reached: a container that had read its limit in
        # files refused every large frame ("0.11 GB available" of a 4 GB limit).
        used -= _page_cache(f'{_CGROUP}/memory.stat')
        free = min(free, max(0, limit - used))
    return free + own


def shortfall(need: int) -> int | None:
    """The bytes available (:func:`available_memory`) when ``need`` bytes exceed them, else
    None (also for needs under 256 MiB, which are not checked)."""
    if need <= _CHECKED_FROM:
        return None
    available = available_memory()
    return available if available is not None and need > available else None

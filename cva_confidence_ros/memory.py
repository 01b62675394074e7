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
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys

__all__ = ['ENV_SWITCH', 'keep_freed_memory']

#: Environment variable that turns the tuning off when set to ``0``.
ENV_SWITCH = 'CVA_MALLOC_TUNING'
# mallopt parameters of glibc's <malloc.h>
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_THRESHOLD = 1 << 30  # 1 GiB: no frame allocates a single block that large

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

"""The allocator tuning of the command-line programs: a frame's big blocks stay on the heap."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

# A frame-sized array (≈ 80 MB, a 640×480×64 cost volume) made and freed twice; glibc's
# mallinfo2 says whether it lived in its own mapping (hblkhd: handed back to the kernel on
# free, fresh zeroed pages next frame) or on the heap (kept for the next frame).
_SCRIPT = """
import ctypes
import numpy as np
from cva_confidence_ros.memory import keep_freed_memory

class MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in (
        'arena', 'ordblks', 'smblks', 'hblks', 'hblkhd', 'usmblks', 'fsmblks', 'uordblks',
        'fordblks', 'keepcost')]

libc = ctypes.CDLL('libc.so.6')
libc.mallinfo2.restype = MallInfo2
applied = keep_freed_memory()
assert keep_freed_memory() is applied  # once per process
mapped = []
for _ in range(2):
    volume = np.ones((64, 480, 640), np.float32)
    mapped.append(libc.mallinfo2().hblkhd)
    del volume
kept = libc.mallinfo2().fordblks  # free bytes the heap holds on to after the frame
print(int(applied), max(mapped), kept)
"""
FRAME = 64 * 480 * 640 * 4


def _run(env: dict[str, str]) -> tuple[bool, int, int]:
    out = subprocess.run(
        [sys.executable, '-c', _SCRIPT], env={**os.environ, **env}, check=True,
        capture_output=True, text=True,
    ).stdout.split()
    return bool(int(out[0])), int(out[1]), int(out[2])


def _has_mallinfo2() -> bool:
    import ctypes

    try:
        return hasattr(ctypes.CDLL('libc.so.6'), 'mallinfo2')
    except OSError:
        return False


@pytest.mark.skipif(not _has_mallinfo2(), reason='needs glibc ≥ 2.33 (mallinfo2)')
def test_a_frame_stays_on_the_heap_for_the_next() -> None:
    applied, mapped, kept = _run({})
    assert applied
    assert mapped < FRAME // 10, f'{mapped} bytes in own mappings'
    assert kept >= FRAME, f'the heap kept only {kept} bytes of an {FRAME}-byte frame'
    applied, mapped, kept = _run({'CVA_MALLOC_TUNING': '0'})
    assert not applied
    assert mapped >= FRAME, 'without the tuning glibc maps the frame on its own'

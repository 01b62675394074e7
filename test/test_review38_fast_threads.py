"""Review 38: ``cva-benchmark --suite fast --threads N`` on a first run.

The thread limit set ``NUMBA_NUM_THREADS`` in the environment inside its block; numba reads it
again at every compilation, and on a first run (kernels not yet in numba's cache) the first
kernel compiled in the block raised "Cannot set NUMBA_NUM_THREADS to a different value once
the threads have been launched". The whole test suite hid it: earlier tests had compiled and
cached the kernels.
"""

from __future__ import annotations

import os
from pathlib import Path
import subprocess
import sys

import numba

SCRIPT = """
import numba
import numpy as np

from cva_confidence_ros.fast_benchmark import _thread_limit

numba.set_num_threads(numba.get_num_threads())  # the pool is launched, as after any frame
with _thread_limit(1):
    @numba.njit(parallel=True)
    def total(values):
        out = 0.0
        for i in numba.prange(values.size):
            out += values[i]
        return out

    assert total(np.ones(64)) == 64.0
    assert numba.get_num_threads() == 1
assert total(np.ones(8)) == 8.0  # after the block too
print('ok')
"""


def test_kernels_compiled_inside_the_thread_limit(tmp_path: Path) -> None:
    env = {**os.environ, 'NUMBA_CACHE_DIR': str(tmp_path)}
    if int(numba.config.NUMBA_NUM_THREADS) < 2:  # type: ignore[attr-defined]
        env['NUMBA_NUM_THREADS'] = '2'  # a pool wider than the limit, as on any 2-core host
    done = subprocess.run([sys.executable, '-c', SCRIPT], env=env, capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == 'ok'

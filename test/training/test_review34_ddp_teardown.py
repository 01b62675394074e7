"""``cva-train`` under ``torchrun`` ends its process group for good, gloo's threads included.

A run of two processes aborted now and then after writing every file (SIGABRT, ``terminate
called without an active exception``): a gloo worker thread let go of the last all_reduce's
tensors only after the interpreter had begun to shut down. Ending the group joins those
threads, but only a group that nothing holds any more ends: DDP's reducer and the defaults of
``torch.distributed.nn`` (bound when DDP imports it) held it. The race is rare; the threads
left behind are not, and they are what this test looks at.
"""

from __future__ import annotations

import os
import subprocess
import sys

from train_test_utils import TINY

# Runs cva-train's main in each process, then writes the threads the process still has to a
# file of its own (torchrun runs python -u: lines of two processes on one pipe can interleave).
_SCRIPT = """
import os, sys
from cva_confidence_ros.training.cli import main

code = main(sys.argv[1:])
names = sorted(open(f'/proc/self/task/{tid}/comm').read().strip()
               for tid in os.listdir('/proc/self/task'))
rank = os.environ['RANK']
with open(os.path.join(os.environ['THREADS_OUT'], f'rank{rank}.txt'), 'w') as out:
    out.write(f'rank {rank} exit {code} threads {names}')
"""


def test_gloo_threads_end_with_the_run(tmp_path):
    script = tmp_path / 'run_and_list_threads.py'
    script.write_text(_SCRIPT)
    out = tmp_path / 'run'
    command = [
        sys.executable, '-m', 'torch.distributed.run', '--standalone', '--nproc-per-node', '2',
        str(script), *TINY, '--samples-per-epoch', '64', '--epochs', '1', '--epochs-low-lr', '0',
        '--out', str(out), '--weights-out', str(out / 'w.pt'),
    ]  # fmt: skip
    env = {**os.environ, 'OMP_NUM_THREADS': '1', 'THREADS_OUT': str(tmp_path)}
    done = subprocess.run(command, capture_output=True, text=True, timeout=300, env=env)
    assert done.returncode == 0, done.stdout + done.stderr
    lines = [(tmp_path / f'rank{rank}.txt').read_text() for rank in (0, 1)]
    assert [line.split(' threads ')[0] for line in lines] == ['rank 0 exit 0', 'rank 1 exit 0']
    for line in lines:
        # While the group lives: gloo_tcp_loop and two pt_gloo_runloop threads.
        assert 'gloo' not in line, line
    assert (out / 'w.pt').is_file()

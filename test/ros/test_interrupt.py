"""Ctrl-C at any point of a node's life: noted, never raised, and the node always stops.

Each case runs :func:`cva_confidence_ros.node.run_entry` in a process of its own on a small
module written here, which sends itself SIGINT at the moment under test, the way a terminal or
``cva-bag-replay`` stopping its node does.
"""

from __future__ import annotations

import os
from pathlib import Path
import subprocess
import sys

from node_test_utils import spare_domain_id
import pytest

import cva_confidence_ros

pytestmark = pytest.mark.timeout(120)

ROOT = Path(cva_confidence_ros.__file__).resolve().parents[1]

# Library code that swallows everything (a bare ``except:``) while the signal comes in. With
# Python's own handler the KeyboardInterrupt vanished there and the node came up and spun on.
SWALLOWING_IMPORT = """
import os, signal, time
try:
    os.kill(os.getpid(), signal.SIGINT)
    time.sleep(0.3)
except BaseException:
    pass
print('IMPORTED', flush=True)

def run(argv):
    print('RUN', flush=True)
    return 0
"""

# The signal while the node is built, after rclpy.init: the start is interrupted (130).
SIGNAL_WHILE_BUILT = """
import os, signal, time
from rclpy.node import Node
from cva_confidence_ros.ros.common import run_node

def build():
    os.kill(os.getpid(), signal.SIGINT)
    time.sleep(0.3)
    print('BUILT', flush=True)
    return Node('interrupt_test_built')

def run(argv):
    return run_node(build, 'interrupt_test_built', argv)
"""

# The signal once the node is up (from its own timer): a clean stop (0) through rclpy's handler.
SIGNAL_WHILE_SPINNING = """
import os, signal
from rclpy.node import Node
from cva_confidence_ros.ros.common import run_node

def build():
    node = Node('interrupt_test_spinning')
    node.create_timer(0.2, lambda: os.kill(os.getpid(), signal.SIGINT))
    return node

def run(argv):
    return run_node(build, 'interrupt_test_spinning', argv)
"""

SCRIPT = """
import signal, sys
from cva_confidence_ros.node import run_entry
code = run_entry(sys.argv[1], [sys.argv[0]])
# run_entry puts Python's own handler back.
print('HANDLER', signal.getsignal(signal.SIGINT) is signal.default_int_handler, flush=True)
sys.exit(code)
"""


def _run_entry(tmp_path: Path, source: str) -> tuple[int, str]:
    (tmp_path / 'entry_under_test.py').write_text(source)
    env = dict(
        os.environ,
        ROS_DOMAIN_ID=str(spare_domain_id()),
        ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
        PYTHONPATH=os.pathsep.join(
            p for p in (str(tmp_path), str(ROOT), os.environ.get('PYTHONPATH', '')) if p
        ),
    )
    done = subprocess.run(
        [sys.executable, '-c', SCRIPT, 'entry_under_test'],
        env=env, capture_output=True, text=True, timeout=90,
    )
    return done.returncode, done.stdout + done.stderr


def test_a_ctrl_c_swallowed_during_the_imports_still_stops_the_start(tmp_path: Path) -> None:
    code, output = _run_entry(tmp_path, SWALLOWING_IMPORT)
    assert code == 130, output
    assert 'IMPORTED' in output, 'the imports were cut short'
    assert 'RUN' not in output.replace('IMPORTED', ''), 'the program went on after the Ctrl-C'
    assert 'HANDLER True' in output
    assert 'Traceback' not in output and 'KeyboardInterrupt' not in output, output


def test_a_ctrl_c_while_the_node_is_built_interrupts_the_start(tmp_path: Path) -> None:
    code, output = _run_entry(tmp_path, SIGNAL_WHILE_BUILT)
    assert code == 130, output
    # The constructor was not interrupted half-way: no exception raised inside it.
    assert 'BUILT' in output
    assert 'ready:' not in output
    assert 'Traceback' not in output and 'KeyboardInterrupt' not in output, output


def test_a_ctrl_c_once_the_node_is_up_is_a_clean_stop(tmp_path: Path) -> None:
    code, output = _run_entry(tmp_path, SIGNAL_WHILE_SPINNING)
    assert code == 0, output
    assert 'ready: interrupt_test_spinning' in output
    assert 'HANDLER True' in output
    assert 'Traceback' not in output and 'KeyboardInterrupt' not in output, output

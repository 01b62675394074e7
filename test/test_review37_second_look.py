"""Second look at review 37's changes (regression tests of the faults found in them)."""

from __future__ import annotations

import threading

from cva_confidence_ros.ros.lifecycle_cli import interruptible


def test_the_tools_run_from_a_thread_other_than_the_main_one() -> None:
    # cva-param's and cva-lifecycle's main() called from a thread (a GUI, a test harness): the
    # SIGTERM handler installed for Ctrl-C/SIGTERM raised ValueError ("signal only works in
    # main thread") before anything was asked; the old code ran there.
    outcome: list[object] = []

    def call() -> None:
        try:
            outcome.append(interruptible('cva-param', lambda: 7))
        except Exception as error:  # noqa: BLE001  (the assertion below names it)
            outcome.append(error)

    thread = threading.Thread(target=call)
    thread.start()
    thread.join(10.0)
    assert outcome == [7]

"""Two writers of one file (two runs into one folder) do not share a temporary file."""

from __future__ import annotations

from pathlib import Path
import threading

from cva_confidence_ros.outputs import write_atomic


def test_a_second_writer_of_the_same_file_meanwhile_does_not_break_the_first(
    tmp_path: Path,
) -> None:
    # With one fixed `<path>.tmp`, the second writer truncated and renamed the first one's
    # half-written file, and the first failed on its vanished file (FileNotFoundError).
    path = tmp_path / 'history.json'

    def second() -> None:
        write_atomic(path, lambda handle: handle.write(b'second'))

    def first(handle: object) -> None:
        handle.write(b'first, ')  # type: ignore[attr-defined]
        other = threading.Thread(target=second)
        other.start()
        other.join()
        handle.write(b'whole')  # type: ignore[attr-defined]

    write_atomic(path, first)
    assert path.read_bytes() == b'first, whole'
    assert sorted(p.name for p in tmp_path.iterdir()) == ['history.json']

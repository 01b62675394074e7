"""Review 38, a second look at the morning's memory check: regression tests of the faults found."""

from __future__ import annotations

from pathlib import Path
import sys

import pytest

from cva_confidence_ros import memory

GB = 10**9


@pytest.mark.skipif(not sys.platform.startswith('linux'), reason='reads /proc')
def test_a_containers_page_cache_counts_as_free(tmp_path: Path, monkeypatch) -> None:
    # A container of 4 GB that has read 3.5 GB of bag files: memory.current (3.9 GB) counts
    # that page cache, which the kernel reclaims first. 0.11 GB were "available", and every
    # frame over that was refused although 3.6 GB could be had.
    (tmp_path / 'memory.max').write_text('4000000000\n')
    (tmp_path / 'memory.current').write_text('3900000000\n')
    (tmp_path / 'memory.stat').write_text(
        'anon 400000000\nfile 3500000000\nshmem 0\nactive_file 1500000000\n'
        'inactive_file 2000000000\n'
    )
    monkeypatch.setattr(memory, '_CGROUP', str(tmp_path), raising=False)
    monkeypatch.delenv(memory.CHECK_SWITCH, raising=False)
    read = memory._read_int

    def plenty(path: str, key: str = '') -> int | None:
        # The machine has memory to spare: the container's limit is what binds.
        return 64 * GB if key == 'MemAvailable' else read(path, key)

    monkeypatch.setattr(memory, '_read_int', plenty)
    own = read('/proc/self/status', 'VmRSS')
    assert own is not None
    available = memory.available_memory()
    assert available is not None
    assert available - own == 4 * GB - 3_900_000_000 + 3_500_000_000
    assert memory.shortfall(2 * GB) is None  # fits once the cache is reclaimed
    assert memory.shortfall(5 * GB + own) == available  # past the limit: still refused

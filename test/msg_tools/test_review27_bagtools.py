"""Walkthrough fixes of the bag tools: a replay that writes nothing leaves no empty output bag
behind (a retry needs no ``--overwrite`` for it)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from msg_tools.bagio import InputBag, OutputBag
from msg_tools.convert import IMAGE, image_to_msg


def _write(path: Path, count: int, **options: object) -> OutputBag:
    with OutputBag(path, **options) as bag:  # type: ignore[arg-type]
        for index in range(count):
            bag.write('/a', IMAGE, image_to_msg(np.full((4, 6), index, np.uint8), index, 'f'),
                      index)
    return bag


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_an_empty_new_bag_is_removed_only_when_asked(tmp_path: Path, storage: str) -> None:
    kept = _write(tmp_path / 'kept', 0, storage=storage)
    assert (tmp_path / 'kept' / 'metadata.yaml').is_file() and not kept.dropped_empty
    dropped = _write(tmp_path / 'dropped', 0, storage=storage, keep_empty=False)
    assert dropped.dropped_empty and not (tmp_path / 'dropped').exists()
    written = _write(tmp_path / 'written', 2, storage=storage, keep_empty=False)
    assert not written.dropped_empty
    with InputBag(tmp_path / 'written') as bag:
        assert len(list(bag.messages(['/a']))) == 2


def test_an_old_bag_is_never_removed_for_an_empty_run(tmp_path: Path) -> None:
    _write(tmp_path / 'out', 3)
    again = _write(tmp_path / 'out', 0, overwrite=True, keep_empty=False)
    assert again.kept_old and not again.dropped_empty
    with InputBag(tmp_path / 'out') as bag:
        assert len(list(bag.messages(['/a']))) == 3
    assert sorted(p.name for p in tmp_path.iterdir()) == ['out']

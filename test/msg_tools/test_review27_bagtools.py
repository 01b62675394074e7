"""Walkthrough fixes of the bag tools: a replay that writes nothing leaves no empty output bag
behind (a retry needs no ``--overwrite`` for it); a live replay that starts its node gives both
ends the large-message Fast DDS profile."""

from __future__ import annotations

import os
from pathlib import Path
from xml.etree import ElementTree

import numpy as np
import pytest

from cva_confidence_ros.ros.dds_profile import (
    FASTDDS_LARGE_MESSAGES_XML,
    PROFILE_VARIABLES,
    write_profile,
)
from msg_tools.bagio import InputBag, OutputBag
from msg_tools.convert import IMAGE, image_to_msg
from msg_tools.live import _large_messages_profile


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


def test_the_shipped_profile_file_is_the_one_the_tools_write(tmp_path: Path) -> None:
    root = Path(__file__).resolve().parents[2]
    shipped = ElementTree.parse(root / 'config' / 'fastdds_large_messages.xml').getroot()
    written = ElementTree.parse(write_profile(tmp_path)).getroot()

    def canonical(element: ElementTree.Element) -> list[tuple[str, str]]:
        return [(e.tag, (e.text or '').strip()) for e in element.iter()]

    assert canonical(shipped) == canonical(written)


def test_a_live_replay_that_starts_its_node_sets_the_large_message_profile(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    for name in PROFILE_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    lines: list[str] = []
    with _large_messages_profile(True, lines.append):
        files = {os.environ[name] for name in PROFILE_VARIABLES}
        (path,) = files
        # What the node's environment inherits (NodeProcess copies os.environ).
        assert Path(path).read_text() == FASTDDS_LARGE_MESSAGES_XML
    assert not Path(path).exists()
    assert not any(name in os.environ for name in PROFILE_VARIABLES)
    assert lines == ['no Fast DDS profile set: this replay and its node use the large-message '
                     'one (config/fastdds_large_messages.xml)']
    # A node already running keeps its settings; a profile of the user's is left alone.
    with _large_messages_profile(False, lines.append):
        assert not any(name in os.environ for name in PROFILE_VARIABLES)
    monkeypatch.setenv(PROFILE_VARIABLES[0], 'mine.xml')
    with _large_messages_profile(True, lines.append):
        assert os.environ[PROFILE_VARIABLES[0]] == 'mine.xml'
        assert PROFILE_VARIABLES[1] not in os.environ
    assert len(lines) == 1

"""Review 32 of the stamp synchroniser: messages of one pass of a looping bag delivered late
(stragglers) never pair with the next pass, nor hold it up."""

from __future__ import annotations

from cva_confidence_ros.sync import DEFAULT_KEYS, MatchedSet, StampSynchronizer

MS = 1_000_000
PERIOD = 33 * MS  # 30 Hz


def _stamps(frames: int) -> list[int]:
    return [10**12 + frame * PERIOD for frame in range(frames)]


def _pass(sync: StampSynchronizer, stamps: list[int], tag: str) -> list[MatchedSet]:
    return [s for t in stamps for key in DEFAULT_KEYS for s in sync.add(key, t, f'{key}{tag}@{t}')]


def _mixed(sets: list[MatchedSet], tag: str) -> list[int]:
    """The stamps of the sets holding a message of another pass than ``tag``."""
    return [s.stamp_ns for s in sets if any(tag not in str(m) for m in s.items.values())]


def _total(sync: StampSynchronizer) -> int:
    return len(sync.keys) * sync.matched + sync.dropped + sum(sync.pending().values())


def test_a_straggler_of_the_last_key_never_pairs_with_the_next_pass() -> None:
    # The right camera info of frame 10 comes 1.6 s late (kept aside: a jump back, maybe), then
    # the pass goes on. After the loop, frame 10 of the new pass must not take it: before, the
    # set {left, right, left_info of pass 2, right_info of pass 1} was emitted.
    stamps = _stamps(90)
    late = ('right_info', stamps[10])
    sync = StampSynchronizer(record_drops=True)
    first = []
    for t in stamps[:60]:
        for key in DEFAULT_KEYS:
            if (key, t) != late:
                first += sync.add(key, t, f'{key}#1@{t}')
    first += sync.add(*late, f'right_info#1@{stamps[10]}')
    first += _pass(sync, stamps[60:], '#1')
    second = _pass(sync, stamps, '#2')
    assert len(first) == 89
    assert [s.stamp_ns for s in second] == stamps
    assert _mixed(second, '#2') == []
    assert second[10].items['right_info'] == f'right_info#2@{stamps[10]}'
    sync.drain()
    assert len(sync.take_drops()) == sync.dropped == 4
    assert _total(sync) == 4 * 180


def test_a_straggler_after_the_last_frame_never_pairs_with_the_next_pass() -> None:
    # The lost right camera info of frame 10 turns up after the last frame of the pass, just
    # before the loop: it came before the new pass's first right camera info, so it is of the
    # pass before (a stream is time ordered) and is let go when the streams start over.
    stamps = _stamps(60)
    late = ('right_info', stamps[10])
    sync = StampSynchronizer(record_drops=True)
    for t in stamps:
        for key in DEFAULT_KEYS:
            if (key, t) != late:
                sync.add(key, t, f'{key}#1@{t}')
    sync.add(*late, f'right_info#1@{stamps[10]}')
    second = _pass(sync, stamps, '#2')
    assert [s.stamp_ns for s in second] == stamps
    assert _mixed(second, '#2') == []
    assert second[0].jumped_from_ns == stamps[-1]
    drops = sync.take_drops()
    assert ('right_info', stamps[10], 'late') in [(d.key, d.stamp_ns, d.kind) for d in drops]
    sync.drain()
    assert len(drops) + len(sync.take_drops()) == sync.dropped == 4
    assert _total(sync) == 4 * 120


def test_stragglers_kept_aside_do_not_hold_up_the_next_pass() -> None:
    # Two right camera infos come 1.3 s late and the pass goes on past them. Before, they stayed
    # aside for good: with queue_size=2 every right camera info of the next pass older than
    # them was pushed out at once, so the next pass paired nothing before frame 20, and then
    # frames 20 and 25 with the stragglers of the pass before.
    stamps = _stamps(90)
    due = {stamps[60]: stamps[20], stamps[65]: stamps[25]}
    sync = StampSynchronizer(queue_size=2)
    first = []
    for t in stamps:
        for key in DEFAULT_KEYS:
            if key != 'right_info' or t not in due.values():
                first += sync.add(key, t, f'{key}#1@{t}')
        if t in due:
            first += sync.add('right_info', due[t], f'right_info#1@{due[t]}')
    second = _pass(sync, stamps, '#2')
    assert len(first) == 88
    assert [s.stamp_ns for s in second] == stamps
    assert _mixed(second, '#2') == []
    assert sync.jumps == 1
    assert _total(sync) == 4 * 180

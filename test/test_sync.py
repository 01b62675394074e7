"""Tests of the ROS-free stamp synchroniser."""

from __future__ import annotations

import threading

import pytest

from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.sync import DEFAULT_KEYS, MatchedSet, StampSynchronizer

MS = 1_000_000


def _feed_frame(sync: StampSynchronizer, stamp: int, tag: str = '') -> list[MatchedSet]:
    out: list[MatchedSet] = []
    for key in DEFAULT_KEYS:
        out += sync.add(key, stamp, f'{key}{tag}@{stamp}')
    return out


def test_exact_pairs_equal_stamps_in_any_arrival_order() -> None:
    sync = StampSynchronizer()
    assert sync.add('right_info', 100, 'ri') == []
    assert sync.add('left', 100, 'l') == []
    assert sync.add('right', 100, 'r') == []
    (matched,) = sync.add('left_info', 100, 'li')
    assert matched.stamp_ns == 100
    assert matched.items == {'left': 'l', 'right': 'r', 'left_info': 'li', 'right_info': 'ri'}
    assert list(matched.items) == list(DEFAULT_KEYS)
    assert matched.stamps_ns == dict.fromkeys(DEFAULT_KEYS, 100)
    assert sync.matched == 1
    assert sync.dropped == 0
    assert sync.pending() == dict.fromkeys(DEFAULT_KEYS, 0)


def test_exact_does_not_pair_different_stamps() -> None:
    sync = StampSynchronizer(keys=('a', 'b'))
    assert sync.add('a', 100, 'a100') == []
    assert sync.add('b', 101, 'b101') == []
    assert sync.pending() == {'a': 1, 'b': 1}
    (matched,) = sync.add('a', 101, 'a101')
    assert matched.items == {'a': 'a101', 'b': 'b101'}
    # a@100 is older than the emitted a@101: it can never match and is evicted.
    assert sync.dropped == 1
    assert sync.pending() == {'a': 0, 'b': 0}


def test_exact_ignores_tolerance() -> None:
    sync = StampSynchronizer(keys=('a', 'b'), approximate=False, tolerance_ns=50)
    assert sync.tolerance_ns == 0
    sync.add('a', 100, 'a')
    assert sync.add('b', 120, 'b') == []


def test_exact_evicts_older_unmatched_of_every_key() -> None:
    sync = StampSynchronizer(keys=('a', 'b'))
    sync.add('a', 1, 'a1')
    sync.add('a', 2, 'a2')
    sync.add('b', 0, 'b0')
    (matched,) = sync.add('b', 2, 'b2')
    assert matched.stamp_ns == 2
    # a1 and b0 go; nothing newer is pending.
    assert sync.dropped == 2
    assert sync.pending() == {'a': 0, 'b': 0}


def test_late_and_duplicate_messages_are_dropped() -> None:
    sync = StampSynchronizer(keys=('a', 'b'))
    sync.add('a', 10, 'a10')
    assert sync.add('a', 10, 'again') == []
    assert sync.dropped == 1
    (matched,) = sync.add('b', 10, 'b10')
    # The newer of two messages with one stamp is kept (after a loop, the older is stale).
    assert matched.items['a'] == 'again'
    # Stamps at or before the last emitted one of the key cannot form a new set.
    assert sync.add('a', 10, 'late') == []
    assert sync.add('b', 5, 'later') == []
    assert sync.dropped == 3
    assert sync.pending() == {'a': 0, 'b': 0}


def test_full_queue_evicts_oldest_and_counts() -> None:
    sync = StampSynchronizer(keys=('a', 'b'), queue_size=3)
    for stamp in range(1, 6):
        assert sync.add('a', stamp, f'a{stamp}') == []
    assert sync.pending() == {'a': 3, 'b': 0}
    assert sync.dropped == 2
    # a1 was evicted: its partner finds nothing.
    assert sync.add('b', 1, 'b1') == []
    (matched,) = sync.add('b', 4, 'b4')
    assert matched.items == {'a': 'a4', 'b': 'b4'}
    # a3 and b1 are older than the set and leave; a5 stays.
    assert sync.dropped == 4
    assert sync.pending() == {'a': 1, 'b': 0}


def test_queue_bound_holds_under_a_long_unmatched_stream() -> None:
    sync = StampSynchronizer(queue_size=5)
    for stamp in range(1000):
        sync.add('left', stamp, stamp)
    assert sync.pending()['left'] == 5
    assert sync.dropped == 995


def test_out_of_order_arrival_within_queue_still_matches() -> None:
    sync = StampSynchronizer(keys=('a', 'b'))
    sync.add('a', 20, 'a20')
    sync.add('a', 10, 'a10')
    (first,) = sync.add('b', 10, 'b10')
    assert first.items == {'a': 'a10', 'b': 'b10'}
    (second,) = sync.add('b', 20, 'b20')
    assert second.items == {'a': 'a20', 'b': 'b20'}
    assert sync.dropped == 0


def test_approximate_pairs_within_tolerance_only() -> None:
    sync = StampSynchronizer(keys=('left', 'right'), approximate=True, tolerance_ns=5 * MS)
    sync.add('left', 100 * MS, 'l100')
    assert sync.add('right', 106 * MS, 'r106') == []
    (matched,) = sync.add('left', 103 * MS, 'l103')
    assert matched.items == {'left': 'l103', 'right': 'r106'}
    assert matched.stamp_ns == 103 * MS
    assert matched.stamps_ns == {'left': 103 * MS, 'right': 106 * MS}
    assert sync.dropped == 1  # l100


def test_approximate_boundary_is_inclusive() -> None:
    sync = StampSynchronizer(keys=('a', 'b'), approximate=True, tolerance_ns=10)
    sync.add('a', 0, 'a')
    assert len(sync.add('b', 10, 'b')) == 1


def test_approximate_picks_the_tightest_set() -> None:
    sync = StampSynchronizer(keys=('a', 'b', 'c'), approximate=True, tolerance_ns=10)
    sync.add('a', -8, 'a-8')
    sync.add('a', 5, 'a5')
    sync.add('b', -9, 'b-9')
    # With c@0 the sets {-8, -9, 0} (spread 9) and none with a5 (b-9..5 = 14) exist.
    (matched,) = sync.add('c', 0, 'c0')
    assert matched.stamps_ns == {'a': -8, 'b': -9, 'c': 0}
    assert sync.pending() == {'a': 1, 'b': 0, 'c': 0}


def test_approximate_chooses_minimal_spread_among_several() -> None:
    sync = StampSynchronizer(keys=('a', 'b'), approximate=True, tolerance_ns=10)
    sync.add('a', 92, 'a92')
    sync.add('a', 99, 'a99')
    (matched,) = sync.add('b', 100, 'b100')
    assert matched.items == {'a': 'a99', 'b': 'b100'}
    assert sync.dropped == 1


def test_approximate_stream_of_jittered_frames() -> None:
    period = 33 * MS
    sync = StampSynchronizer(approximate=True, tolerance_ns=3 * MS)
    sets = []
    for frame in range(20):
        base = frame * period
        jitter = (frame % 5 - 2) * MS  # -2 … +2 ms on the right camera
        sets += sync.add('left', base, ('L', frame))
        sets += sync.add('left_info', base, ('LI', frame))
        sets += sync.add('right_info', base + jitter, ('RI', frame))
        sets += sync.add('right', base + jitter, ('R', frame))
    assert len(sets) == 20
    for frame, matched in enumerate(sets):
        assert {msg[1] for msg in matched.items.values()} == {frame}
        assert matched.stamp_ns == frame * period
    assert sync.dropped == 0


def test_generic_keys_and_objects() -> None:
    sync = StampSynchronizer(keys=(0, 1), queue_size=1)
    payload = object()
    sync.add(0, 7, payload)
    (matched,) = sync.add(1, 7, None)
    assert matched.items[0] is payload
    assert matched.items[1] is None


def test_reset_forgets_pending_and_last() -> None:
    sync = StampSynchronizer(keys=('a', 'b'))
    sync.add('a', 1, 'a')
    sync.add('b', 1, 'b')
    sync.add('a', 2, 'a2')
    sync.reset()
    assert sync.pending() == {'a': 0, 'b': 0}
    # After a reset (e.g. a bag loops), earlier stamps are accepted again.
    sync.add('a', 1, 'a')
    assert len(sync.add('b', 1, 'b')) == 1


def test_concurrent_adds_keep_counts_consistent() -> None:
    sync = StampSynchronizer(keys=('a', 'b'), queue_size=1000)
    results: list[MatchedSet] = []
    lock = threading.Lock()

    def feed(key: str) -> None:
        for stamp in range(500):
            out = sync.add(key, stamp, (key, stamp))
            with lock:
                results.extend(out)

    threads = [threading.Thread(target=feed, args=(key,)) for key in ('a', 'b')]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert len(results) == sync.matched
    for matched in results:
        assert matched.items['a'][1] == matched.items['b'][1] == matched.stamp_ns
    # Each stamp is either matched (2 messages) or its messages were dropped/pending.
    total = 2 * len(results) + sync.dropped + sum(sync.pending().values())
    assert total == 1000


@pytest.mark.parametrize(
    'kwargs',
    [
        {'keys': ()},
        {'keys': ('a', 'a')},
        {'queue_size': 0},
        {'queue_size': 2.5},
        {'queue_size': True},
        {'tolerance_ns': -1},
        {'tolerance_ns': 0.5, 'approximate': True},
    ],
)
def test_invalid_configurations(kwargs: dict) -> None:
    with pytest.raises(ConfigError):
        StampSynchronizer(**kwargs)


def test_invalid_key_and_stamp() -> None:
    sync = StampSynchronizer(keys=('a', 'b'))
    with pytest.raises(ConfigError, match='unknown key'):
        sync.add('c', 1, None)
    with pytest.raises(InputError, match='integer'):
        sync.add('a', 1.5, None)  # type: ignore[arg-type]


def _total(sync: StampSynchronizer) -> int:
    """Every message offered ends up matched, dropped or pending, exactly once."""
    return len(sync.keys) * sync.matched + sync.dropped + sum(sync.pending().values())


def test_stamps_jumping_back_start_over() -> None:
    # ros2 bag play --loop, a driver restart or a simulator reset: a whole frame, older.
    sync = StampSynchronizer(min_jump_ns=1)  # stamps in ns here: any step back counts
    (first,) = _feed_frame(sync, 10)
    assert first.jumped_from_ns is None
    (after_jump,) = _feed_frame(sync, 5)
    assert after_jump.stamp_ns == 5
    assert after_jump.jumped_from_ns == 10
    assert after_jump.items['left'] == 'left@5'
    assert sync.jumps == 1
    # Pairing goes on from the new time, with no further jump.
    (following,) = _feed_frame(sync, 6)
    assert following.stamp_ns == 6 and following.jumped_from_ns is None
    assert sync.jumps == 1
    assert sync.dropped == 0
    assert _total(sync) == 12


def test_jump_back_far_into_the_past_in_nanoseconds() -> None:
    sync = StampSynchronizer()
    t = 2_000_000_000 * 10**9
    sets = _feed_frame(sync, t) + _feed_frame(sync, t - 100 * 10**9)
    sets += _feed_frame(sync, t - 99 * 10**9)
    assert [s.stamp_ns for s in sets] == [t, t - 100 * 10**9, t - 99 * 10**9]
    assert [s.jumped_from_ns for s in sets] == [None, t, None]


def test_jump_back_drops_what_waited_from_before() -> None:
    sync = StampSynchronizer(min_jump_ns=1)  # stamps in ns here: any step back counts
    _feed_frame(sync, 10)
    # Half of frame 11 came before the jump; its other half never will.
    sync.add('left', 11, 'l11')
    sync.add('right', 11, 'r11')
    (matched,) = _feed_frame(sync, 3)
    assert matched.jumped_from_ns == 10
    assert sync.pending() == dict.fromkeys(DEFAULT_KEYS, 0)
    assert sync.dropped == 2
    assert _total(sync) == 10


def test_late_straggler_is_still_dropped_and_is_no_jump() -> None:
    sync = StampSynchronizer(min_jump_ns=1)  # stamps in ns here: any step back counts
    _feed_frame(sync, 10)
    _feed_frame(sync, 20)
    # One message of frame 15 delivered out of order, after frame 20 went out.
    assert sync.add('left', 15, 'late') == []
    assert sync.add('right_info', 10, 'repeat') == []
    assert sync.dropped == 2
    assert sync.jumps == 0
    (matched,) = _feed_frame(sync, 30)
    assert matched.jumped_from_ns is None
    assert sync.jumps == 0
    assert _total(sync) == 14


def test_stragglers_of_many_frames_never_make_a_jump() -> None:
    sync = StampSynchronizer(min_jump_ns=1)  # stamps in ns here: any step back counts
    sets: list[MatchedSet] = []
    late: list[tuple[str, int]] = []
    for frame in range(1, 41):
        for index, key in enumerate(DEFAULT_KEYS):
            if frame % 4 == index and frame % 2:
                late.append((key, frame))  # delivered after the next frame
            else:
                sets += sync.add(key, frame, f'{key}@{frame}')
        while late and late[0][1] < frame:
            key, stamp = late.pop(0)
            sets += sync.add(key, stamp, f'{key}@{stamp}')
    assert sync.jumps == 0
    assert all(s.jumped_from_ns is None for s in sets)
    # Every even frame pairs; an odd one misses its straggler.
    assert [s.stamp_ns for s in sets] == list(range(2, 41, 2))
    assert all(n <= sync.queue_size for n in sync.pending().values())


def test_approximate_stream_survives_a_jump_back() -> None:
    period = 33 * MS
    sync = StampSynchronizer(approximate=True, tolerance_ns=3 * MS)
    sets = []
    for start in (1000 * period, 0):  # a second pass from an earlier time
        for frame in range(10):
            base = start + frame * period
            jitter = (frame % 5 - 2) * MS
            sets += sync.add('left', base, ('L', frame))
            sets += sync.add('left_info', base, ('LI', frame))
            sets += sync.add('right_info', base + jitter, ('RI', frame))
            sets += sync.add('right', base + jitter, ('R', frame))
    assert len(sets) == 20
    assert [s.jumped_from_ns for s in sets].count(None) == 19
    assert sets[10].jumped_from_ns == 1009 * period
    assert sets[10].stamp_ns == 0
    assert sync.jumps == 1
    assert sync.dropped == 0


def test_reset_forgets_messages_held_aside() -> None:
    sync = StampSynchronizer(keys=('a', 'b'), min_jump_ns=1)
    sync.add('a', 10, 'a10')
    sync.add('b', 10, 'b10')
    sync.add('a', 5, 'a5')  # held aside as a possible jump back
    sync.reset()
    sync.add('a', 20, 'a20')
    sync.add('b', 20, 'b20')
    # b@5 after the reset is late again; it must not pair with the a@5 from before it.
    assert sync.add('b', 5, 'b5') == []
    assert sync.jumps == 0


def test_a_frame_delivered_late_is_no_jump_back() -> None:
    # With the default threshold (1 s) a whole frame that comes in after a newer one (reordered
    # delivery) is dropped as stragglers, and does not reset the streams.
    sync = StampSynchronizer()
    period = 33 * MS
    sets = _feed_frame(sync, 1000 * period) + _feed_frame(sync, 1002 * period)
    sets += _feed_frame(sync, 1001 * period)  # complete, but older than the last set
    sets += _feed_frame(sync, 1003 * period)
    assert [s.stamp_ns for s in sets] == [1000 * period, 1002 * period, 1003 * period]
    assert sync.jumps == 0 and sync.dropped == 4
    # A jump back by less than the threshold that goes on (a second whole frame before any newer
    # message) is a jump: pairing starts over from the first of the two frames.
    later = [s for k in range(995, 1006) for s in _feed_frame(sync, k * period)]
    assert [s.stamp_ns for s in later] == [k * period for k in range(995, 1006)]
    assert [s.jumped_from_ns for s in later] == [1003 * period] + [None] * 10
    assert sync.jumps == 1 and sync.dropped == 4
    assert _total(sync) == 4 * 15


def test_min_jump_must_be_a_positive_integer() -> None:
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ConfigError, match='min_jump_ns must be an integer >= 1'):
            StampSynchronizer(min_jump_ns=bad)  # type: ignore[arg-type]


def test_every_message_let_go_is_recorded_once_with_why() -> None:
    sync = StampSynchronizer(keys=('a', 'b'), queue_size=2, record_drops=True)
    assert sync.add('a', 10, 'a10') == []
    assert sync.add('a', 10, 'again') == []  # duplicate while waiting
    assert sync.add('a', 20, 'a20') == [] and sync.add('a', 30, 'a30') == []  # 10 overflows
    assert sync.add('b', 25, 'b25') == []
    (matched,) = sync.add('b', 30, 'b30')  # a20 and b25 are passed by the set at 30
    assert matched.stamp_ns == 30
    assert sync.add('b', 30, 'b30 again') == []  # the stamp just paired: a repeat
    assert sync.add('b', 29, 'b29') == []  # older than the last set by less than a jump
    assert sync.add('a', 40, 'a40') == []
    sync.drain()  # end of input: a40 never found a partner
    drops = sync.take_drops()
    assert [(d.key, d.stamp_ns, d.kind) for d in drops] == [
        ('a', 10, 'duplicate'),
        ('a', 10, 'overflow'),
        ('a', 20, 'passed'),
        ('b', 25, 'passed'),
        ('b', 30, 'repeat'),
        ('b', 29, 'late'),
        ('a', 40, 'unmatched'),
    ]
    assert len(drops) == sync.dropped and sync.pending() == {'a': 0, 'b': 0}
    # Each drop says what the other stream held then: b had 25 (and 30 arriving) for a20.
    passed = next(d for d in drops if (d.key, d.stamp_ns) == ('a', 20))
    assert passed.others == {'b': (25, 30)}
    assert sync.take_drops() == []


def test_a_jump_back_records_what_waited_and_nothing_twice() -> None:
    second = 1_000_000_000
    sync = StampSynchronizer(keys=('a', 'b'), record_drops=True)
    sync.add('a', 100 * second, 1)
    sync.add('b', 100 * second, 1)  # a set at 100 s
    sync.add('a', 101 * second, 2)  # waits for b, which never comes
    sync.add('a', 5 * second, 3)  # 95 s back: held aside
    (matched,) = sync.add('b', 5 * second, 3)  # the old ones pair: the streams jumped
    assert matched.jumped_from_ns == 100 * second
    sync.drain()
    drops = sync.take_drops()
    assert [(d.key, d.stamp_ns, d.kind) for d in drops] == [('a', 101 * second, 'jump')]
    assert len(drops) == sync.dropped


def test_drops_are_not_kept_unless_asked() -> None:
    sync = StampSynchronizer(keys=('a', 'b'))
    sync.add('a', 1, 'x')
    sync.add('a', 1, 'dup')
    sync.drain()
    assert sync.dropped == 2 and sync.take_drops() == []


def _passes(sets: list[MatchedSet]) -> list[set[str]]:
    """For each set, the passes (``#N`` tags) its messages came from: one each if none mixes."""
    return [{str(msg).split('#')[1].split('@')[0] for msg in m.items.values()} for m in sets]


def test_a_bag_loop_never_pairs_a_message_of_the_pass_before() -> None:
    # ros2 bag play --loop of a 3 s bag at 30 Hz: the stamps start over, the payloads are new.
    # One left image of the first pass came over a second late and was kept aside: the second
    # pass's image of that stamp replaces it, instead of the old one pairing with new partners.
    period = 33 * MS
    stamps = [10**12 + frame * period for frame in range(90)]
    sync = StampSynchronizer(record_drops=True)
    first = []
    for stamp in stamps[:60]:
        for key in DEFAULT_KEYS:
            if (key, stamp) != ('left', stamps[10]):
                first += sync.add(key, stamp, f'{key}#1@{stamp}')
    first += sync.add('left', stamps[10], f'left#1@{stamps[10]}')  # 1.6 s late: kept aside
    first += [s for stamp in stamps[60:] for s in _feed_frame(sync, stamp, '#1')]
    second = [s for stamp in stamps for s in _feed_frame(sync, stamp, '#2')]
    assert len(first) == 89 and _passes(first) == [{'1'}] * 89
    assert [s.stamp_ns for s in second] == stamps
    assert _passes(second) == [{'2'}] * 90
    assert second[10].items['left'] == f'left#2@{stamps[10]}'
    assert [s.jumped_from_ns for s in second] == [stamps[-1]] + [None] * 89
    sync.drain()
    assert len(sync.take_drops()) == sync.dropped == 4  # frame 10 of the first pass
    assert _total(sync) == 4 * 180 - 4 + 4


def test_a_bag_shorter_than_a_jump_loops_too() -> None:
    # A 0.5 s bag on a loop goes back by less than min_jump_ns (1 s): every pass still pairs
    # all its frames, each with its own messages, and the jumps are counted and marked.
    period = 33 * MS
    stamps = [10**12 + frame * period for frame in range(15)]
    sync = StampSynchronizer(record_drops=True)
    passes = [[s for t in stamps for s in _feed_frame(sync, t, f'#{n}')] for n in (1, 2, 3)]
    for n, sets in enumerate(passes, 1):
        assert [s.stamp_ns for s in sets] == stamps
        assert _passes(sets) == [{str(n)}] * 15
    # Recognised by its second frame, the jump emits the first one too.
    assert [s.jumped_from_ns for s in passes[1]] == [stamps[-1]] + [None] * 14
    assert sync.jumps == 2 and sync.dropped == 0
    sync.drain()
    assert sync.take_drops() == [] and _total(sync) == 4 * 45


def test_an_incomplete_last_frame_does_not_pair_with_the_next_pass() -> None:
    # The last frame of a short bag lost its right camera info; the next pass's one must not
    # complete it with the three messages of the pass before.
    stamps = [10**12 + frame * 33 * MS for frame in range(10)]
    sync = StampSynchronizer(record_drops=True)
    first = []
    for stamp in stamps:
        for key in DEFAULT_KEYS:
            if (key, stamp) != ('right_info', stamps[-1]):
                first += sync.add(key, stamp, f'{key}#1@{stamp}')
    second = [s for stamp in stamps for s in _feed_frame(sync, stamp, '#2')]
    assert len(first) == 9 and [s.stamp_ns for s in second] == stamps
    assert _passes(second) == [{'2'}] * 10
    drops = sync.take_drops()
    assert sorted((d.stamp_ns, d.kind) for d in drops) == [(stamps[-1], 'jump')] * 3
    assert len(drops) == sync.dropped


def test_a_one_frame_bag_on_a_loop_pairs_every_other_pass() -> None:
    # Each pass repeats the stamp just paired: the first pass back is taken aside (it could be
    # a repeat), the next one is the jump; no set mixes two passes.
    sync = StampSynchronizer(record_drops=True)
    stamp = 10**12
    sets = [_feed_frame(sync, stamp, f'#{n}') for n in range(1, 8)]
    assert [len(s) for s in sets] == [1, 0, 1, 0, 1, 0, 1]
    assert [_passes(s) for s in sets if s] == [[{'1'}], [{'3'}], [{'5'}], [{'7'}]]
    assert [s[0].jumped_from_ns for s in sets if s] == [None, stamp, stamp, stamp]
    sync.drain()
    assert len(sync.take_drops()) == sync.dropped == 12 and _total(sync) == 28


def test_a_late_frame_between_newer_ones_is_dropped_and_recorded_once() -> None:
    sync = StampSynchronizer(keys=('a', 'b'), record_drops=True)
    sync.add('a', 2000 * MS, 'a2000')
    sync.add('b', 2000 * MS, 'b2000')
    assert sync.add('a', 1967 * MS, 'late a') == [] and sync.add('b', 1967 * MS, 'late b') == []
    assert sync.dropped == 2 and sync.take_drops() == []  # taken aside: late, or a jump
    (matched,) = sync.add('a', 2033 * MS, 'a2033') or sync.add('b', 2033 * MS, 'b2033')
    assert matched.stamp_ns == 2033 * MS and matched.jumped_from_ns is None
    # The newer message told: it was a late frame, let go in the order it came.
    assert [(d.key, d.stamp_ns, d.kind) for d in sync.take_drops()] == [
        ('a', 1967 * MS, 'late'), ('b', 1967 * MS, 'late')
    ]
    assert sync.jumps == 0 and sync.dropped == 2

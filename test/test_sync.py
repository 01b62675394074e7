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
    assert matched.items['a'] == 'a10'
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

"""Match messages from several streams by their time stamps (ROS-free).

``message_filters`` is not on the package index, so the node and ``cva-bag-replay`` share this
small synchroniser. It works on any objects: the caller passes the stamp (integer nanoseconds)
next to each message.

Policies:

* **exact** (default): a set is emitted when every key holds a message with the same stamp.
* **approximate**: a set is emitted as soon as every key holds a message and all chosen stamps
  lie within ``tolerance_ns`` of each other (max − min ≤ tolerance). When several sets would fit,
  the one with the smallest spread is taken. Choose a tolerance below half the frame period, so
  that two frames of one stream can never both fit.

Both policies emit eagerly: a set leaves as soon as it is complete. Messages of a key that are
older than the ones just emitted can never be part of a later set (streams are time ordered), so
they are evicted, as is anything that arrives with a stamp at or before the last emitted one of
its key, and the oldest message of a key whose queue is full. Every evicted message counts once
in :attr:`StampSynchronizer.dropped`.

Time going backwards (``ros2 bag play --loop``, a driver restart, a simulator reset) is told from
a late straggler by how far back it goes (``min_jump_ns``, 1 s by default) and by whether the
old messages form a set: those that far before the last emitted stamp of their key are kept
aside (bounded like the queues, and counted as dropped); a single straggler, whose partners have
long gone, never completes a set, but once the old messages do, the streams have jumped back.
The synchroniser then starts over from them: the set is emitted with
:attr:`MatchedSet.jumped_from_ns` set, the messages still waiting from before the jump are
dropped, and :attr:`StampSynchronizer.jumps` counts one.
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence
from dataclasses import dataclass, field, replace
import threading
from typing import Any

from cva_confidence_ros.errors import ConfigError, InputError

__all__ = ['DEFAULT_KEYS', 'DROP_KINDS', 'Drop', 'MatchedSet', 'StampSynchronizer']

#: Why a message left the synchroniser without a set (:class:`Drop`):
#: ``duplicate``: its key already held a message with that stamp;
#: ``repeat``: its stamp is the one just emitted on its key (paired before);
#: ``late``: older than the last set of its key, by less than a jump;
#: ``overflow``: its key's queue was full, and it was the oldest;
#: ``passed``: a set of later stamps was emitted first;
#: ``jump``: it waited when the stamps jumped back and pairing started over;
#: ``unmatched``: still waiting when :meth:`StampSynchronizer.drain` was called.
DROP_KINDS = ('duplicate', 'repeat', 'late', 'overflow', 'passed', 'jump', 'unmatched')

DEFAULT_KEYS: tuple[str, ...] = ('left', 'right', 'left_info', 'right_info')


@dataclass(frozen=True)
class Drop:
    """One message that left the synchroniser without a set (``record_drops=True``).

    Attributes:
        key: Its stream.
        stamp_ns: Its stamp.
        kind: Why (one of :data:`DROP_KINDS`).
        others: For every other key, the stamps it held then (waiting, and the last emitted
            one), to say which partner was missing and how near the nearest came.
    """

    key: Hashable
    stamp_ns: int
    kind: str
    others: dict[Hashable, tuple[int, ...]]


@dataclass(frozen=True)
class MatchedSet:
    """One message per key whose stamps match.

    Attributes:
        stamp_ns: Stamp of the set in nanoseconds: the common stamp in exact mode, the stamp of
            the first key's message in approximate mode.
        items: key → message, one entry per key of the synchroniser.
        stamps_ns: key → stamp of that message in nanoseconds.
        jumped_from_ns: None, or the stamp of the set emitted before this one when this set is
            older: the stamps jumped back and the synchroniser started over.
    """

    stamp_ns: int
    items: dict[Hashable, Any]
    stamps_ns: dict[Hashable, int] = field(default_factory=dict)
    jumped_from_ns: int | None = None


class StampSynchronizer:
    """Group messages of several keyed streams whose stamps match.

    Args:
        keys: Names of the streams, e.g. ``('left', 'right', 'left_info', 'right_info')``.
            At least one, all distinct.
        queue_size: Most messages held per key while waiting for a match (≥ 1).
        approximate: Use the approximate policy instead of exact stamp equality.
        tolerance_ns: Largest spread of stamps in one set, in nanoseconds (≥ 0). Only used
            when ``approximate`` is True; the exact policy always uses 0.
        min_jump_ns: How far before the last emitted stamp a message must lie to count as a
            possible jump back in time (≥ 1; default 1 s). Nearer ones are late stragglers and
            dropped: a complete frame delivered after a newer one never resets the streams,
            and a jump back by less than this heals by itself once the stamps pass the old
            ones.
        record_drops: Keep a :class:`Drop` for every message that leaves without a set
            (:meth:`take_drops`), for tools that report them one by one; off in the node.

    Attributes:
        dropped: Messages evicted without being part of a set.
        matched: Sets emitted.
        jumps: Times the stamps jumped back and the synchroniser started over.

    Raises:
        ConfigError: Empty or repeated keys, ``queue_size`` < 1, ``tolerance_ns`` < 0 or
            ``min_jump_ns`` < 1.

    Thread-safe: :meth:`add` may be called from several threads.
    """

    def __init__(
        self,
        keys: Sequence[Hashable] = DEFAULT_KEYS,
        queue_size: int = 10,
        approximate: bool = False,
        tolerance_ns: int = 0,
        min_jump_ns: int = 1_000_000_000,
        record_drops: bool = False,
    ) -> None:
        keys = tuple(keys)
        if not keys:
            raise ConfigError('keys must name at least one stream; got an empty sequence')
        if len(set(keys)) != len(keys):
            raise ConfigError(f'keys must be distinct; got {keys}')
        if isinstance(queue_size, bool) or not isinstance(queue_size, int) or queue_size < 1:
            raise ConfigError(f'queue_size must be an integer >= 1; got {queue_size!r}')
        if isinstance(tolerance_ns, bool) or not isinstance(tolerance_ns, int) or tolerance_ns < 0:
            raise ConfigError(f'tolerance_ns must be an integer >= 0; got {tolerance_ns!r}')
        if isinstance(min_jump_ns, bool) or not isinstance(min_jump_ns, int) or min_jump_ns < 1:
            raise ConfigError(f'min_jump_ns must be an integer >= 1; got {min_jump_ns!r}')
        self.keys = keys
        self.min_jump_ns = min_jump_ns
        self.queue_size = queue_size
        self.approximate = bool(approximate)
        self.tolerance_ns = tolerance_ns if self.approximate else 0
        self.dropped = 0
        self.matched = 0
        self.jumps = 0
        self._queues: dict[Hashable, list[tuple[int, Any]]] = {key: [] for key in keys}
        # Messages before the last emitted stamp of their key: late stragglers, or the first
        # messages after a jump back in time (see the module docstring).
        self._stale: dict[Hashable, list[tuple[int, Any]]] = {key: [] for key in keys}
        self._last: dict[Hashable, int | None] = {key: None for key in keys}
        self._last_set_ns: int | None = None
        self._lock = threading.Lock()
        self.record_drops = bool(record_drops)
        self._drops: list[Drop] = []

    def _note(self, key: Hashable, stamps: Sequence[int], kind: str) -> None:
        """Record ``stamps`` of ``key`` as dropped for ``kind`` (before the queues change)."""
        if not self.record_drops or not stamps:
            return
        others = {}
        for other in self.keys:
            if other == key:
                continue
            held = [s for s, _ in self._queues[other]] + [s for s, _ in self._stale[other]]
            last = self._last[other]
            others[other] = tuple(sorted(held + ([last] if last is not None else [])))
        self._drops.extend(Drop(key, int(stamp), kind, others) for stamp in stamps)

    def take_drops(self) -> list[Drop]:
        """The drops recorded since the last call, oldest first (``record_drops=True``)."""
        with self._lock:
            drops, self._drops = self._drops, []
            return drops

    def drain(self) -> None:
        """End of input: drop everything still waiting (counted, and recorded as
        ``unmatched``, or ``late`` for messages kept aside as a possible jump back)."""
        with self._lock:
            for key in self.keys:
                self._note(key, [s for s, _ in self._queues[key]], 'unmatched')
                self._note(key, [s for s, _ in self._stale[key]], 'late')
            for key in self.keys:
                self.dropped += len(self._queues[key])  # held-aside ones counted already
                self._queues[key] = []
                self._stale[key] = []

    def add(self, key: Hashable, stamp_ns: int, msg: Any) -> list[MatchedSet]:
        """Offer one message; return the sets it completes (empty or one element).

        Args:
            key: One of :attr:`keys`.
            stamp_ns: The message's stamp in integer nanoseconds.
            msg: Any object; handed back untouched inside a :class:`MatchedSet`.

        Returns:
            The completed sets, oldest first (at most one per call with eager emission). A set
            older than the one before it (the stamps jumped back) has
            :attr:`MatchedSet.jumped_from_ns` set.

        Raises:
            ConfigError: ``key`` is not one of :attr:`keys`.
            InputError: ``stamp_ns`` is not an integer.
        """
        if key not in self._queues:
            raise ConfigError(f'unknown key {key!r}; expected one of {self.keys}')
        if isinstance(stamp_ns, bool) or not isinstance(stamp_ns, int):
            raise InputError(
                f'stamp_ns must be an integer number of nanoseconds; got {stamp_ns!r}'
            )
        with self._lock:
            last = self._last[key]
            if last is not None and stamp_ns <= last:
                self.dropped += 1
                if last - stamp_ns < self.min_jump_ns:
                    # A repeat of what was just emitted (a second publisher, a resent
                    # message) or a late straggler.
                    self._note(key, [stamp_ns], 'repeat' if stamp_ns == last else 'late')
                    return []
                return self._add_stale(key, stamp_ns, msg)
            queue = self._queues[key]
            if not self._insert(key, queue, stamp_ns, msg):
                return []
            chosen = self._best_set(self._queues, key, stamp_ns)
            if chosen is None:
                return []
            return [self._emit(chosen)]

    def _insert(
        self, key: Hashable, queue: list[tuple[int, Any]], stamp_ns: int, msg: Any
    ) -> bool:
        """Put a message into a queue (sorted, bounded); False if it did not stay there."""
        if any(stamp == stamp_ns for stamp, _ in queue):
            # A repeated stamp on one stream: keep the first, the newcomer is a duplicate.
            self.dropped += 1
            self._note(key, [stamp_ns], 'duplicate')
            return False
        queue.append((stamp_ns, msg))
        queue.sort(key=lambda entry: entry[0])
        if len(queue) > self.queue_size:
            self._note(key, [queue[0][0]], 'overflow')
            queue.pop(0)
            self.dropped += 1
        return any(entry[0] == stamp_ns for entry in queue)

    def _add_stale(self, key: Hashable, stamp_ns: int, msg: Any) -> list[MatchedSet]:
        """Keep a message older than the last set aside; start over if the old ones pair up.

        The message has already been counted as dropped, and so has everything held aside: what
        a jump brings back is taken off :attr:`dropped` again.
        """
        before = self.dropped
        kept = self._insert(key, self._stale[key], stamp_ns, msg)
        # Held-aside messages were counted when they came; evicting or refusing one is no news.
        self.dropped = before
        if not kept:
            return []
        chosen = self._best_set(self._stale, key, stamp_ns)
        if chosen is None:
            return []
        # A whole set older than the last one: the streams went back in time, not astray.
        jumped_from = self._last_set_ns
        self.jumps += 1
        for other in self.keys:
            self._note(other, [s for s, _ in self._queues[other]], 'jump')
        self.dropped += sum(len(queue) for queue in self._queues.values())
        self.dropped -= sum(len(queue) for queue in self._stale.values())
        self._queues = self._stale
        self._stale = {other: [] for other in self.keys}
        self._last = dict.fromkeys(self.keys)
        matched = self._emit(chosen)
        return [replace(matched, jumped_from_ns=jumped_from)]

    def _best_set(
        self, queues: dict[Hashable, list[tuple[int, Any]]], key: Hashable, stamp_ns: int
    ) -> dict[Hashable, int] | None:
        """The tightest set in ``queues`` that holds the new message, as key → stamp, or None."""
        tol = self.tolerance_ns
        # Only the new message can complete a set: before it came none was complete.
        candidates = {
            other: [s for s, _ in queues[other] if abs(s - stamp_ns) <= tol]
            for other in self.keys
            if other != key
        }
        if any(not stamps for stamps in candidates.values()):
            return None
        # Any valid set fits in a window [low, low + tol] that holds stamp_ns and starts at
        # one of the set's stamps, so trying every such start finds them all.
        starts = {stamp_ns}
        for stamps in candidates.values():
            starts.update(s for s in stamps if s <= stamp_ns)
        best: dict[Hashable, int] | None = None
        best_spread = -1
        for low in sorted(starts):
            high = low + tol
            chosen: dict[Hashable, int] = {key: stamp_ns}
            for other, stamps in candidates.items():
                inside = [s for s in stamps if low <= s <= high]
                if not inside:
                    break
                chosen[other] = min(inside, key=lambda s: abs(s - stamp_ns))
            else:
                spread = max(chosen.values()) - min(chosen.values())
                if best is None or spread < best_spread:
                    best, best_spread = chosen, spread
        return best

    def _emit(self, chosen: dict[Hashable, int]) -> MatchedSet:
        items: dict[Hashable, Any] = {}
        # Recorded before any queue changes, so each drop sees the stamps its partners had.
        for key in self.keys:
            self._note(key, [s for s, _ in self._queues[key] if s < chosen[key]], 'passed')
        for key in self.keys:
            stamp = chosen[key]
            queue = self._queues[key]
            kept: list[tuple[int, Any]] = []
            for entry_stamp, msg in queue:
                if entry_stamp == stamp:
                    items[key] = msg
                elif entry_stamp < stamp:
                    self.dropped += 1
                else:
                    kept.append((entry_stamp, msg))
            self._queues[key] = kept
            self._last[key] = stamp
        self.matched += 1
        ordered = {key: chosen[key] for key in self.keys}
        self._last_set_ns = ordered[self.keys[0]]
        return MatchedSet(stamp_ns=ordered[self.keys[0]], items=items, stamps_ns=ordered)

    def pending(self) -> dict[Hashable, int]:
        """Number of messages waiting per key."""
        with self._lock:
            return {key: len(queue) for key, queue in self._queues.items()}

    def reset(self) -> None:
        """Forget every waiting message and the last emitted stamps (counters are kept)."""
        with self._lock:
            for key in self.keys:
                self._queues[key] = []
                self._stale[key] = []
                self._last[key] = None
            self._last_set_ns = None

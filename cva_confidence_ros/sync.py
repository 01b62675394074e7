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
its key, and the oldest message of a key whose queue is full. A second message with the stamp of
one still waiting on its key replaces it (the newer one is kept: after a bag loop or a restart,
the old one belongs to another pass). Every evicted message counts once in
:attr:`StampSynchronizer.dropped`.

Time going backwards (``ros2 bag play --loop``, a driver restart, a simulator reset) is told from
late stragglers by whether the old messages form sets, and by how far back they go
(``min_jump_ns``, 1 s by default). Messages at or before the last emitted stamp of their key are
kept aside (bounded like the queues, and counted as dropped); a single straggler, whose partners
have long gone, never completes a set, and is let go when a newer message of its key comes (its
stream went on past it) or when it came before the message of its key that starts the streams
over: it never pairs with the messages of the next pass. Once the old messages do complete one,
the streams have jumped back when that set lies ``min_jump_ns`` or more before the last one, or
when it is the second such set in a row, with no newer message in between (a shorter jump that
goes on: the loop of a bag shorter than ``min_jump_ns``); a single whole frame delivered after a
newer one is dropped. The synchroniser then starts over from them: the set is emitted with
:attr:`MatchedSet.jumped_from_ns` set (after a shorter jump, the first of the two sets is emitted
too), the messages still waiting from before the jump are dropped, and
:attr:`StampSynchronizer.jumps` counts one.
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence
from dataclasses import dataclass, field, replace
import threading
from typing import Any

import numpy as np

from cva_confidence_ros.checks import is_int
from cva_confidence_ros.errors import ConfigError, InputError

__all__ = ['DEFAULT_KEYS', 'DROP_KINDS', 'Drop', 'MatchedSet', 'StampSynchronizer']

#: Why a message left the synchroniser without a set (:class:`Drop`):
#: ``duplicate``: a newer message of its key with the same stamp replaced it while it waited;
#: ``repeat``: its stamp is the one just emitted on its key (paired before);
#: ``late``: older than the last set of its key, and the streams did not jump back;
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


@dataclass(eq=False)
class _Held:
    """A message kept aside: at or before the last emitted stamp of its key.

    Attributes:
        stamp_ns: Its stamp.
        msg: The message.
        seq: Arrival order (its drop is recorded in that order).
        near: Less than ``min_jump_ns`` before the last emitted stamp of its key.
        drop: Its record (``record_drops``), kept until it is let go.
    """

    stamp_ns: int
    msg: Any
    seq: int
    near: bool
    drop: Drop | None


@dataclass(eq=False)
class _Behind:
    """A whole set of held-aside messages less than ``min_jump_ns`` before the last set: a late
    frame, or the first frame of a shorter jump back, until the next set or a newer message
    tells which."""

    stamps_ns: dict[Hashable, int]
    items: dict[Hashable, Any]
    entries: list[_Held]


class StampSynchronizer:
    """Group messages of several keyed streams whose stamps match.

    Args:
        keys: Names of the streams, e.g. ``('left', 'right', 'left_info', 'right_info')``.
            At least one, all distinct.
        queue_size: Most messages held per key while waiting for a match (≥ 1).
        approximate: Use the approximate policy instead of exact stamp equality.
        tolerance_ns: Largest spread of stamps in one set, in nanoseconds (≥ 0). Only used
            when ``approximate`` is True; the exact policy always uses 0.
        min_jump_ns: How far before the last emitted stamp a whole set must lie to be a jump
            back in time at once (≥ 1; default 1 s). A nearer one is a jump only when a second
            one follows with no newer message in between (the loop of a short bag, a small
            reset); a single complete frame delivered after a newer one is dropped and never
            resets the streams.
        record_drops: Keep a :class:`Drop` for every message that leaves without a set
            (:meth:`take_drops`), for tools that report them one by one; off in the node.

    Attributes:
        dropped: Messages evicted without being part of a set.
        matched: Sets emitted.
        jumps: Times the stamps jumped back and the synchroniser started over.

    Raises:
        ConfigError: Empty, repeated or unhashable keys, or one string as ``keys``;
            ``queue_size`` < 1, ``tolerance_ns`` < 0 or ``min_jump_ns`` < 1 (integers, numpy
            ones included); ``approximate`` or ``record_drops`` not a bool.

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
        if isinstance(keys, (str, bytes)):
            # tuple('left') would make four streams named 'l', 'e', 'f' and 't'.
            raise ConfigError(
                f'keys must be a sequence of stream names, not one string; got {keys!r}'
            )
        try:
            keys = tuple(keys)
            distinct = set(keys)
        except TypeError:
            # None, a number, or a name that cannot be a dict key (a list): a TypeError deep
            # inside the constructor otherwise.
            raise ConfigError(
                f'keys must be a sequence of hashable stream names; got {keys!r}'
            ) from None
        if not keys:
            raise ConfigError('keys must name at least one stream; got an empty sequence')
        if len(distinct) != len(keys):
            raise ConfigError(f'keys must be distinct; got {keys}')
        if not is_int(queue_size) or queue_size < 1:
            raise ConfigError(f'queue_size must be an integer >= 1; got {queue_size!r}')
        if not is_int(tolerance_ns) or tolerance_ns < 0:
            raise ConfigError(f'tolerance_ns must be an integer >= 0; got {tolerance_ns!r}')
        if not is_int(min_jump_ns) or min_jump_ns < 1:
            raise ConfigError(f'min_jump_ns must be an integer >= 1; got {min_jump_ns!r}')
        # bool('false') is True: a flag given as a string would silently switch the policy on.
        for name, flag in (('approximate', approximate), ('record_drops', record_drops)):
            if not isinstance(flag, (bool, np.bool_)):
                raise ConfigError(f'{name} must be True or False; got {flag!r}')
        self.keys = keys
        self.min_jump_ns = int(min_jump_ns)
        self.queue_size = int(queue_size)
        self.approximate = bool(approximate)
        self.tolerance_ns = int(tolerance_ns) if self.approximate else 0
        self.dropped = 0
        self.matched = 0
        self.jumps = 0
        self._queues: dict[Hashable, list[tuple[int, Any]]] = {key: [] for key in keys}
        # Messages at or before the last emitted stamp of their key: late stragglers, or the
        # first messages after a jump back in time (see the module docstring).
        self._stale: dict[Hashable, list[_Held]] = {key: [] for key in keys}
        # The first whole set of them less than a jump back, until a second one (a jump) or a
        # newer message (it was a late frame) comes.
        self._behind: _Behind | None = None
        self._seq = 0
        self._last: dict[Hashable, int | None] = {key: None for key in keys}
        self._last_set_ns: int | None = None
        self._lock = threading.Lock()
        self.record_drops = bool(record_drops)
        self._drops: list[Drop] = []

    def _drop(self, key: Hashable, stamp_ns: int, kind: str) -> Drop:
        """The record of ``key``'s message at ``stamp_ns`` leaving for ``kind``, with the stamps
        the other keys hold now."""
        others = {}
        for other in self.keys:
            if other == key:
                continue
            held = [s for s, _ in self._queues[other]] + [h.stamp_ns for h in self._stale[other]]
            last = self._last[other]
            others[other] = tuple(sorted(held + ([last] if last is not None else [])))
        return Drop(key, int(stamp_ns), kind, others)

    def _note(self, key: Hashable, stamps: Sequence[int], kind: str) -> None:
        """Record ``stamps`` of ``key`` as dropped for ``kind`` (before the queues change)."""
        if self.record_drops:
            self._drops.extend(self._drop(key, stamp, kind) for stamp in stamps)

    def _release(self, held: Sequence[_Held]) -> None:
        """Record held-aside messages let go (counted as dropped when they came), in the order
        they came."""
        if self.record_drops:
            for entry in sorted(held, key=lambda entry: entry.seq):
                if entry.drop is not None:
                    self._drops.append(entry.drop)

    def take_drops(self) -> list[Drop]:
        """The drops recorded since the last call, oldest first (``record_drops=True``)."""
        with self._lock:
            drops, self._drops = self._drops, []
            return drops

    def drain(self) -> None:
        """End of input: drop everything still waiting (counted, and recorded as
        ``unmatched``, or ``late``/``repeat`` for messages kept aside as a possible jump
        back)."""
        with self._lock:
            self._drain()

    def _drain(self) -> None:
        for key in self.keys:
            self._note(key, [s for s, _ in self._queues[key]], 'unmatched')
        held = [entry for key in self.keys for entry in self._stale[key]]
        if self._behind is not None:
            held += self._behind.entries
        self._release(held)
        for key in self.keys:
            self.dropped += len(self._queues[key])  # held-aside ones counted already
            self._queues[key] = []
            self._stale[key] = []
        self._behind = None

    def add(self, key: Hashable, stamp_ns: int, msg: Any) -> list[MatchedSet]:
        """Offer one message; return the sets it completes.

        Args:
            key: One of :attr:`keys`.
            stamp_ns: The message's stamp in integer nanoseconds.
            msg: Any object; handed back untouched inside a :class:`MatchedSet`.

        Returns:
            The completed sets, oldest first: none or one, or two when a shorter jump back
            is recognised by its second set. The first set after a jump back (older than the
            one before it) has :attr:`MatchedSet.jumped_from_ns` set.

        Raises:
            ConfigError: ``key`` is not one of :attr:`keys`.
            InputError: ``stamp_ns`` is not an integer (Python or numpy).
        """
        try:
            known = key in self._queues
        except TypeError:  # an unhashable key (a list) cannot be one of the keys
            known = False
        if not known:
            raise ConfigError(f'unknown key {key!r}; expected one of {self.keys}')
        if not is_int(stamp_ns):
            raise InputError(
                f'stamp_ns must be an integer number of nanoseconds; got {stamp_ns!r}'
            )
        # Kept as a Python int: the stamps handed back are plain ints whatever came in.
        stamp_ns = int(stamp_ns)
        with self._lock:
            last = self._last[key]
            if last is not None and stamp_ns <= last:
                self.dropped += 1
                return self._hold(key, stamp_ns, msg, last)
            # A newer message: the streams go on, so what lay only a little back was late, and
            # so was all that this key holds aside (a stream is time ordered).
            self._release_near(key)
            queue = self._queues[key]
            if not self._insert(key, queue, stamp_ns, msg):
                return []
            stamps = {other: [s for s, _ in self._queues[other]] for other in self.keys}
            chosen = self._best_set(stamps, key, stamp_ns)
            if chosen is None:
                return []
            return [self._emit(chosen)]

    def _insert(
        self, key: Hashable, queue: list[tuple[int, Any]], stamp_ns: int, msg: Any
    ) -> bool:
        """Put a message into a queue (sorted, bounded); False if it did not stay there."""
        for index, (stamp, _) in enumerate(queue):
            if stamp == stamp_ns:
                # A repeated stamp on one stream: the newer message is kept (after a bag loop
                # or a restart the one waiting is of the pass before, and must not pair with
                # the partners of this one).
                self._note(key, [stamp_ns], 'duplicate')
                queue[index] = (stamp_ns, msg)
                self.dropped += 1
                return True
        queue.append((stamp_ns, msg))
        queue.sort(key=lambda entry: entry[0])
        if len(queue) > self.queue_size:
            self._note(key, [queue[0][0]], 'overflow')
            queue.pop(0)
            self.dropped += 1
        return any(entry[0] == stamp_ns for entry in queue)

    def _hold(self, key: Hashable, stamp_ns: int, msg: Any, last: int) -> list[MatchedSet]:
        """Keep a message at or before the last set of its key aside; start over if the held
        messages show that the streams jumped back.

        The message has already been counted as dropped, and so has everything held aside: what
        a jump brings back is taken off :attr:`dropped` again.
        """
        near = last - stamp_ns < self.min_jump_ns
        kind = 'repeat' if stamp_ns == last else 'late'
        self._seq += 1
        entry = _Held(
            stamp_ns,
            msg,
            self._seq,
            near,
            self._drop(key, stamp_ns, kind) if self.record_drops else None,
        )
        held = [h for h in self._stale[key] if h.stamp_ns != stamp_ns]
        # One of the same stamp came before (a pass before a loop): the newer one is kept.
        self._release([h for h in self._stale[key] if h.stamp_ns == stamp_ns])
        held.append(entry)
        held.sort(key=lambda h: h.stamp_ns)
        if len(held) > self.queue_size:
            self._release([held.pop(0)])
        self._stale[key] = held
        if not any(h is entry for h in held):
            return []
        stamps = {other: [h.stamp_ns for h in self._stale[other]] for other in self.keys}
        chosen = self._best_set(stamps, key, stamp_ns)
        if chosen is None:
            return []
        if not near:
            # A whole set a jump or more older than the last one: the streams went back in
            # time, not astray.
            return self._start_over(chosen)
        if self._behind is None:
            # A whole set a little older than the last one: a frame delivered late, or the
            # first after a shorter jump back; a second one before any newer message tells.
            self._behind = self._take_held(chosen)
            return []
        return self._start_over(chosen, first=self._behind)

    def _take_held(self, chosen: dict[Hashable, int]) -> _Behind:
        """Take the held-aside messages of the set ``chosen`` out of :attr:`_stale`."""
        items: dict[Hashable, Any] = {}
        entries: list[_Held] = []
        for key in self.keys:
            (entry,) = [h for h in self._stale[key] if h.stamp_ns == chosen[key]]
            self._stale[key] = [h for h in self._stale[key] if h is not entry]
            items[key] = entry.msg
            entries.append(entry)
        return _Behind(dict(chosen), items, entries)

    def _release_near(self, newer: Hashable) -> None:
        """A message of ``newer`` later than the last set of its key came, so the streams go on:
        the held messages only a little older were late, and are let go, as are all of
        ``newer``'s (its stream went on past them: stragglers, which would otherwise pair with
        the next pass after a loop). Those of other keys a jump or more back stay (the first
        messages after a jump may cross the last ones from before it)."""
        let_go: list[_Held] = []
        if self._behind is not None:
            let_go += self._behind.entries
            self._behind = None
        for key in self.keys:
            held = self._stale[key]
            gone = [entry for entry in held if key == newer or entry.near]
            if gone:
                let_go += gone
                self._stale[key] = [entry for entry in held if not (key == newer or entry.near)]
        self._release(let_go)

    def _start_over(
        self, chosen: dict[Hashable, int], first: _Behind | None = None
    ) -> list[MatchedSet]:
        """The streams jumped back: pair from the held-aside messages on, emitting the set
        ``chosen`` among them (after ``first``, a set taken aside before, when that is older
        on every key)."""
        jumped_from = self._last_set_ns
        self.jumps += 1
        stragglers: list[_Held] = []
        for key in self.keys:
            starts = [h.seq for h in self._stale[key] if h.stamp_ns == chosen[key]]
            if not starts:
                continue
            # Newer than the set, yet come before it on its key: of the pass before (a stream
            # is time ordered), never to pair with the new pass.
            gone = [
                h for h in self._stale[key] if h.stamp_ns > chosen[key] and h.seq < min(starts)
            ]
            stragglers += gone
            self._stale[key] = [h for h in self._stale[key] if not any(h is g for g in gone)]
        self._release(stragglers)
        for other in self.keys:
            self._note(other, [s for s, _ in self._queues[other]], 'jump')
        self.dropped += sum(len(queue) for queue in self._queues.values())
        self.dropped -= sum(len(held) for held in self._stale.values())
        self._queues = {
            key: [(entry.stamp_ns, entry.msg) for entry in self._stale[key]] for key in self.keys
        }
        self._stale = {key: [] for key in self.keys}
        self._last = dict.fromkeys(self.keys)
        behind, self._behind = self._behind, None
        sets: list[MatchedSet] = []
        if first is not None and all(first.stamps_ns[k] < chosen[k] for k in self.keys):
            self.dropped -= len(first.entries)
            sets.append(self._matched(first.stamps_ns, first.items))
        elif behind is not None:
            # A late frame after all, or the same stamps again (a bag of one frame on a loop):
            # the newer set is the one of the new pass.
            self._release(behind.entries)
        sets.append(self._emit(chosen))
        sets[0] = replace(sets[0], jumped_from_ns=jumped_from)
        return sets

    def _best_set(
        self, waiting: dict[Hashable, list[int]], key: Hashable, stamp_ns: int
    ) -> dict[Hashable, int] | None:
        """The tightest set among ``waiting`` (key → stamps waiting) that holds the new message,
        as key → stamp, or None."""
        tol = self.tolerance_ns
        # Only the new message can complete a set: before it came none was complete.
        candidates = {
            other: [s for s in waiting[other] if abs(s - stamp_ns) <= tol]
            for other in self.keys
            if other != key
        }
        if any(not stamps for stamps in candidates.values()):
            return None
        # Any valid set fits in a window [low, low + tol] that holds stamp_ns and starts at
        # one of the set's stamps, so trying every such start finds them all. Given its
        # start, the tightest set takes the earliest stamp of every key in the window (the
        # one nearest the new stamp may lie further from the other keys' stamps).
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
                chosen[other] = min(inside)
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
        return self._matched(chosen, items)

    def _matched(self, chosen: dict[Hashable, int], items: dict[Hashable, Any]) -> MatchedSet:
        """Count and return the set of ``items`` at the stamps ``chosen``."""
        self.matched += 1
        ordered = {key: chosen[key] for key in self.keys}
        self._last_set_ns = ordered[self.keys[0]]
        return MatchedSet(
            stamp_ns=ordered[self.keys[0]],
            items={key: items[key] for key in self.keys},
            stamps_ns=ordered,
        )

    def pending(self) -> dict[Hashable, int]:
        """Number of messages waiting per key."""
        with self._lock:
            return {key: len(queue) for key, queue in self._queues.items()}

    def reset(self) -> None:
        """Forget every waiting message and the last emitted stamps. The messages let go are
        counted in :attr:`dropped` and recorded as :meth:`drain` does (they were forgotten
        uncounted, so that received ≠ matched + dropped); the counters are kept."""
        with self._lock:
            self._drain()
            for key in self.keys:
                self._last[key] = None
            self._last_set_ns = None

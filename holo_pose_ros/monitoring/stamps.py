"""Matching by stamp: a buffer of time-stamped items that answers "the item nearest this stamp, within a
tolerance", and a matcher that pairs each estimate (stamped with its image) with the reported state nearest that
stamp. Stamps are integer nanoseconds (header stamps); waiting times are seconds of the caller's clock (`now`,
e.g. time.monotonic()), so the logic is testable without a clock of its own."""

from __future__ import annotations

import bisect
from collections import deque
from dataclasses import dataclass
from typing import Any

NS = 1_000_000_000


class StampBuffer:
    """Items kept by stamp for `history_s` behind the newest stamp (at most `max_items`, the oldest dropped first).

    A stamp more than `history_s` older than the newest is taken as the stream starting over (a replayed bag
    looping, a simulation reset): the buffer is emptied and restarts from it (`resets` counts these)."""

    def __init__(self, history_s: float, max_items: int = 10_000):
        if history_s <= 0 or max_items < 1:
            raise ValueError("history_s must be > 0 and max_items >= 1")
        self.history_ns = int(history_s * NS)
        self.max_items = int(max_items)
        self._stamps: list[int] = []
        self._items: list[Any] = []
        self.resets = 0

    def __len__(self) -> int:
        return len(self._stamps)

    @property
    def newest_ns(self) -> int | None:
        return self._stamps[-1] if self._stamps else None

    def add(self, stamp_ns: int, item: Any) -> None:
        stamp_ns = int(stamp_ns)
        newest = self.newest_ns
        if newest is not None and stamp_ns < newest - self.history_ns:
            self.clear()
            self.resets += 1
        i = bisect.bisect_right(self._stamps, stamp_ns)
        self._stamps.insert(i, stamp_ns)
        self._items.insert(i, item)
        cut = bisect.bisect_left(self._stamps, self._stamps[-1] - self.history_ns)
        cut = max(cut, len(self._stamps) - self.max_items)
        if cut > 0:
            del self._stamps[:cut], self._items[:cut]

    def nearest(self, stamp_ns: int, tolerance_ns: int) -> tuple[int, Any] | None:
        """(stamp, item) of the item whose stamp is nearest `stamp_ns` (the earlier one on a tie), or None when
        none is within `tolerance_ns`."""
        i = bisect.bisect_left(self._stamps, int(stamp_ns))
        best = None
        for j in (i - 1, i):
            if 0 <= j < len(self._stamps):
                gap = abs(self._stamps[j] - stamp_ns)
                if gap <= tolerance_ns and (best is None or gap < abs(self._stamps[best] - stamp_ns)):
                    best = j
        return None if best is None else (self._stamps[best], self._items[best])

    def clear(self) -> None:
        self._stamps.clear()
        self._items.clear()


@dataclass(frozen=True)
class Match:
    """An estimate and the reported state nearest its stamp: `reported` is None (and `offset_ns` too) when no
    reported state was within the tolerance. offset_ns = reported stamp - estimate stamp."""

    stamp_ns: int
    estimate: Any
    reported: Any = None
    offset_ns: int | None = None

    @property
    def matched(self) -> bool:
        return self.reported is not None


class StampMatcher:
    """Pairs each estimate with the reported state nearest its stamp within `tolerance_s`.

    Estimates usually arrive after the reported states of their image's time (inference takes time), but not
    always: an estimate waits until a reported state stamped at or after its own has arrived (with increasing
    reported stamps, no nearer one can come later), or until it has waited `wait_s`; then it is resolved, matched
    or not. At most `max_pending` estimates wait; older ones are resolved early (`dropped` counts them)."""

    def __init__(self, tolerance_s: float, wait_s: float, history_s: float, max_pending: int = 100,
                 max_reported: int = 10_000):
        if tolerance_s < 0 or wait_s < 0:
            raise ValueError("tolerance_s and wait_s must be >= 0")
        self.tolerance_ns = int(tolerance_s * NS)
        self.wait_s = float(wait_s)
        self.max_pending = int(max_pending)
        self.reported = StampBuffer(history_s, max_reported)
        self._pending: deque[tuple[int, Any, float]] = deque()  # (stamp, estimate, arrival time)
        self.dropped = 0

    def add_reported(self, stamp_ns: int, item: Any, now: float) -> list[Match]:
        self.reported.add(stamp_ns, item)
        return self.poll(now)

    def add_estimate(self, stamp_ns: int, item: Any, now: float) -> list[Match]:
        self._pending.append((int(stamp_ns), item, now))
        early = []
        while len(self._pending) > self.max_pending:
            self.dropped += 1
            early.append(self._resolve(self._pending.popleft()))
        return early + self.poll(now)

    def poll(self, now: float) -> list[Match]:
        """Resolve every waiting estimate that is settled or has waited `wait_s`, in arrival order."""
        newest = self.reported.newest_ns
        done, waiting = [], deque()
        for entry in self._pending:
            stamp, _, arrived = entry
            if (newest is not None and newest >= stamp) or now - arrived >= self.wait_s:
                done.append(self._resolve(entry))
            else:
                waiting.append(entry)
        self._pending = waiting
        return done

    def _resolve(self, entry: tuple[int, Any, float]) -> Match:
        stamp, estimate, _ = entry
        found = self.reported.nearest(stamp, self.tolerance_ns)
        if found is None:
            return Match(stamp, estimate)
        return Match(stamp, estimate, found[1], found[0] - stamp)

    @property
    def pending(self) -> int:
        return len(self._pending)

"""Delay and jitter on a data link, sans IO: a user-space netem for the bilateral experiment.

`tc netem` is not available on every machine this runs on (FACTS.md), so
the delay is added where the data link reaches the receiving host: each
packet is due `delay` +/- `jitter` (uniform) after it arrived, and with
`keep_order` never before the one ahead of it (as on a serial line); without
it, packets may overtake, as datagrams on a real network do.  Events never
pass through here: the event link is a link of its own.
"""

from __future__ import annotations

import heapq
import random
from typing import Generic, TypeVar

T = TypeVar("T")


class DelayLine(Generic[T]):
    def __init__(
        self, delay: float = 0.0, jitter: float = 0.0, keep_order: bool = True, seed: int = 0
    ) -> None:
        if delay < 0 or jitter < 0:
            raise ValueError("delay and jitter are >= 0")
        if jitter > delay:
            raise ValueError("the jitter must not exceed the delay")
        self.delay, self.jitter, self.keep_order = delay, jitter, keep_order
        self._rng = random.Random(seed)
        self._heap: list[tuple[float, int, T]] = []
        self._n = 0
        self._last_due = float("-inf")

    def __len__(self) -> int:
        return len(self._heap)

    def put(self, now: float, item: T) -> float:
        """`item` arrived at `now`; returns when it is due."""
        due = now + self.delay + (self._rng.uniform(-self.jitter, self.jitter) if self.jitter else 0.0)
        if self.keep_order:
            due = max(due, self._last_due)
            self._last_due = due
        heapq.heappush(self._heap, (due, self._n, item))
        self._n += 1
        return due

    def take(self, now: float) -> list[T]:
        """Every item due by `now`, in the order they fall due."""
        out = []
        heap = self._heap
        while heap and heap[0][0] <= now:
            out.append(heapq.heappop(heap)[2])
        return out

"""The data-plane clock as the controller sees it, and the round trip to it, measured on every read."""

from __future__ import annotations

import asyncio
import time
from collections import deque
from collections.abc import Sequence

from cell.bus import BusTimeout
from cell.dataplane.client import DataplaneClient
from cell.v1 import dataplane_pb2

RETRY_READ_S = 0.5  # a read of the data plane's state unanswered this long is asked again


class Link:
    """The data-plane clock as seen from here, and the round trip to it, measured on every read."""

    def __init__(self, dp: DataplaneClient) -> None:
        self.dp = dp
        self.offset_ns = 0
        self.realtime_offset_ns: int | None = None  # the cell clock less the data plane's (exact)
        self.boot_id: int | None = None  # the data plane's start (DataplaneState.boot_id)
        self._best_rtt: int | None = None  # the offset comes from the read with the shortest round trip
        self.rtts: deque[int] = deque(maxlen=32)

    async def state(
        self, robot_ids: Sequence[int] = (), timeout: float | None = None
    ) -> dataplane_pb2.DataplaneState:
        """The robots' registers and last status (all robots, or those given), no counters.

        A read, so a request lost on the way (a connection of the data plane's made anew as it
        came back from a hang) is asked again once, within the same timeout."""
        total = timeout or self.dp.timeout or self.dp.bus.config.request_timeout_s
        first = RETRY_READ_S if total >= 2 * RETRY_READ_S else total  # (a short poll is not retried)
        t0 = time.monotonic_ns()
        try:
            st = await self.dp.state(robot_ids, robots_only=True, timeout=first)
        except BusTimeout:
            if first >= total:
                raise
            t0 = time.monotonic_ns()
            st = await self.dp.state(robot_ids, robots_only=True, timeout=total - first)
        t1 = time.monotonic_ns()
        if st.boot_id != self.boot_id:  # a new data plane: its clock may differ, measure afresh
            self._best_rtt = None
            self.boot_id = st.boot_id
        if st.realtime_offset_ns:
            self.realtime_offset_ns = st.realtime_offset_ns
        rtt = t1 - t0
        self.rtts.append(rtt)
        if self._best_rtt is None or rtt <= self._best_rtt * 1.5:
            self._best_rtt = rtt if self._best_rtt is None else min(rtt, self._best_rtt)
            self.offset_ns = st.now_ns - (t0 + t1) // 2
        return st

    def now(self) -> int:
        return time.monotonic_ns() + self.offset_ns

    @property
    def rtt_ns(self) -> int:
        """A pessimistic round trip: the largest of the recent ones."""
        return max(self.rtts) if self.rtts else 50_000_000

    async def sleep_until(self, t_ns: int) -> None:
        delay = (t_ns - self.now()) / 1e9
        if delay > 0:
            await asyncio.sleep(delay)

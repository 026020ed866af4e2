"""The periodic timer: never early, drift-free, and it says how many periods a stall cost."""

from __future__ import annotations

import time

import pytest

from cell.timer import PeriodicTimer

PERIOD = 2_000_000  # ns


@pytest.mark.parametrize("precise", [True, False], ids=["timerfd", "sleep-fallback"])
async def test_ticks_on_absolute_deadlines_and_counts_a_stall(precise: bool) -> None:
    start = time.monotonic_ns() + PERIOD
    timer = PeriodicTimer(start, PERIOD)
    if not precise:
        timer.close()  # no fd: the asyncio.sleep fallback
    assert timer.precise is precise
    try:
        counted = 0
        for _ in range(20):
            counted += await timer.wait()
            now = time.monotonic_ns()
            due = start + (timer.ticks - 1) * PERIOD
            assert now >= due  # never early
        assert counted == timer.ticks >= 20  # every period is accounted for
        assert time.monotonic_ns() - (start + 19 * PERIOD) < 50 * PERIOD  # no drift to speak of
        before = timer.ticks
        time.sleep(5.5 * PERIOD / 1e9)  # noqa: ASYNC251 - blocking on purpose: a stalled loop
        missed = await timer.wait()
        assert missed >= 5
        assert timer.ticks == before + missed
    finally:
        timer.close()

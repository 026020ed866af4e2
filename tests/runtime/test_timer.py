"""The periodic timer: never early, drift-free, and it says how many periods a stall cost."""

from __future__ import annotations

import asyncio
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


async def test_a_timer_nobody_waits_on_costs_no_cpu() -> None:
    """Between periods its owner may await other things (the SnP cycle awaits replies): the timer's
    readable fd must not make the loop spin meanwhile, and the next wait() still counts the periods."""
    timer = PeriodicTimer(time.monotonic_ns() + PERIOD, PERIOD)
    try:
        await timer.wait()
        cpu0 = time.process_time()
        await asyncio.sleep(25 * PERIOD / 1e9)  # 50 ms of other business, 25 expiries unread
        busy = time.process_time() - cpu0
        assert busy < 0.4 * 25 * PERIOD / 1e9, f"{busy * 1e3:.1f} ms of CPU in a 50 ms wait"  # a spin: ~50
        assert await timer.wait() >= 20
    finally:
        timer.close()

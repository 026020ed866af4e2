"""How much of the event loop each service uses: `busy_ms_per_s` for every service in `cell status`.

Services share a process (and in the "single" layout, one event loop), so
the process's CPU time does not say which of them is expensive.  Every task a
service starts, directly or through its children, its bus node or its
TaskGroups, runs in a context whose `ACCOUNT` is that service's; a task
factory wraps each task's coroutine so that every step the task takes adds
its wall time to the account of the context it runs in.  A step is the time
between two awaits, so this is exactly the time the service held the loop:
what delays everything else in the process.  The cost is two clock reads and
a Python call per step (about 0.5 us).  Work outside tasks (plain callbacks,
other threads such as Rerun's encoders or ZeroMQ's I/O thread) is not
attributed; the process's CPU time beside it shows how much that is.
"""

from __future__ import annotations

import asyncio
import collections.abc
import contextvars
import threading
import time
from collections.abc import Coroutine
from typing import Any

from cell import sched


class Account:
    """Loop time used by one service, ns; and its longest single step (a coroutine running without
    giving the loop back) and whose it was: what holds a real-time loop's next tick up."""

    __slots__ = ("busy_ns", "longest_in", "longest_ns", "name")

    def __init__(self, name: str) -> None:
        self.name = name
        self.busy_ns = 0
        self.longest_ns = 0
        self.longest_in = ""

    def take_longest(self) -> tuple[float, str]:
        """(ms, coroutine) of the longest step since the last call; then starts over."""
        out = (self.longest_ns / 1e6, self.longest_in)
        self.longest_ns, self.longest_in = 0, ""
        return out


ACCOUNT: contextvars.ContextVar[Account | None] = contextvars.ContextVar("cell_account", default=None)
_now = time.perf_counter_ns
# a real-time process's watch on the kernel holding its loop back (RT throttling), checked as a task
# steps: the first step after a wake sees it (sched.Held; made by install() where the process is
# real-time)
HELD: sched.Held | sched.HeldThreads | None = None


class _Metered(collections.abc.Coroutine):
    """A coroutine that charges each of its steps to the account current in the task's context."""

    __slots__ = ("_coro",)

    def __init__(self, coro: Coroutine[Any, Any, Any]) -> None:
        self._coro = coro

    def send(self, value: Any) -> Any:
        t0 = _now()
        if HELD is not None and t0 >= HELD.next_ns:
            HELD.check(t0)
        try:
            return self._coro.send(value)
        finally:
            _charge(t0, self._coro)

    def throw(self, *exc: Any) -> Any:
        t0 = _now()
        try:
            return self._coro.throw(*exc)
        finally:
            _charge(t0, self._coro)

    def close(self) -> None:
        self._coro.close()

    def __next__(self) -> Any:
        return self.send(None)

    def __iter__(self) -> _Metered:
        return self

    def __await__(self) -> _Metered:
        return self

    # what asyncio's task repr and get_stack() read from a coroutine
    def __getattr__(self, name: str) -> Any:
        if name in ("cr_frame", "cr_running", "cr_await", "cr_code", "__name__"):
            return getattr(self._coro, name)
        raise AttributeError(name)


def _charge(t0: int, coro: Any) -> None:
    account = ACCOUNT.get()
    if account is not None:
        took = _now() - t0
        account.busy_ns += took
        if took > account.longest_ns:
            account.longest_ns = took
            account.longest_in = getattr(getattr(coro, "cr_code", None), "co_qualname", "?")


def install(loop: asyncio.AbstractEventLoop) -> None:
    """Meter every task created on `loop` from now on (once per loop; other factories are kept); in a
    real-time process, also watch for the kernel holding the loop back (HELD)."""
    global HELD
    if HELD is None and sched.realtime():
        HELD = sched.Held()
    previous = loop.get_task_factory()
    if getattr(previous, "_cell_meter", False):
        return

    def factory(loop: asyncio.AbstractEventLoop, coro: Any, **kwargs: Any) -> asyncio.Future[Any]:
        if isinstance(coro, collections.abc.Coroutine) and not isinstance(coro, _Metered):
            coro = _Metered(coro)
        if previous is not None:
            return previous(loop, coro, **kwargs)
        return asyncio.Task(coro, loop=loop, **kwargs)

    factory._cell_meter = True  # type: ignore[attr-defined]  # a mark on the function: installed already
    loop.set_task_factory(factory)


def watch_thread(tid: int) -> None:
    """From now on HELD watches thread `tid` too (a native loop that kept the process's real-time
    priority, sched.hand_over; the first one replaces this thread's watch), still checked as this
    thread's tasks step."""
    global HELD
    if not isinstance(HELD, sched.HeldThreads):
        HELD = sched.HeldThreads()
    HELD.add(tid)


def real_time_loop(priority: int) -> list[str]:
    """From now on this process's Python runs at SCHED_FIFO `priority` (sched.rest_at: a loop that
    must be real-time in Python), this thread watched for holds; what could not be done, in words."""
    problems = sched.rest_at(priority)
    if sched.realtime():
        watch_thread(threading.get_native_id())
    return problems


def charge_to(account: Account) -> None:
    """From now on, the current task and every task it starts charge their steps to `account`."""
    ACCOUNT.set(account)


class Rate:
    """A counter's rate per second over windows of at least `window_s` (heartbeats come unevenly)."""

    def __init__(self, window_s: float) -> None:
        self.window_s = window_s
        self._last: tuple[float, float] | None = None
        self.value: float | None = None

    def update(self, total: float, now: float | None = None) -> float | None:
        now = time.monotonic() if now is None else now
        if self._last is None:
            self._last = (now, total)
        elif now - self._last[0] >= self.window_s:
            t0, v0 = self._last
            self.value = (total - v0) / (now - t0)
            self._last = (now, total)
        return self.value

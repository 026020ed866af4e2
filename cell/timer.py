"""A drift-free periodic timer for the event loop: Linux timerfd, with an asyncio fallback.

uvloop's timers have millisecond resolution, too coarse for 2 ms periods; a
timerfd armed with absolute CLOCK_MONOTONIC deadlines wakes epoll on time (to
tens of microseconds), never accumulates error, and its read says how many
periods have elapsed, so a late tick knows exactly how much it missed.
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import ctypes.util
import functools
import os
import time

CLOCK_MONOTONIC = 1
TFD_NONBLOCK = 0o4000
TFD_CLOEXEC = 0o2000000
TFD_TIMER_ABSTIME = 1


class _Timespec(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]


class _Itimerspec(ctypes.Structure):
    _fields_ = [("it_interval", _Timespec), ("it_value", _Timespec)]


def _libc() -> ctypes.CDLL | None:
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    libc = ctypes.CDLL(name, use_errno=True)
    return libc if hasattr(libc, "timerfd_create") else None


_LIBC = _libc()


def _ts(ns: int) -> _Timespec:
    return _Timespec(ns // 1_000_000_000, ns % 1_000_000_000)


class PeriodicTimer:
    """Ticks every `period_ns` from `start_ns` (CLOCK_MONOTONIC, i.e. time.monotonic_ns())."""

    def __init__(self, start_ns: int, period_ns: int) -> None:
        self.start_ns = start_ns
        self.period_ns = period_ns
        self.ticks = 0  # periods elapsed so far, by the timer's count
        self._fd = -1
        self._waiter: asyncio.Future[int] | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        if _LIBC is not None:
            fd = _LIBC.timerfd_create(CLOCK_MONOTONIC, TFD_NONBLOCK | TFD_CLOEXEC)
            if fd >= 0:
                spec = _Itimerspec(_ts(period_ns), _ts(start_ns))
                if _LIBC.timerfd_settime(fd, TFD_TIMER_ABSTIME, ctypes.byref(spec), None) == 0:
                    self._fd = fd
                else:
                    os.close(fd)

    @property
    def precise(self) -> bool:
        return self._fd >= 0

    async def wait(self) -> int:
        """Wait for the next deadline; return how many periods elapsed since the last wait (>= 1)."""
        if self._fd < 0:
            return await self._wait_sleep()
        n = self._read()
        if n:
            return n
        loop = asyncio.get_running_loop()
        if self._loop is not loop:  # registered while someone waits each period: no epoll_ctl pair
            self._loop = loop
            loop.add_reader(self._fd, self._ready)
        self._waiter = loop.create_future()
        try:
            return await self._waiter
        finally:
            self._waiter = None

    def _ready(self) -> None:
        fut = self._waiter
        if fut is None or fut.done():
            # nobody waits (the owner awaits something else between periods): the fd stays readable,
            # and a level-triggered reader would run on every turn of the loop; the next wait() re-adds it
            if self._loop is not None:
                self._loop.remove_reader(self._fd)
                self._loop = None
            return
        if got := self._read():
            fut.set_result(got)

    def _read(self) -> int:
        try:
            n = int.from_bytes(os.read(self._fd, 8), "little")
        except BlockingIOError:
            return 0
        self.ticks += n
        return n

    async def _wait_sleep(self) -> int:
        due = self.start_ns + self.ticks * self.period_ns  # the next expiration
        now = time.monotonic_ns()
        if now < due:
            await asyncio.sleep((due - now) / 1e9)
            now = time.monotonic_ns()
        n = max(1, (now - self.start_ns) // self.period_ns + 1 - self.ticks)
        self.ticks += n
        return n

    def close(self) -> None:
        if self._fd >= 0:
            if self._loop is not None and not self._loop.is_closed():
                self._loop.remove_reader(self._fd)
            os.close(self._fd)
            self._fd = -1


class Alarm:
    """A one-shot timerfd on CLOCK_MONOTONIC for blocking epoll loops (Python's epoll waits in
    whole milliseconds): set(ns) arms it for an absolute time, its fd turns readable then."""

    def __init__(self) -> None:
        if _LIBC is None:
            raise OSError("timerfd is not available here")
        self._libc = _LIBC
        self.fd = self._libc.timerfd_create(CLOCK_MONOTONIC, TFD_NONBLOCK | TFD_CLOEXEC)
        if self.fd < 0:
            raise OSError(ctypes.get_errno(), "timerfd_create")

    def set(self, at_ns: int) -> None:
        spec = _Itimerspec(_ts(0), _ts(max(1, at_ns)))
        if self._libc.timerfd_settime(self.fd, TFD_TIMER_ABSTIME, ctypes.byref(spec), None) != 0:
            raise OSError(ctypes.get_errno(), "timerfd_settime")

    def clear(self) -> None:
        """Take the expiry (the fd is readable until then)."""
        with contextlib.suppress(BlockingIOError):
            os.read(self.fd, 8)

    def close(self) -> None:
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1


@functools.cache
def realtime_offset() -> int:
    """CLOCK_REALTIME - CLOCK_MONOTONIC (ns), for taking the kernel's datagram stamps (realtime) to
    the monotonic clock; read once per process, as the narrowest of 50 bracketed reads.

    One read (time_ns() - monotonic_ns()) is off by whatever passed between its two calls: 2 us
    for a first call here, more if preempted.  Every stamp it converts carries that error, and two
    offsets read apart (a process's receive and send stamps, or two processes') differ by it: a
    steady error in any clock servoed across them.  Cached, so that all of a process's conversions
    agree; a step of the system clock (settimeofday) after the first call is not seen."""
    best_gap, offset = None, 0
    for _ in range(50):
        before = time.monotonic_ns()
        real = time.time_ns()
        after = time.monotonic_ns()
        if best_gap is None or after - before < best_gap:
            best_gap, offset = after - before, real - (before + after) // 2
    return offset

"""The real-time budget of a process's Python (cell/rt_budget.c, built on first use).

Where Python must run at SCHED_FIFO (sched.rest_at: a UR daemon's group ticking in Python, a data
plane's control plane), more work than its CPU has would make the kernel's RT throttling stop every
real-time thread of that CPU, the native loops of every other arm with it, for up to 50 ms of each
second.  A watcher thread at the native loops' priority keeps that Python to BUDGET_NS of each
WINDOW_NS at its real-time priority, and at the normal policy past that until the window ends: the
overloaded Python degrades alone.  (sched.Spin is the same idea for a loop that checks its own
budget; this one needs no check in the code it budgets: uvloop's callbacks, C extensions.)
"""

from __future__ import annotations

import ctypes
import functools
import os
from pathlib import Path

from cell.native import CFLAGS, NativeUnavailable, build

HERE = Path(__file__).parent
WINDOW_NS = 100_000_000
# 70 % of each window: with the native loops' share (the robots' tick threads and a data plane's
# control plane, 10-20 % on a slow day) the CPU's real-time threads stay under the kernel's 95 %,
# and the Python that needs real time (a UR daemon's e-stop path) loses it only in true overload (at
# 50 % a CI run's daemon spent it in 138 windows of 150 and stood 14 ms past its e-stop bound)
BUDGET_NS = 70_000_000
SHARE = BUDGET_NS / WINDOW_NS  # (of its CPU, at the most, at real-time priority)
# the least time between two looks of the watcher: it looks when the budget could be spent at the
# soonest (and at each window's end), 2-3 times a window for an idle Python
CHECK_NS = 2_000_000
MAX_LOOPS = 32  # rt_budget.c's
_I = ctypes.c_int64


class BudgetState(ctypes.Structure):
    """budget_t of rt_budget.c."""

    _fields_ = [
        *((name, _I) for name in ("priority", "nice", "window_ns", "budget_ns", "check_ns", "cpus")),
        ("loops", _I * MAX_LOOPS),
        *((name, _I) for name in ("n_loops", "stop", "tid", "spent", "normal_ns", "used_max_ns", "looks")),
        ("rt", ctypes.c_void_p),
    ]


@functools.cache
def _lib() -> ctypes.CDLL:
    lib = build("rt_budget", (HERE / "rt_budget.c",), (HERE / "rt_thread.h",), (*CFLAGS, "-pthread"))
    ref = ctypes.POINTER(BudgetState)
    lib.bg_start.argtypes, lib.bg_start.restype = [ref, _I], ctypes.c_int
    lib.bg_stop.argtypes, lib.bg_stop.restype = [ref], None
    return lib


_STATE: BudgetState | None = None


def start(watcher_priority: int, priority: int, nice: int, loops: set[int]) -> list[str]:
    """Budget every thread of this process but `loops` (and those exempt() names later): SCHED_FIFO
    `priority` within the budget, the normal policy at `nice` past it; the watcher at
    `watcher_priority`.  Once per process (later calls change the priority it restores); what could
    not be done, in words."""
    global _STATE
    if _STATE is not None:
        _STATE.priority = priority
        return []
    try:
        lib = _lib()
    except NativeUnavailable as exc:
        return [f"no real-time budget for this process's Python ({exc})"]
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    st = BudgetState(
        priority=priority, nice=nice, window_ns=WINDOW_NS, budget_ns=BUDGET_NS, check_ns=CHECK_NS, cpus=cpus
    )
    for tid in loops:
        exempt(tid, st)
    rc = lib.bg_start(ctypes.byref(st), watcher_priority)
    if rc:
        return [f"no real-time budget for this process's Python (its watcher: errno {rc})"]
    _STATE = st
    return []


def exempt(tid: int, st: BudgetState | None = None) -> None:
    """Thread `tid` (a native loop) is not budgeted: never moved, its CPU time not counted."""
    st = st or _STATE
    if st is None or tid in st.loops[: st.n_loops] or st.n_loops >= MAX_LOOPS:
        return
    st.loops[st.n_loops] = tid
    st.n_loops += 1  # (after the id: the watcher reads n_loops first)


def watcher() -> int:
    """The watcher's thread id (0: none runs): no other code may move it."""
    return int(_STATE.tid) if _STATE is not None else 0


def counters(prefix: str) -> dict[str, float]:
    """How often the budget was spent and how long the budgeted threads ran at the normal policy for
    it ({} where no budget runs)."""
    st = _STATE
    if st is None:
        return {}
    return {
        f"{prefix}budget_spent": float(st.spent),
        f"{prefix}budget_normal_ms": st.normal_ns / 1e6,
        f"{prefix}budget_used_max_ms": st.used_max_ns / 1e6,
        f"{prefix}budget_looks": float(st.looks),
    }


def stop() -> None:
    global _STATE
    if _STATE is not None:
        _lib().bg_stop(ctypes.byref(_STATE))
        _STATE = None

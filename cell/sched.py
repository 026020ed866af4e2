"""A process's place on the machine: pinned to CPUs, at a real-time priority where the OS allows it.

SCHED_FIFO makes the kernel run a process the moment it becomes runnable
(its timer fires, a datagram arrives), ahead of every normal process, which
is what a 2 ms robot tick needs on a loaded machine; CFS alone lets a busy
neighbour hold the core for a time slice of several milliseconds.  Where
SCHED_FIFO is refused (no CAP_SYS_NICE, an RLIMIT_RTPRIO of 0, a cgroup with
no real-time budget) the process falls back to a nice value, and where that
is refused too it runs as it is: what it got is reported, never hidden.
Everything is applied to every thread the process has, and threads started
later (ZeroMQ's I/O thread) inherit it.
"""

from __future__ import annotations

import gc
import os

_POLICY = {
    getattr(os, "SCHED_OTHER", 0): "normal",
    getattr(os, "SCHED_FIFO", 1): "fifo",
    getattr(os, "SCHED_RR", 2): "rr",
    getattr(os, "SCHED_BATCH", 3): "batch",
    getattr(os, "SCHED_IDLE", 5): "idle",
}


def _threads() -> list[int]:
    try:
        return [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        return [0]


def place(cpus: list[int], rt_priority: int, nice: int) -> list[str]:
    """Pin this process to `cpus` ([] = leave as is) and make it SCHED_FIFO `rt_priority` (0 = leave
    the policy as is) or, failing that, nice `nice`; return what could not be done, in words."""
    problems: list[str] = []
    if cpus and hasattr(os, "sched_setaffinity"):
        # the machine's CPUs, not the ones this process inherited: a parent's narrower mask is no limit
        online = set(range(os.cpu_count() or 1))
        use = set(cpus) & online
        if not use:
            problems.append(f"CPUs {cpus} are not among this machine's {sorted(online)}: not pinned")
        else:
            if use != set(cpus):
                problems.append(
                    f"CPUs {sorted(set(cpus) - online)} do not exist here: pinned to {sorted(use)}"
                )
            try:
                for tid in _threads():
                    os.sched_setaffinity(tid, use)
            except OSError as exc:  # e.g. outside the cgroup's cpuset
                problems.append(f"CPUs {sorted(use)} refused ({exc.strerror}): not pinned")
    if rt_priority and hasattr(os, "sched_setscheduler"):
        try:
            for tid in _threads():
                os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(rt_priority))
            return problems
        except OSError as exc:
            problems.append(f"SCHED_FIFO {rt_priority} refused ({exc.strerror}): nice {nice} instead")
    if nice:
        try:
            for tid in _threads():
                os.setpriority(os.PRIO_PROCESS, tid, nice)
        except OSError as exc:
            problems.append(f"nice {nice} refused ({exc.strerror}): normal priority")
    return problems


def describe() -> str:
    """How the OS schedules this process now: 'fifo 70, cpu 1', 'nice -5, cpus 0-1', 'normal, cpus 0-1'."""
    if not hasattr(os, "sched_getscheduler"):
        return "unknown"
    policy = os.sched_getscheduler(0) & 0xFF  # without SCHED_RESET_ON_FORK
    name = _POLICY.get(policy, f"policy {policy}")
    if name in ("fifo", "rr"):
        what = f"{name} {os.sched_getparam(0).sched_priority}"
    else:
        niceness = os.getpriority(os.PRIO_PROCESS, 0)
        what = f"nice {niceness}" if niceness else name
    cpus = sorted(os.sched_getaffinity(0))
    return f"{what}, {'cpu' if len(cpus) == 1 else 'cpus'} {_ranges(cpus)}"


def _ranges(cpus: list[int]) -> str:
    out: list[str] = []
    for c in cpus:
        if out and out[-1].split("-")[-1] == str(c - 1):
            out[-1] = f"{out[-1].split('-')[0]}-{c}"
        else:
            out.append(str(c))
    return ",".join(out)


def cpu_seconds() -> float:
    """CPU time this process has used so far, all its threads, user and system."""
    t = os.times()
    return t.user + t.system


def settle_heap() -> None:
    """Collect what start-up left and move the rest out of the garbage collector's sight.

    A full (generation 2) pass walks every object the process holds: with numpy and the cell's
    modules loaded that is 5-13 ms on this machine kind, ten 1 ms cycles lost at once, every few
    seconds, in a loop that allocates a little per cycle.  Frozen, start-up's objects are never
    walked again and a pass costs what the loop itself made since.  Call it once, in a process of
    its own, after setting up and before the real-time loop (it freezes the whole process)."""
    gc.collect()
    gc.freeze()
